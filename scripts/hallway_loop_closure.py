"""Why the hallway loop does or does not close: association audit and covariance consistency.

Two modes.

**A finished study** (``experiments/hallway_odometry_sweep.py -o FOLDER``): one row per estimator,
from its result files and the scenarios' ground truth (:func:`hybridslam.analysis.consistency.loop_closure_report`):
re-detections of landmarks first seen more than ``--gap`` steps earlier and how many were
associated with the landmark's first object (a loop closure), detections merged into another
landmark's object, objects against landmarks, and, just before the first re-detection, the pose
NEES of the top component, its heading error in reported standard deviations, its reported heading
sd against dead reckoning's, and the Cramér-Rao bound on that sd against dead reckoning's.

**One run, traced** (``--probe EST:TRACE:SEED``, EST one of ml, gpda, max-mixture): for every
re-detection, at the propagated belief of that step, ``d²`` against the landmark's first object
(thesis Eq. 4.14-4.15), ``½ log|S|``, the log density of "it is that object" (geometry plus the
semantic term, Eq. 4.13 / 2.14) against "it is a new object", the robot pose's NEES and its
heading error and sd. ``--exact-detections`` replaces the detections by their true range and
bearing (the odometry stays noisy): then the filter's heading sd meets the Cramér-Rao bound.

**The drift a loop closure must bridge** (``--oracle``): the full smoother with the *true*
associations (:func:`hybridslam.analysis.consistency.oracle_drift`) on the study's scenarios (5
levels × ``--seeds`` seeds): its position error and reported sd just before the first
re-detection, and its final error once the loop has closed. With perfect associations up to the
loop, this is as close as an estimator of the same model can be when the re-detections arrive.

Usage::

    python3 scripts/hallway_loop_closure.py runs/hallway          # after the hallway study
    python3 scripts/hallway_loop_closure.py --probe ml:0.005:0
    python3 scripts/hallway_loop_closure.py --oracle [--seeds 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from hybridslam.analysis import consistency
from hybridslam.estimators import gaussian
from hybridslam.estimators.registry import make_estimator
from hybridslam.inference import gating
from hybridslam.io.result import load_result
from hybridslam.io.scenario import load_scenario, stack_steps
from hybridslam.models import geometry
from hybridslam.models.measurement import Detections
from hybridslam.sim import hallway
from hybridslam.config import setup

setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

jax.config.update("jax_enable_x64", True)

PROBED = ("ml", "gpda", "max-mixture")  # the single-Gaussian filters, whose state _probe reads


@jax.jit
def _probe(state, odometry, det: Detections, slots):
    """Per detection: d², ½log|S|, log density of ``slots[j]`` and of a new object; the pose covariance."""
    mean, cov = gaussian.predict(state, odometry)
    inn = gating.innovations(state.model.sensor, mean, cov, det)
    assoc = gaussian.associate(state, mean, cov, det)
    j = jnp.arange(slots.shape[0])
    s = jnp.maximum(slots, 0)
    half_logdet = 0.5 * jnp.linalg.slogdet(inn.cov[s])[1]
    d2 = inn.d2[j, s]
    sem = logsumexp(state.class_log_post[s] + assoc.class_loglik[j, s], axis=-1)
    known = -math.log(2 * math.pi) - half_logdet - 0.5 * d2 + sem
    new = state.params.new_object_log_density + logsumexp(
        state.params.new_class_log_prior[None] + assoc.new_class_loglik, axis=-1)
    return d2, half_logdet, known, new, mean[:3], cov[:3, :3]


def exact_detections(scenario):
    """The scenario with every detection's range and bearing replaced by the true ones (no noise)."""
    poses, marks = scenario.true_robot_poses, [pose for pose, _ in scenario.true_objects]
    rb = jax.jit(geometry.range_bearing)

    def exact(k, d):
        r, b = (float(v) for v in rb(jnp.asarray(poses[k + 1]), jnp.asarray(marks[d.true_object])))
        return dataclasses.replace(d, range=r, bearing=b)

    return scenario.replace(steps=tuple(dataclasses.replace(s, detections=tuple(exact(k, d) for d in s.detections))
                                        for k, s in enumerate(scenario.steps)))


