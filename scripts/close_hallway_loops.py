"""The loop-closure pass (:mod:`hybridslam.estimators.loops.closure`) over a finished hallway study.

For every estimator of the study and every scenario: the smoothed trajectory's last-pose error and
APE and the map error (:func:`~hybridslam.analysis.map_error.map_error`: each object against the true
landmark most of its detections are of) before and after
:func:`~hybridslam.estimators.loops.closure.close_loops`, and how many of its merges join two objects
whose detections are mostly of the same true landmark (right) or not (wrong). Then the means per
estimator.

    python3 experiments/hallway_odometry_sweep.py -o runs/hallway_full --estimators ml,max-mixture
    python3 scripts/close_hallway_loops.py runs/hallway_full [--revisit-log-odds 5] [--misses point]

``--gated-oracle`` judges the back end apart from the front end: on each scenario of the study, the
true associations except that landmarks re-detected after ``--gap`` steps are new objects
(:func:`hybridslam.analysis.consistency.gated_oracle_result`, what a gated one-step association
that made no other mistake leaves at the loop), then the same pass. It also prints how the pass's
model judges the *true* merge set (:func:`~hybridslam.estimators.loops.closure.score_merges`): its log
posterior odds against no merge, whether its re-solved cost passes verification, and the score of the
pass's own first choice, so that a search that missed the truth can be told from data that do not
favour it.
"""

from __future__ import annotations

import argparse
import glob
import os

import jax
import numpy as np

from hybridslam.analysis import consistency
from hybridslam.analysis.map_error import map_error, object_landmarks
from hybridslam.analysis.trajectory import error_summary
from hybridslam.estimators.loops.closure import close_loops, score_merges
from hybridslam.estimators.loops.settings import MISS_MODELS, LoopClosureSettings
from hybridslam.io.result import load_result
from hybridslam.io.scenario import load_scenario
from hybridslam.config import setup

setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

jax.config.update("jax_enable_x64", True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", help="a finished hallway study (scenarios/, results/<estimator>/)")
    parser.add_argument("--revisit-log-odds", type=float, default=0.0)
    parser.add_argument("--gap", type=int, default=20)
    parser.add_argument("--misses", choices=MISS_MODELS, default=LoopClosureSettings.misses,
                        help="negative information: marginal (default) or point (LoopClosureSettings.misses)")
    parser.add_argument("--gated-oracle", action="store_true",
                        help="the true associations with late re-detections as new objects, not the study's results")
    args = parser.parse_args(argv)
    settings = LoopClosureSettings(gap=args.gap, revisit_log_odds=args.revisit_log_odds, misses=args.misses)
    print(f"{'estimator':<12} {'scenario':<28} {'last before':>11} {'after':>6} {'APE before':>10} {'after':>6} "
          f"{'map before':>10} {'after':>6} {'right':>5} {'wrong':>5}")
    scenarios = sorted(glob.glob(os.path.join(args.folder, "scenarios", "*.json")))
    estimators = ["gated-oracle"] if args.gated_oracle else sorted(os.listdir(os.path.join(args.folder, "results")))
    for est in estimators:
        rows, judged = [], []
        for path in scenarios:
            result_path = os.path.join(args.folder, "results", est, os.path.basename(path))
            if not (args.gated_oracle or os.path.exists(result_path)):
                continue
            scenario = load_scenario(path)
            if args.gated_oracle:
                result, truth = consistency.gated_oracle_result(scenario, args.gap)
                # "before": the same graph re-solved with nothing merged
                result, _ = close_loops(scenario, result, LoopClosureSettings(gap=args.gap, max_rounds=0))
            else:
                result = load_result(result_path)
                truth = object_landmarks(scenario, result)
            closed, report = close_loops(scenario, result, settings)
            right = sum(truth[a] == truth[b] for c in report.closures for a, b in c.merges)
            before, after = error_summary(result, scenario), error_summary(closed, scenario)
            maps = [map_error(scenario, r).get("mean_m", np.nan) for r in (result, closed)]
            row = (before["final_smoothed"], after["final_smoothed"], before["ape_smoothed"], after["ape_smoothed"],
                   *maps, right, report.merged - right)
            rows.append(row)
            line = (f"{est:<12} {os.path.basename(path):<28} {row[0]:11.2f} {row[1]:6.2f} {row[2]:10.2f} {row[3]:6.2f} "
                    f"{row[4]:10.2f} {row[5]:6.2f} {row[6]:5d} {row[7]:5d}")
            if args.gated_oracle:
                judged.append(_judge_truth(scenario, result, truth, report, settings))
                line += "  " + judged[-1][0]
            print(line, flush=True)
        r = np.array(rows)
        print(f"{est:<12} {'mean over ' + str(len(rows)):<28} {r[:, 0].mean():11.2f} {r[:, 1].mean():6.2f} "
              f"{r[:, 2].mean():10.2f} {r[:, 3].mean():6.2f} {r[:, 4].mean():10.2f} {r[:, 5].mean():6.2f} "
              f"{int(r[:, 6].sum()):5d} {int(r[:, 7].sum()):5d}")
        if judged:
            odds = np.array([j[1] for j in judged])
            print(f"the true merge set: more probable than no merge in {int(np.sum(odds[:, 0] > 0))} of {len(odds)} "
                  f"files (log odds {np.median(odds[:, 0]):.2f} median, {odds[:, 0].min():.2f} to "
                  f"{odds[:, 0].max():.2f}), verified in {int(odds[:, 1].sum())}, at least as probable as the "
                  f"pass's first choice in {int(np.sum(odds[:, 0] >= odds[:, 2] - 1e-9))}")


def _judge_truth(scenario, result, truth, report, settings) -> tuple[str, tuple[float, bool, float]]:
    """The true merge set (each late object onto the first object of its landmark) as the pass scores it."""
    first: dict[int, int] = {}
    for s in sorted(truth):
        first.setdefault(truth[s], s)
    merges = [(s, first[truth[s]]) for s in sorted(truth) if first[truth[s]] != s]
    score = score_merges(scenario, result, merges, settings)
    chosen = report.closures[0].log_bayes_factor if report.closures else 0.0
    text = (f"truth {len(merges)} merges: log odds {score.log_odds:6.2f} (Bayes factor {score.log_bayes_factor:6.2f}, "
            f"negative information {score.negative_information:+6.2f}), cost +{score.cost_rise:.2f}"
            f"{'' if score.verified else ' (fails verification)'}; first choice {chosen:6.2f}")
    return text, (score.log_odds, score.verified, chosen)


if __name__ == "__main__":
    main()
