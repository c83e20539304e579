"""Benchmark planning: score 256 candidate 5-step action sequences from a paper-setup belief.

The belief is the estimator's after 2 steps of a paper-setup track (geometry-only model, so it
is still ambiguous). ``hybridslam.planning.score_candidates`` predicts observations for every
candidate from the belief and runs the belief update on them (one jitted, vmapped call). Prints
compile time and the median time of a call. Then the gradient of the expected objective with
respect to the turn rates of one candidate (smooth visibility, reverse mode through the predicted
observations and the H belief updates): compile time and the median time of one gradient.
Asserts nothing.

    python scripts/bench_planning.py [--candidates 256] [--horizon 5] [--capacity 4] [--draws 1] [--no-grad]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

import hybridslam as hs
from hybridslam import planning
from hybridslam.planning.plan import turn_actions


hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--candidates", type=int, default=256)
    parser.add_argument("--horizon", type=int, default=5)
    parser.add_argument("--capacity", type=int, default=4, help="components kept for planning")
    parser.add_argument("--draws", type=int, default=1, help="predicted worlds per candidate")
    parser.add_argument("--gn-max-steps", type=int, default=2)
    parser.add_argument("--weights", default="linearized", choices=("linearized", "sampled", "laplace-is"))
    parser.add_argument("--classifier", default="none", choices=("none", "mirror", "independent"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-grad", action="store_true", help="skip the gradient timing")
    a = parser.parse_args()
    scenario = hs.simulate(0, steps=2)
    belief = hs.run_estimator(scenario, "hybrid", classifier=a.classifier, capacity=16, max_detections=2).state
    plan = planning.prepare(belief, a.horizon, capacity=a.capacity, weights=a.weights, gn_max_steps=a.gn_max_steps)
    cands = planning.arc_candidates(a.candidates, a.horizon, key=jax.random.PRNGKey(1))
    print(f"{a.candidates} candidates x {a.horizon} steps x {a.draws} draw(s); belief: "
          f"{int(plan.belief.alive.sum())} live of {a.capacity} kept components, classifier {a.classifier}, weights {a.weights}, gn_max_steps {a.gn_max_steps}")
    t0 = time.perf_counter()
    jax.block_until_ready(planning.score_candidates(plan, cands, jax.random.PRNGKey(0), a.draws))
    first = time.perf_counter() - t0
    times = []
    for i in range(a.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(planning.score_candidates(plan, cands, jax.random.PRNGKey(i + 1), a.draws))
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    print(f"first call (compile + run): {first:.1f} s")
    print(f"score all candidates: median {med:.3f} s, min {min(times):.3f} s "
          f"({1e3 * med / (a.candidates * a.horizon * a.draws):.2f} ms per predicted step)")
    if not a.no_grad:
        _bench_gradient(belief, a)


def _bench_gradient(belief, a) -> None:
    smooth = planning.prepare(belief, a.horizon, capacity=a.capacity, weights=a.weights,
                              gn_max_steps=a.gn_max_steps, visibility_temperature=0.5)
    keys = jax.random.split(jax.random.PRNGKey(0), a.draws)

    @jax.jit
    def grad(turns, keys):
        return jax.value_and_grad(lambda t: planning.expected_objective(
            smooth, turn_actions(jnp.arctanh(t / 0.6), 1.0, 0.6), keys))(turns)

    turns = jnp.linspace(-0.3, 0.3, a.horizon)
    t0 = time.perf_counter()
    jax.block_until_ready(grad(turns, keys))
    first = time.perf_counter() - t0
    times = []
    for i in range(a.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(grad(turns + 0.01 * i, keys))
        times.append(time.perf_counter() - t0)
    print(f"gradient of the expected objective w.r.t. {a.horizon} turn rates ({a.draws} draw(s), smooth visibility "
          f"0.5 m): first call {first:.1f} s, then median {1e3 * statistics.median(times):.1f} ms, "
          f"min {1e3 * min(times):.1f} ms")


if __name__ == "__main__":
    main()
