"""Spurious detections on a known map, with and without a clutter hypothesis.

The paper setup (6 mapped objects, ``mirror`` classifier, 10 steps, ≤ 2 detections per step) with
a ghost added to every other step: a detection of no object (``true_object`` unset), at a range
drawn from [1, 8] m and a bearing from [-0.5, 0.5] rad, with uninformative scores [0.5, 0.5]. The
paper's model says every detection is of an object; ``--clutter LOG_DENSITY`` lets a detection be
clutter instead (a log density over [range, bearing]). Prints, per estimator, clutter setting and
seed, the translation errors of ``hybridslam run`` (online APE, last pose:
``analysis.trajectory.error_summary``) on the clean file and on the ghosted one, and the detections each run left unassociated (``skipped``) or called
clutter (``rejected``). Asserts nothing.

    python scripts/spurious_detections.py [--seeds 4] [--estimators hybrid,multimodal] [--clutter none,-6]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

import hybridslam as hs
from hybridslam.analysis.trajectory import error_summary
from hybridslam.driver import Run, run_estimator
from hybridslam.io.scenario import Detection


hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def ghosted(scenario: hs.Scenario, seed: int) -> hs.Scenario:
    """``scenario`` with one ghost detection added to every other step (steps 2, 4, ...)."""
    rng = np.random.default_rng(100 + seed)
    steps = []
    for k, step in enumerate(scenario.steps):
        if k % 2 == 1:
            ghost = Detection(range=float(rng.uniform(1.0, 8.0)), bearing=float(rng.uniform(-0.5, 0.5)),
                              scores=np.array([0.5, 0.5]), true_object=None)
            step = dataclasses.replace(step, detections=tuple(step.detections) + (ghost,))
        steps.append(step)
    return scenario.replace(steps=tuple(steps))


def errors(run: Run, scenario: hs.Scenario) -> tuple[float, float]:
    """Online APE and last-pose translation error (m), as ``hybridslam run`` prints them."""
    e = error_summary(run.result, scenario)
    return e["ape_online"], e["final"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--estimators", default="hybrid,multimodal")
    parser.add_argument("--clutter", default="none,-6", help="comma-separated log densities; 'none': no clutter hypothesis")
    a = parser.parse_args()
    print("estimator   clutter seed  clean: APE / last (m)   ghosts: APE / last (m)   skipped rejected")
    for name in a.estimators.split(","):
        for text in a.clutter.split(","):
            clutter = None if text == "none" else float(text)
            rows = []
            for seed in range(a.seeds):
                clean = hs.simulate(seed, steps=10, setup=hs.PaperSetup(max_detections=2, max_range=12.0))
                dirty = ghosted(clean, seed)
                options = {"capacity": 16, **({} if clutter is None else {"clutter": clutter})}
                c = errors(run_estimator(clean, name, seed=0, **options), clean)
                run = run_estimator(dirty, name, seed=0, **options)
                g = errors(run, dirty)
                skipped = sum(int(i.skipped) for i in run.infos)
                rejected = sum(int(i.rejected) for i in run.infos)
                rows.append((c, g))
                print(f"{name:11s} {text:>7s} {seed:4d}  {c[0]:6.3f} / {c[1]:6.3f}         {g[0]:6.3f} / {g[1]:6.3f}"
                      f"          {skipped:4d} {rejected:8d}", flush=True)
            mean = np.mean([[c[0], c[1], g[0], g[1]] for c, g in rows], axis=0)
            print(f"{name:11s} {text:>7s} mean  {mean[0]:6.3f} / {mean[1]:6.3f}         {mean[2]:6.3f} / {mean[3]:6.3f}")


if __name__ == "__main__":
    main()
