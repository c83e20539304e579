"""Smoothing a whole MRCLAM log: the step cost of each smoother and how far its trajectory is from
the batch solution of its own final graph.

One robot's whole log (default robot 3 of the dataset, 20-870 s: 1700 steps of 0.5 s), imported as
``hybridslam import mrclam`` does (every reading, the file's clutter density; ``--identity-filter``:
the oracle-assisted file), run by each estimator with the settings ``hybridslam run`` chooses for
it and each smoother given. Per run: compile seconds, median and mean ms of the steps before the
last, the last step's seconds (``incremental:L`` re-solves the whole graph there), the APE
translation mean of the online ``x_k`` and of the smoothed trajectory, and the final-pose error.
With GTSAM installed, the run's final graph (the top component's associations) is rebuilt and
solved by GTSAM's batch Levenberg-Marquardt (``scripts/isam2_baseline.py --associations-from
RESULT --batch``): ``batch APE`` is that solution's smoothed APE and ``from batch`` the largest
distance between it and the run's trajectory. The goals of exact smoothing at a bounded step
cost: the hybrid belief's median step within 40 ms, ``ml``'s within 5 ms, and the batch
solution's APE. Asserts nothing; run it on an idle machine (a full-smoother run of a whole log
takes 5-10 minutes).

    python3 scripts/bench_whole_log.py MRCLAM_Dataset7 [--robot 3] [--estimators ml,hybrid]
        [--smoothers lag:50,incremental:50] [--identity-filter] [--duration 850]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys

import numpy as np

import hybridslam as hs
from hybridslam.analysis import trajectory
from hybridslam.datasets.mrclam import import_mrclam

hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

GOALS_MS = {"hybrid": 40.0, "ml": 5.0}  # median step goals on a whole log (docs/performance.md, Whole logs)


def _ape(truth: np.ndarray, poses: np.ndarray) -> float:
    return float(trajectory.ape(truth, poses).statistics()["translation"]["mean"])


def _gtsam_batch(scenario: hs.Scenario, result: hs.Result):
    """GTSAM's batch Levenberg-Marquardt of ``result``'s final graph: its trajectory ``(T+1, 3)``, or
    ``None`` without GTSAM."""
    if importlib.util.find_spec("gtsam") is None:
        return None
    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)
    import isam2_baseline

    given = [list(a) for a in result.steps[-1].components[0].associations]
    obj, _ = isam2_baseline.run(scenario, batch=True, given=given)
    return np.asarray(obj["trajectory"], dtype=float)


def row(scenario: hs.Scenario, name: str, smoother: str) -> dict:
    """One run of ``name`` under ``smoother`` on ``scenario``, and its numbers."""
    estimator = hs.make_estimator(name, scenario=scenario, smoother=smoother)
    run = hs.run(estimator, scenario)
    steps = np.asarray(run.result.timing["step_s"], dtype=float)
    truth = scenario.true_robot_poses
    smoothed = np.asarray(run.result.trajectory, dtype=float)
    online = np.array([s.components[0].pose_mean for s in run.result.steps])
    out = {"estimator": name, "smoother": smoother, "compile_s": run.result.timing["compile_s"],
           "median_ms": 1e3 * float(np.median(steps[:-1])), "mean_ms": 1e3 * float(np.mean(steps[:-1])),
           "last_s": float(steps[-1]), "ape_online": _ape(truth[1:], online),
           "ape_smoothed": _ape(truth[1:], smoothed[1:]),
           "last_pose": float(np.linalg.norm(smoothed[-1, :2] - truth[-1, :2]))}
    batch = _gtsam_batch(scenario, run.result)
    if batch is not None:
        out["ape_batch"] = _ape(truth[1:], batch[1:])
        out["from_batch"] = float(np.max(np.linalg.norm(batch[:, :2] - smoothed[:, :2], axis=1)))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("dataset", help="an MRCLAM dataset folder (MRCLAM_Dataset7)")
    p.add_argument("--robot", type=int, default=3)
    p.add_argument("--start", type=float, default=20.0, help="seconds into the log (default 20)")
    p.add_argument("--duration", type=float, default=850.0, help="seconds (default 850: 1700 steps)")
    p.add_argument("--identity-filter", action="store_true", help="the oracle-assisted import (docs/studies/mrclam.md)")
    p.add_argument("--estimators", default="ml,hybrid")
    p.add_argument("--smoothers", default="lag:50,incremental:50")
    a = p.parse_args(argv)
    scenario = import_mrclam(a.dataset, a.robot, start=a.start, duration=a.duration, identity_filter=a.identity_filter)
    print(f"# MRCLAM {os.path.basename(os.path.normpath(a.dataset))} robot {a.robot}: {scenario.num_steps} steps, "
          f"up to {scenario.max_detections} detections per step"
          + (", identity-filtered" if a.identity_filter else ", every reading"))
    cols = ("compile_s", "median_ms", "mean_ms", "last_s", "ape_online", "ape_smoothed", "ape_batch", "from_batch",
            "last_pose")
    print(f"{'estimator':<10}{'smoother':<16}" + "".join(f"{c:>13}" for c in cols) + "  goal")
    for name in a.estimators.split(","):
        for smoother in a.smoothers.split(","):
            r = row(scenario, name, smoother)
            goal = GOALS_MS.get(name)
            verdict = "" if goal is None else f"  {goal:g} ms: {'met' if r['median_ms'] <= goal else 'missed'}"
            print(f"{name:<10}{smoother:<16}" + "".join(
                f"{r.get(c, float('nan')):>13.2e}" if c == "from_batch" else f"{r.get(c, float('nan')):>13.3f}" for c in cols)
                + verdict, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