def diagnose(estimator: str, trace: float, seed: int, gap: int, exact: bool = False) -> tuple[list[dict], str]:
    """The rows of every re-detection, and a line on the heading sd just before the first one."""
    scenario = hallway.hallway(seed=seed, trace=trace)
    scenario = exact_detections(scenario) if exact else scenario
    headline = ""
    stacked = stack_steps(scenario)
    est = make_estimator(estimator, max_detections=stacked.mask.shape[1], max_steps=scenario.num_steps)
    state = est.init(scenario)
    step = jax.jit(est.step)
    first: dict[int, tuple[int, int]] = {}  # landmark -> (step, detection slot) of its first detection
    rows = []
    for k in range(scenario.num_steps):
        det = Detections(jnp.asarray(stacked.geo[k]), jnp.asarray(stacked.scores[k]), jnp.asarray(stacked.mask[k]))
        truth = stacked.true_object[k]
        hist = np.asarray(state.history)
        slots = np.array([hist[first[t]] if t in first and k - first[t][0] > gap else -1 for t in truth])
        if np.any(slots >= 0) and not headline:
            sd, dead = math.sqrt(float(state.cov[2, 2])), math.sqrt(consistency.dead_reckoning_heading_var(scenario, k))
            headline = (f"after step {k}: heading sd / dead reckoning {sd / dead:.2f}, Cramér-Rao bound / dead "
                        f"reckoning {consistency.heading_bound(scenario, k) / dead:.2f}")
        if np.any(slots >= 0):
            d2, hld, known, new, x_hat, p = jax.device_get(_probe(state, jnp.asarray(stacked.odometry[k]), det,
                                                                   jnp.asarray(slots, dtype=jnp.int32)))
            nees = consistency.pose_nees(scenario.true_robot_poses[k + 1], x_hat, p)
            err = (scenario.true_robot_poses[k + 1][2] - x_hat[2] + math.pi) % (2 * math.pi) - math.pi
        state, _ = step(state, jnp.asarray(stacked.odometry[k]), det, jax.random.PRNGKey(k))
        assigned = np.asarray(state.history)[k]
        for j, t in enumerate(truth):
            if not stacked.mask[k, j]:
                continue
            if slots[j] >= 0:
                rows.append(dict(step=k + 1, landmark=int(t), since=k - first[t][0], slot=int(slots[j]),
                                 assigned=int(assigned[j]), d2=float(d2[j]), half_logdet=float(hld[j]),
                                 known=float(known[j]), new=float(new[j]), nees=nees,
                                 heading_err=float(err), heading_sd=float(math.sqrt(p[2, 2]))))
            first.setdefault(int(t), (k, j))
    return rows, headline


def summarize(folder: str, gap: int) -> tuple[dict[str, list[consistency.LoopClosureReport]], list[float]]:
    """Per estimator of a finished hallway study (``experiments/hallway_odometry_sweep.py -o FOLDER``),
    and per scenario the Cramér-Rao bound on the heading sd before its first re-detection / dead reckoning's."""
    reports: dict[str, list[consistency.LoopClosureReport]] = {}
    bounds: list[float] = []
    for path in sorted(glob.glob(os.path.join(folder, "scenarios", "*.json"))):
        scenario = load_scenario(path)
        for est in sorted(os.listdir(os.path.join(folder, "results"))):
            result = os.path.join(folder, "results", est, os.path.basename(path))
            if os.path.exists(result):
                reports.setdefault(est, []).append(consistency.loop_closure_report(scenario, load_result(result), gap))
        truth = [[d.true_object for d in step.detections] for step in scenario.steps]
        k = consistency.association_audit(truth, truth, gap).first_redetection
        if k is not None and k >= 2:  # the step before it, as in the reports
            bounds.append(consistency.heading_bound(scenario, k - 1)
                          / math.sqrt(consistency.dead_reckoning_heading_var(scenario, k - 1)))
    return reports, bounds


def print_summary(reports: dict[str, list[consistency.LoopClosureReport]], bounds: list[float], gap: int) -> None:
    """One row per estimator: audit counts summed over runs, pose consistency as medians."""
    print(f"re-det: detections of a landmark first detected more than {gap} steps earlier; closed: of those, "
          "assigned to the object made of its first detection; wrong: detections assigned to another landmark's "
          "object. NEES (3 dof; > 11.3 in 1% of steps if consistent), |heading error| / reported sd and reported "
          "heading sd / dead-reckoning sd: the top component just before the first re-detection; medians over runs")
    print(f"{'estimator':<12} {'runs':>4} {'re-det':>6} {'closed':>6} {'wrong':>5} {'objects':>7} "
          f"{'landmarks':>9} {'NEES':>6} {'>11.3':>6} {'|θ|/sd':>6} {'sd/DR':>5}")
    for est, runs in reports.items():
        total = lambda f: sum(getattr(r.audit, f) for r in runs)  # noqa: E731
        nees = [r.nees for r in runs if r.nees is not None]
        med = lambda f: float(np.median([getattr(r, f) for r in runs if getattr(r, f) is not None] or [np.nan]))  # noqa: E731
        print(f"{est:<12} {len(runs):4d} {total('redetections'):6d} {total('closed'):6d} {total('wrong'):5d} "
              f"{total('objects'):7d} {total('landmarks'):9d} {med('nees'):6.1f} "
              f"{sum(n > consistency.NEES_BOUND_99 for n in nees):>3d}/{len(nees):<2d} {med('heading_z'):6.2f} "
              f"{med('heading_sd_ratio'):5.2f}")
    print(f"Cramér-Rao bound on that heading sd / dead-reckoning sd (the least an honest estimator can report): "
          f"median {np.median(bounds):.2f}, range {min(bounds):.2f}-{max(bounds):.2f} over {len(bounds)} scenarios")


