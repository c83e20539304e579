"""Per-step time against the number of detections per step: does the cost grow with them?

A corridor of 32 mapped objects (two rows, 2 m apart along the track, two classes, ``mirror``
classifier), 10 steps, and a detector that reports the ``D`` nearest objects in view (range 25
m, 120° field of view) for ``D`` = 2, 4, 8, 12, 16: the same map and true track at every ``D``
(the sensor noise is drawn anew), only the detections per step change. Each estimator runs with
its usual settings for many detections (the hybrid belief as on the hallway: capacity 16, 3
gated candidates per detection, linearized weights, beam width 64; ``ml`` with its joint
hypotheses built one detection at a time), full smoother. Prints compile seconds and the median
step time after compilation per ``D``, and the growth from the smallest ``D``; asserts nothing
(benchmarks never fail a build).

    python scripts/bench_detections.py [--detections 2,4,8,12,16] [--estimators hybrid,ml] [--smoother full]

An exhaustive enumeration of joint assignments would grow as ``(G+1)^D`` (65,536 rows per parent
at ``D`` = 8, 16.7 million at 12); the beam scores ``D · width · options`` extensions, each a
small conditional density (``hybridslam.estimators.hybrid.weights.PartialChild``).
"""

from __future__ import annotations

import argparse

import numpy as np

import hybridslam as hs
from hybridslam import compilation
from hybridslam.driver import clear_compiled

hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

SETTINGS = {"hybrid": dict(capacity=16, gate=3, weights="linearized"), "multimodal": dict(capacity=16)}


def corridor(detections: int, seed: int = 0) -> hs.Scenario:
    """The benchmark's scenario with up to ``detections`` detections per step."""
    xs = np.arange(2.0, 34.0, 2.0)
    objects = tuple((float(x), side * 2.5, 0.3 * side) for x in xs for side in (1.0, -1.0))
    setup = hs.PaperSetup(object_poses=objects, max_detections=detections, max_range=25.0, turn_std=0.02)
    return hs.simulate(seed, steps=10, setup=setup)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--detections", default="2,4,8,12,16")
    parser.add_argument("--estimators", default="hybrid,ml")
    parser.add_argument("--smoother", default="full")
    parser.add_argument("--repeats", type=int, default=2)
    a = parser.parse_args()
    compilation.QUICK_RUN_STEPS = 0  # every program compiled fully: the step times of the optimized program
    counts = [int(d) for d in a.detections.split(",")]
    print(f"{'estimator':12s} {'D':>3s} {'per step':>9s} {'compile s':>9s} {'median ms':>9s} {'growth':>7s}")
    for name in a.estimators.split(","):
        base = None
        for d in counts:
            scenario = corridor(d)
            seen = [len(s.detections) for s in scenario.steps]
            est = hs.make_estimator(name, smoother=a.smoother, max_detections=d, **SETTINGS.get(name, {}))
            compile_s, steps = 0.0, []
            try:
                for _ in range(a.repeats):
                    r = hs.run(est, scenario)
                    compile_s = max(compile_s, r.result.timing["compile_s"])
                    steps += r.result.timing["step_s"]
            except ValueError as e:  # an estimator's own limit on the slots or objects
                print(f"{name:12s} {d:3d} refused: {e}", flush=True)
                continue
            finally:
                clear_compiled()
            ms = 1e3 * float(np.median(steps))
            base = ms if base is None else base
            print(f"{name:12s} {d:3d} {min(seen):>4d}-{max(seen):<4d} {compile_s:9.1f} {ms:9.1f} {ms / base:6.1f}x",
                  flush=True)


if __name__ == "__main__":
    main()
