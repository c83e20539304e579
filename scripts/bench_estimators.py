"""Benchmark every association strategy on the hallway study (thesis Sec. 5.4.1) at its default settings.

One hallway scenario (seed 0, the thesis's example noise ``tr(Λ_t) = 0.021``, one loop of 60 steps,
unknown map of 60 landmarks, object capacity 70) per estimator: compile time, then the median,
mean and max wall time of a step after compilation, and the APE translation mean of the run.
The settings are those of ``experiments/hallway_odometry_sweep.py``. Asserts nothing.

    python scripts/bench_estimators.py [--estimators ml,gpda,max-mixture,multimodal,hybrid] [--steps 60]
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from hybridslam import compilation, driver
from hybridslam.analysis import trajectory
from hybridslam.sim import hallway
from hybridslam.config import setup

setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "experiments"))
from hallway_odometry_sweep import DEFAULT_ESTIMATORS, EXAMPLE_TRACE, SETTINGS, estimator  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--estimators", default=",".join(DEFAULT_ESTIMATORS))
    parser.add_argument("--steps", type=int, default=None, help="default: one loop (60 steps)")
    parser.add_argument("--seed", type=int, default=0)
    a = parser.parse_args()
    compilation.QUICK_RUN_STEPS = 0  # every program compiled fully: the step times of the optimized program
    scenario = hallway.hallway(a.seed, EXAMPLE_TRACE, steps=a.steps)
    _, truth = trajectory.trajectory_from_scenario(scenario)
    print(f"hallway seed {a.seed}, tr(Λ_t) = {EXAMPLE_TRACE}: {scenario.num_steps} steps, "
          f"{len(scenario.true_objects)} landmarks, object capacity {scenario.discovery.max_objects}, "
          f"up to {scenario.max_detections} detections per step")
    print(f"{'estimator':<12} {'settings':<46} {'compile s':>9} {'median ms':>9} {'mean ms':>8} {'max ms':>8} "
          f"{'APE m':>6}")
    for name in a.estimators.split(","):
        settings = SETTINGS.get(name, {})
        run = driver.run(estimator(name), scenario, seed=a.seed)
        step_ms = 1e3 * np.asarray(run.result.timing["step_s"])
        _, estimate = trajectory.trajectory_from_result(run.result)
        ape = trajectory.ape(truth, estimate).statistics()["translation"]["mean"]
        text = ", ".join(f"{k}={v}" for k, v in settings.items()) or "defaults"
        print(f"{name:<12} {text:<46} {run.result.timing['compile_s']:>9.1f} {np.median(step_ms):>9.1f} "
              f"{np.mean(step_ms):>8.1f} {np.max(step_ms):>8.1f} {ape:>6.2f}", flush=True)


if __name__ == "__main__":
    main()
