"""Is the smoothed covariance honest on the hallway? The Cramér-Rao heading bound and the pose NEES.

For every scenario of a finished hallway study (``experiments/hallway_odometry_sweep.py -o FOLDER``;
``FOLDER/scenarios/*.json``), and for every estimator's result files in ``FOLDER/results/<estimator>/``:

* **true associations**: :func:`hybridslam.analysis.consistency.true_association_smoother`, the full
  smoother given every detection's true landmark; the reference (issue 13 §5: its heading sd within
  10% of the Cramér-Rao bound, its NEES inside the 99% bound in at least 90% of the runs);
* **each estimator with its own associations**: the online ``x_k`` of the result file's top component.

Per run, at every step ``k``: the reported heading sd over the Cramér-Rao bound
(:func:`~hybridslam.analysis.consistency.heading_bound`: no estimator can be more certain, so a
ratio below 1 is overconfidence) and the pose NEES against its 99% bound (11.34, 3 degrees of
freedom). Printed per estimator: runs whose last step is within 10% of the bound and inside the
NEES bound, the median ratio over all steps, the share of steps inside the NEES bound and the mean NEES.

    python3 scripts/hallway_consistency.py runs/hallway [--estimators ml,gpda,max-mixture]
"""

from __future__ import annotations

import argparse
import glob
import os

import numpy as np

from hybridslam.analysis import consistency
from hybridslam.io.result import load_result
from hybridslam.io.scenario import load_scenario
from hybridslam.config import setup


setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def _scores(scenario, means, covs, bounds):
    """Per step: heading sd / Cramér-Rao bound and the pose NEES."""
    truth = np.asarray(scenario.true_robot_poses)
    ratio = np.sqrt(covs[:, 2, 2]) / bounds
    nees = np.array([consistency.pose_nees(truth[k + 1], means[k], covs[k]) for k in range(len(means))])
    return ratio, nees


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", help="a finished hallway study (its scenarios/ and results/)")
    parser.add_argument("--estimators", default=None, help="the estimators' result folders (default: all)")
    a = parser.parse_args()
    paths = sorted(glob.glob(os.path.join(a.folder, "scenarios", "*.json")))
    if not paths:
        raise SystemExit(f"{a.folder}/scenarios: no scenario files (run experiments/hallway_odometry_sweep.py -o {a.folder})")
    names = a.estimators.split(",") if a.estimators else sorted(
        os.path.basename(d) for d in glob.glob(os.path.join(a.folder, "results", "*")) if os.path.isdir(d))
    rows: dict[str, list] = {"true associations (full smoother)": []}
    rows.update({n: [] for n in names})
    for path in paths:
        scenario = load_scenario(path)
        bounds = np.array([consistency.heading_bound(scenario, k) for k in range(1, scenario.num_steps + 1)])
        oracle = consistency.true_association_smoother(scenario)
        rows["true associations (full smoother)"].append(_scores(scenario, oracle.means, oracle.covs, bounds))
        for name in names:
            result_path = os.path.join(a.folder, "results", name, os.path.basename(path))
            if not os.path.exists(result_path):
                continue
            r = load_result(result_path)
            top = [max(s.components, key=lambda c: c.weight) for s in r.steps]
            means = np.array([c.pose_mean for c in top])
            covs = np.array([c.pose_cov for c in top])
            rows[name].append(_scores(scenario, means, covs, bounds))
        print(f"{os.path.basename(path)}: done", flush=True)
    print(f"\n{'estimator':<36} {'runs':>4} {'last step ok':>12} {'sd/CRB median':>13} {'sd/CRB last':>11} "
          f"{'NEES<=11.34':>11} {'mean NEES':>9}")
    for name, runs in rows.items():
        if not runs:
            continue
        last_ok = sum(bool(abs(ratio[-1] - 1) <= 0.1 and nees[-1] <= consistency.NEES_BOUND_99) for ratio, nees in runs)
        ratios = np.concatenate([r for r, _ in runs])
        nees = np.concatenate([n for _, n in runs])
        last = np.array([r[-1] for r, _ in runs])
        print(f"{name:<36} {len(runs):>4} {last_ok:>5} of {len(runs):<4} {np.median(ratios):>13.3f} "
              f"{np.min(last):>5.2f}-{np.max(last):<5.2f} {np.mean(nees <= consistency.NEES_BOUND_99):>11.0%} "
              f"{np.mean(nees):>9.1f}")


if __name__ == "__main__":
    main()
