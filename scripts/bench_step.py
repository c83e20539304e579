"""Benchmark one inference step: compile time and latency at K = 16, 64, 256 live components.

Paper setup (6 objects, 2 classes, mirror model), 2 detections per step.
Table 1 makes every slot of the belief alive (copies of a real component with equal weights):
the cost at full capacity. Table 2 runs whole simulated tracks at capacity K, where only the
components that survive pruning are alive (the step skips chunks of dead slots). Prints; asserts
nothing.

    python scripts/bench_step.py [--capacities 16 64 256] [--samples N] [--weights laplace-is sampled linearized]

"draws" is n_s per parent for sampled (default 1000) and the draws per candidate child for
laplace-is (default 256); linearized draws nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp

import hybridslam as hs
from hybridslam.driver import compile_lowered
from hybridslam.estimators.hybrid.weighers import make_weigher


hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def estimator(capacity: int, samples: int | None, weights: str, classifier: str | None = None) -> hs.Hybrid:
    """The hybrid belief at capacity K with 2 detection slots; ``samples`` sets the draws of the weight
    method (``None``: its default; the deterministic ``linearized`` draws none and ignores it)."""
    weigher = make_weigher(weights, None if weights == "linearized" else samples)
    return hs.Hybrid(weights=weigher, capacity=capacity, classifier=classifier, max_detections=2)


def full_belief(scenario: hs.Scenario, est: hs.Hybrid) -> hs.Belief:
    """The initial belief with every one of its K slots alive (equal weights)."""
    belief = est.init(scenario)
    return dataclasses.replace(belief, log_weights=jnp.full((est.capacity,), -jnp.log(est.capacity)))


def two_detection_step(scenario: hs.Scenario):
    stacked = hs.stack_steps(scenario, 2)
    k = int(next(i for i in range(scenario.num_steps) if stacked.mask[i].sum() == 2))
    det = hs.Detections(jnp.asarray(stacked.geo[k]), jnp.asarray(stacked.scores[k]), jnp.asarray(stacked.mask[k]))
    return jnp.asarray(stacked.odometry[k]), det


def bench(capacity: int, samples: int, weights: str, repeats: int) -> tuple[float, float, float]:
    scenario = hs.simulate(0, steps=10)
    est = estimator(capacity, samples, weights)
    belief = full_belief(scenario, est)
    odometry, det = two_detection_step(scenario)
    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    compiled = compile_lowered(eqx.filter_jit(est.step).lower(belief, odometry, det, key))
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(belief, odometry, det, key))  # warm-up
    times = []
    for i in range(repeats):
        k = jax.random.fold_in(key, i)
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(belief, odometry, det, k))
        times.append(time.perf_counter() - t0)
    return compile_s, statistics.median(times), min(times)


def bench_tracks(capacity: int, samples: int, weights: str, tracks: int) -> tuple[float, float]:
    """Median step time over whole paper-setup tracks, and the mean number of live components."""
    times, alive = [], []
    for seed in range(tracks):
        for classifier in ("mirror", "none"):
            run = hs.run(estimator(capacity, samples, weights, classifier), hs.simulate(seed, steps=10))
            times += run.result.timing["step_s"]
            alive += [s.metrics["num_components"] for s in run.result.steps]
    return statistics.median(times), statistics.mean(alive)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capacities", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--samples", type=int, default=None, help="draws of the weight method (default: its own)")
    parser.add_argument("--weights", nargs="+", default=["laplace-is", "sampled", "linearized"])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--tracks", type=int, default=3, help="tracks per classifier for table 2 (0: skip)")
    args = parser.parse_args()
    print(f"device: {jax.devices()[0].device_kind} x{len(jax.devices())}, jax {jax.__version__}, float64")
    print(f"{'weights':>10} {'K':>5} {'draws':>6} {'compile s':>10} {'step ms (median)':>17} {'step ms (min)':>14}")
    for weights in args.weights:
        for capacity in args.capacities:
            c, med, best = bench(capacity, args.samples, weights, args.repeats)
            draws = estimator(capacity, args.samples, weights).weights.draws
            print(f"{weights:>10} {capacity:>5} {draws:>6} {c:>10.2f} {med * 1e3:>17.1f} {best * 1e3:>14.1f}")
    if args.tracks:
        print(f"\nwhole tracks (mirror and none, {args.tracks} tracks each, 10 steps, paper setup)")
        print(f"{'weights':>10} {'K':>5} {'draws':>6} {'live (mean)':>12} {'step ms (median)':>17}")
        for weights in args.weights:
            for capacity in args.capacities:
                med, live = bench_tracks(capacity, args.samples, weights, args.tracks)
                draws = estimator(capacity, args.samples, weights).weights.draws
                print(f"{weights:>10} {capacity:>5} {draws:>6} {live:>12.1f} {med * 1e3:>17.1f}")


if __name__ == "__main__":
    main()
