"""Active disambiguation: does acting on the hybrid belief resolve the association sooner?

The aliased map of the paper's Sec. V (six objects of one class in two rows, orientations
differ) and a highly uncertain start. The viewpoint dependence is weak (``alpha`` = 0.1 by
default) so that where the robot looks from matters. Three policies move the robot for ``steps``
steps from the same start, over the same seeds:

- ``straight``: 1 m forward every step;
- ``random``: 1 m forward, a uniform random turn in [-0.6, 0.6] rad;
- ``planner``: receding horizon. At every step, score ``candidates`` sequences of ``horizon``
  actions (arcs and random turns, 1 m steps) with :func:`hybridslam.planning.score_candidates`
  (expected association entropy after the predicted belief updates, ``draws`` predicted worlds
  each) and execute the first action of the best;
- ``refined``: the planner's best sequence, then refined by gradient descent on the smooth
  objective (:func:`hybridslam.planning.refine_actions`, smooth visibility at 0.5 m) before its
  first action is executed.

The start heading is drawn uniformly per seed (``--start-heading random``, the default), the same
for every policy, so the straight line is not handed a start that faces the objects; ``--start-heading
paper`` keeps the paper setup's start, which already looks down the aliased rows.

The estimator is the same for all (Algorithm 1, ``laplace-is``, capacity 16). Plots entropy
H(w) and the position error x̃^wmax over time (mean and 95% band over seeds) and prints them.

    python experiments/active_disambiguation.py [-o runs/figures] [--seeds 20] [--steps 8]
"""

from __future__ import annotations

import argparse
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure

import hybridslam as hs
from hybridslam import planning
from hybridslam.analysis.plot import mean_band
from hybridslam.sim.paper import move, observe

hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

POLICIES = ("straight", "random", "planner", "refined")
MAX_TURN = 0.6


@eqx.filter_jit
def _step(estimator: hs.Hybrid, belief: hs.Belief, odometry, detections: hs.Detections, key):
    """One step of Algorithm 1 (compiled once per estimator and belief shape, shared by every episode)."""
    return estimator.step(belief, odometry, detections, key)


def _detections(dets: tuple, slots: int, m: int) -> hs.Detections:
    geo, scores, mask = np.zeros((slots, 2)), np.zeros((slots, m)), np.zeros(slots, bool)
    for i, d in enumerate(dets[:slots]):
        geo[i], scores[i], mask[i] = (d.range, d.bearing), d.scores, True
    return hs.Detections(jnp.asarray(geo), jnp.asarray(scores), jnp.asarray(mask))


def _start(scenario: hs.Scenario, seed: int, start_heading: str) -> hs.Scenario:
    """The seed's scenario with its start heading drawn uniformly (``random``) or as simulated (``paper``)."""
    if start_heading == "paper":
        return scenario
    heading = np.random.default_rng(30_000 + seed).uniform(-np.pi, np.pi)
    poses = np.array(scenario.true_robot_poses)
    poses[0, 2] = heading
    return scenario.replace(true_robot_poses=poses,
                            robot_prior_mean=np.array([*scenario.robot_prior_mean[:2], heading]))


def _plan(policy, belief, k, key, candidates, horizon, draws):
    """The first action of the planned sequence (``planner`` or ``refined``)."""
    plan = planning.prepare(belief, horizon, capacity=8, weights="linearized", gn_max_steps=2)
    cands = planning.arc_candidates(candidates, horizon, max_turn=MAX_TURN, key=jax.random.fold_in(key, 1000 + k))
    scores = planning.score_candidates(plan, cands, jax.random.fold_in(key, 2000 + k), num_draws=draws)
    best = cands[int(jnp.argmin(scores))]
    if policy == "refined":
        smooth = planning.prepare(belief, horizon, capacity=8, weights="linearized", gn_max_steps=2,
                                  visibility_temperature=0.5)
        best = planning.refine_actions(smooth, best[:, 2], jax.random.fold_in(key, 3000 + k), max_turn=MAX_TURN,
                                       num_draws=draws, max_steps=5).actions
    return np.asarray(best[0])