def print_oracle(seeds: int, gap: int) -> None:
    """One row per hallway scenario (level, seed) of :func:`consistency.oracle_drift`, then the means."""
    print(f"{'tr(Λ_t)':>8} {'seed':>4} {'step':>4} {'error m':>8} {'sd m':>6} {'err/sd':>6} {'θ err':>7} "
          f"{'θ sd':>6} {'final m':>7}")
    rows = []
    for trace in hallway.LEVELS:
        for seed in range(seeds):
            d = consistency.oracle_drift(hallway.hallway(seed, trace), gap)
            rows.append(d)
            print(f"{trace:8.3f} {seed:4d} {d.before_step or 0:4d} {d.before_error:8.2f} {d.before_sd:6.2f} "
                  f"{d.before_error / d.before_sd:6.2f} {d.before_heading_error:7.3f} {d.before_heading_sd:6.3f} "
                  f"{d.final_error:7.2f}", flush=True)
    mean = lambda f: float(np.mean([f(d) for d in rows]))  # noqa: E731
    print(f"mean over {len(rows)} runs: error before the loop {mean(lambda d: d.before_error):.2f} m "
          f"(reported sd {mean(lambda d: d.before_sd):.2f} m, |θ error| {mean(lambda d: abs(d.before_heading_error)):.3f} "
          f"rad), after it {mean(lambda d: d.final_error):.2f} m")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", nargs="?", help="a finished hallway study (its scenarios/ and results/)")
    parser.add_argument("--probe", metavar="EST:TRACE:SEED", help="trace every re-detection of one run "
                        "(EST one of ml, gpda, max-mixture), e.g. ml:0.005:0")
    parser.add_argument("--exact-detections", action="store_true",
                        help="with --probe: replace the detections by their true range and bearing")
    parser.add_argument("--gap", type=int, default=20, help="steps since the first detection (default 20)")
    parser.add_argument("--oracle", action="store_true",
                        help="the true-association smoother's drift before the loop closes, on the study's scenarios")
    parser.add_argument("--seeds", type=int, default=3, help="with --oracle: seeds per level (default 3)")
    args = parser.parse_args(argv)
    if sum((args.folder is not None, args.probe is not None, args.oracle)) != 1:
        parser.error("give a study folder, --probe or --oracle (one of them)")
    if args.oracle:
        print_oracle(args.seeds, args.gap)
        return
    if args.folder:
        print_summary(*summarize(args.folder, args.gap), args.gap)
        return
    est, trace, seed = args.probe.split(":")
    if est not in PROBED:
        parser.error(f"--probe: EST must be one of {', '.join(PROBED)}, got {est!r}")
    rows, headline = diagnose(est, float(trace), int(seed), args.gap, args.exact_detections)
    print(f"{est}, tr(Λ_t) = {float(trace):g}, seed {seed}{', exact detections' if args.exact_detections else ''}: "
          f"{len(rows)} re-detections, {sum(r['assigned'] == r['slot'] for r in rows)} assigned to the landmark's "
          f"first object; {headline}")
    print(f"{'step':>4} {'lm':>3} {'since':>5} {'slot':>4} {'got':>4} {'d2':>8} {'½log|S|':>8} "
          f"{'known':>8} {'new':>7} {'NEES':>7} {'θ err':>7} {'θ sd':>6}")
    for r in rows:
        print(f"{r['step']:4d} {r['landmark']:3d} {r['since']:5d} {r['slot']:4d} {r['assigned']:4d} "
              f"{r['d2']:8.1f} {r['half_logdet']:8.2f} {r['known']:8.2f} {r['new']:7.2f} {r['nees']:7.1f} "
              f"{r['heading_err']:7.3f} {r['heading_sd']:6.3f}")


if __name__ == "__main__":
    main()
