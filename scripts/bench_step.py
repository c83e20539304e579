"""Benchmark one inference step: compile time and latency at K = 16, 64, 256 live components.

Paper setup (6 objects, 2 classes, mirror model), 2 detections per step, n_s = 1000 by default.
Every slot of the belief is made alive (copies of a real component with equal weights) so the
numbers are for full capacity. Prints a table; asserts nothing.

    python scripts/bench_step.py [--capacities 16 64 256] [--samples 1000] [--weights sampled linearized] [--repeats 20]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

import hybridslam as hs
from hybridslam.run import config_for


def full_belief(scenario: hs.Scenario, capacity: int, samples: int, weights: str) -> hs.Belief:
    config = config_for(scenario, capacity=capacity, num_samples=samples, weights=weights, max_detections=2)
    belief = hs.init_belief(scenario, config=config)
    return hs.Belief(
        jnp.full((capacity,), -jnp.log(capacity)), belief.mean, belief.cov, belief.classes,
        belief.history, belief.k, belief.model, belief.config,
    )


def two_detection_step(scenario: hs.Scenario):
    stacked = hs.stack_steps(scenario, 2)
    k = int(next(i for i in range(scenario.num_steps) if stacked.mask[i].sum() == 2))
    det = hs.Detections(jnp.asarray(stacked.geo[k]), jnp.asarray(stacked.scores[k]), jnp.asarray(stacked.mask[k]))
    return jnp.asarray(stacked.odometry[k]), det


def bench(capacity: int, samples: int, weights: str, repeats: int) -> tuple[float, float, float]:
    scenario = hs.simulate(0, steps=10)
    belief = full_belief(scenario, capacity, samples, weights)
    odometry, det = two_detection_step(scenario)
    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    compiled = hs.step.lower(belief, odometry, det, key).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(belief, odometry, det, key))  # warm-up
    times = []
    for i in range(repeats):
        k = jax.random.fold_in(key, i)
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(belief, odometry, det, k))
        times.append(time.perf_counter() - t0)
    return compile_s, statistics.median(times), min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capacities", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--weights", nargs="+", default=["sampled", "linearized"])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    print(f"device: {jax.devices()[0].device_kind} x{len(jax.devices())}, jax {jax.__version__}, float64")
    print(f"{'weights':>10} {'K':>5} {'n_s':>6} {'compile s':>10} {'step ms (median)':>17} {'step ms (min)':>14}")
    for weights in args.weights:
        for capacity in args.capacities:
            c, med, best = bench(capacity, args.samples, weights, args.repeats)
            print(f"{weights:>10} {capacity:>5} {args.samples:>6} {c:>10.2f} {med * 1e3:>17.1f} {best * 1e3:>14.1f}")


if __name__ == "__main__":
    main()