def run_policy(policy: str, seed: int, steps: int, alpha: float, candidates: int, horizon: int,
               draws: int = 4, start_heading: str = "random") -> dict:
    """One episode: returns per-step entropy, error, and planning seconds."""
    scenario = _start(hs.simulate(seed, steps=1, alpha=alpha), seed, start_heading)  # map, truth, priors
    truth_objects = np.asarray(scenario.true_object_poses)
    classifier = hs.make_classifier("mirror", 2, alpha, 15.0)
    estimator = hs.Hybrid(capacity=16, max_steps=steps, max_detections=2)  # laplace-is, the scenario's classifier
    belief = estimator.init(scenario)
    rng = np.random.default_rng(10_000 + seed)  # the world's noise: the same for every policy
    turns = np.random.default_rng(20_000 + seed)  # the random policy's own draws
    pose = np.asarray(scenario.true_robot_poses[0])
    key = jax.random.PRNGKey(seed)
    out = {"entropy": [], "error": [], "plan_s": []}
    for k in range(steps):
        if policy == "straight":
            action = np.array([1.0, 0.0, 0.0])
        elif policy == "random":
            action = np.array([1.0, 0.0, turns.uniform(-MAX_TURN, MAX_TURN)])
        else:
            t0 = time.perf_counter()
            action = _plan(policy, belief, k, key, candidates, horizon, draws)
            out["plan_s"].append(time.perf_counter() - t0)
        pose = move(pose, action, rng)
        dets = observe(rng, pose, truth_objects, classifier)
        belief, _ = _step(estimator, belief, jnp.asarray(action), _detections(dets, 2, 2), jax.random.fold_in(key, k))
        m = hs.metrics(belief, jnp.asarray(pose))
        out["entropy"].append(float(m.entropy))
        out["error"].append(float(m.err_wmax))
    return out


def main(output: str = os.path.join("runs", "figures"), seeds: int = 20, steps: int = 8, alpha: float = 0.1,
         candidates: int = 64, horizon: int = 3, draws: int = 4, start_heading: str = "random") -> str:
    """Run every policy on every seed; plot ``output/active_disambiguation.png``; return the path."""
    results = {p: [] for p in POLICIES}
    for seed in range(seeds):
        for policy in POLICIES:
            results[policy].append(run_policy(policy, seed, steps, alpha, candidates, horizon, draws, start_heading))
        print(f"seed {seed}: final H(w) " + ", ".join(f"{p} {results[p][-1]['entropy'][-1]:.3f}" for p in POLICIES),
              flush=True)

    fig = Figure(figsize=(11, 4.2), layout="constrained")
    axes = fig.subplots(1, 2)
    ks = np.arange(1, steps + 1)
    print(f"\nmean over {seeds} seeds (± 95% half-width), alpha {alpha}, {candidates} candidates x horizon {horizon} "
          f"x {draws} draws, start heading {start_heading}")
    for metric, ax, title in (("entropy", axes[0], "association entropy H(w)"),
                              ("error", axes[1], r"position error $\tilde{x}^{w_{\max}}$ [m]")):
        print(f"{metric}:  k = " + " ".join(f"{k:>13d}" for k in ks))
        for i, policy in enumerate(POLICIES):
            values = np.array([r[metric] for r in results[policy]])
            mean, half = mean_band(values)
            ax.plot(ks, mean, marker="os^D"[i], color=f"C{i}", label=policy)
            ax.fill_between(ks, mean - half, mean + half, color=f"C{i}", alpha=0.15, lw=0)
            print(f"  {policy:<9} " + " ".join(f"{m:>6.3f} ±{h:5.3f}" for m, h in zip(mean, half)))
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("step k")
        ax.grid(True, alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"Active disambiguation on the aliased map: {seeds} seeds, alpha = {alpha}, start heading "
                 f"{start_heading}, mean and 95% band",
                 fontsize=11)
    for policy in ("planner", "refined"):
        plan_s = [s for r in results[policy] for s in r["plan_s"][1:]]  # the first call compiles
        print(f"{policy}: {np.median(plan_s) * 1e3:.0f} ms per planning step (median, after compilation)")
    os.makedirs(output, exist_ok=True)
    path = os.path.join(output, f"active_disambiguation{'' if start_heading == 'random' else '_' + start_heading}.png")
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", default=os.path.join("runs", "figures"))
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--alpha", type=float, default=0.1)
    parser.add_argument("--candidates", type=int, default=64)
    parser.add_argument("--horizon", type=int, default=3)
    parser.add_argument("--draws", type=int, default=4, help="predicted worlds per candidate")
    parser.add_argument("--start-heading", choices=("random", "paper"), default="random")
    a = parser.parse_args()
    main(a.output, a.seeds, a.steps, a.alpha, a.candidates, a.horizon, a.draws, a.start_heading)
