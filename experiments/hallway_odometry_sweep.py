"""Doherty's hallway study (thesis Sec. 5.4.1, Fig. 5-3): every association strategy against odometry noise.

The simulated hallway loop of :mod:`hybridslam.sim.hallway` (landmarks of 2 classes in aliased rows,
120° / 3.5 m field of view, range and bearing noise variance 0.01, a 90%-accurate confusion
matrix, an unknown map). For each odometry noise level ``tr(Λ_t)`` (five, 0.005 to 0.05) and
each seed, one scenario; every estimator runs on the same files. Reports, per estimator, the
average translation error (APE translation mean over the run, thesis Fig. 5-3d) against
``tr(Λ_t)`` with a least-squares line, and draws one trajectory per estimator like Fig. 5-3a-c
(ground truth dashed, landmarks colored by class) on the thesis's example ``Λ_t = diag(0.01,
0.01, 0.001)``.

Writes, under ``--output``:

- ``scenarios/*.json``: the scenario files (for other implementations);
- ``results/<estimator>/*.json``: result files; ``tum/<estimator>/*.tum`` and ``tum/truth/*.tum``
  trajectories for ``evo_ape`` / ``evo_rpe``;
- ``cells.jsonl``: one record per (estimator, level, seed), keyed by the estimator's settings
  (``estimator.settings()``), appended as each finishes: a killed run resumes where it stopped (same
  settings; cells of other settings run afresh);
- ``errors.csv``: APE/RPE statistics of every cell; ``hallway_error.png``, ``hallway_trajectories.png``.

    python experiments/hallway_odometry_sweep.py [-o runs/hallway] [--seeds 3] [--estimators ml,gpda,...]

``--first-seed N`` starts the seeds at ``N`` (held-out files: seeds no earlier study used);
``--new-landmark mahalanobis:TAU`` gives every estimator the thesis's new-landmark rule (Sec.
3.2.1; :mod:`hybridslam.estimators.novelty`) instead of the density rule; write each rule to its own
folder. Beside the errors it prints, per estimator, the recall of the true loop closure
(:func:`hybridslam.analysis.recall.closure_recall`): the runs whose top component associates every
loop-closing re-detection right, the runs where some kept component does, and their final-pose errors.

``--estimators`` also takes ``hybrid+loops`` and ``multimodal+loops``: the hybrid belief or
``multimodal`` with loop closure during the run
(:class:`hybridslam.estimators.loops.online.OnlineLoopClosure`, the pass's default settings);
``--loop-threshold X`` sets its least log odds of a closure against the component searched
(``LoopClosureSettings.threshold``, default 0; -5.01 = -log 150 adds every closure the hybrid
belief's pruning would keep); ``--loop-misses point`` charges its negative information at the point
estimate (``LoopClosureSettings.misses``; default ``marginal``); ``--capacity N`` sets the hybrid
belief's and ``multimodal``'s components (default 16). ``--prune-ratio R`` sets the hybrid belief's pruning ratio (default 150, the
paper's, Sec. V); ``--merge-threshold D2`` merges its equivalent components (``Hybrid.merge_threshold``, default none).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import time

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from hybridslam import driver
from hybridslam.analysis import trajectory
from hybridslam.analysis.map_error import map_error
from hybridslam.analysis.recall import closure_recall
from hybridslam.analysis.plot import plot_trajectory
from hybridslam.estimators import ESTIMATORS, AbstractEstimator, make_estimator
from hybridslam.estimators.loops.online import OnlineLoopClosure
from hybridslam.estimators.loops.settings import MISS_MODELS, LoopClosureSettings
from hybridslam.io.result import load_result, save_result
from hybridslam.io.scenario import load_scenario, save_scenario
from hybridslam.sim import hallway
from hybridslam.studies.study import Records
from hybridslam.config import setup

setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

EXAMPLE_TRACE = 0.021  # the thesis's Fig. 5-3a-c example, Λ_t = diag(0.01, 0.01, 0.001)
DEFAULT_ESTIMATORS = ("ml", "gpda", "max-mixture", "multimodal", "hybrid")
# Options per estimator (hybridslam.make_estimator keywords); the estimator's settings are part of
# each cell's key: both mixtures keep 16 components; the hybrid gates to 3 candidate objects per
# detection (its exact enumeration over ~70 object slots is intractable) and uses the deterministic
# linearized weights (scripts/bench_estimators.py: ~0.4-0.5 s per step for either on this
# 213-dimensional state).
SETTINGS: dict[str, dict] = {
    "ml": {}, "gpda": {}, "max-mixture": {},
    "multimodal": {"capacity": 16},
    "hybrid": {"capacity": 16, "gate": 3, "weights": "linearized"},
}


NEW_LANDMARK = "density"  # main(new_landmark=...): every estimator's rule for a new object (.novelty)
LOOPS = LoopClosureSettings()  # main(loop_threshold=...): the settings of loop closure during the run
PRUNE_RATIO: float | None = None  # main(prune_ratio=...): the hybrid belief's (None: its default, Sec. V's 150)
CAPACITY: int | None = None  # main(capacity=...): the mixtures' components (None: SETTINGS', 16)
MERGE: float | None = None  # main(merge=...): the hybrid belief's Hybrid.merge_threshold (None: no merging)
SMOOTHER = "full"  # main(smoother=...): "full" (the papers' smoothers, the default) or "filter"
# Not estimators of their own: the hybrid belief or multimodal with loop closure during the run
# (merge hypotheses added between steps, hybridslam.estimators.loops.online; full smoother only).
LOOPS_SUFFIX = "+loops"
ONLINE_NAMES = ("hybrid+loops", "multimodal+loops")


def estimator(name: str, max_detections: int | None = None) -> AbstractEstimator:
    """Estimator ``name`` with the study's :data:`SETTINGS` and :data:`SMOOTHER`; ``max_detections`` pads
    every step to that many detection slots (``None``: the scenario's largest step)."""
    base = name.removesuffix(LOOPS_SUFFIX) if name in ONLINE_NAMES else name
    extra: dict = {"prune_ratio": PRUNE_RATIO} if base == "hybrid" and PRUNE_RATIO is not None else {}
    if CAPACITY is not None and "capacity" in SETTINGS.get(base, {}):
        extra["capacity"] = CAPACITY
    if MERGE is not None and base == "hybrid":
        extra["merge_threshold"] = MERGE
    return make_estimator(base, max_detections=max_detections, smoother=SMOOTHER, new_landmark=NEW_LANDMARK,
                          **{**SETTINGS.get(base, {}), **extra})


def _scenario(folder: str, trace: float, seed: int, steps: int | None):
    path = os.path.join(folder, "scenarios", hallway.scenario_name(trace, seed))
    if not os.path.exists(path):
        os.makedirs(os.path.dirname(path), exist_ok=True)
        save_scenario(hallway.hallway(seed, trace, steps=steps), path)
    return path, load_scenario(path)


def run_cell(folder: str, name: str, trace: float, seed: int, steps: int | None, max_detections: int) -> dict:
    """Run estimator ``name`` on one scenario; write its result and TUM files; return the cell's record.

    ``max_detections`` is the same for every cell, so each estimator compiles its step once.
    """
    path, scenario = _scenario(folder, trace, seed, steps)
    stem = os.path.splitext(os.path.basename(path))[0]
    warnings: list[str] = []
    est = estimator(name, max_detections)
    hook = OnlineLoopClosure(est, scenario, LOOPS) if name in ONLINE_NAMES else None
    run = driver.run(est, scenario, seed=seed, on_step=lambda r, info, s: warnings.extend(info.warnings()),
                     between_steps=hook)
    result_path = os.path.join(folder, "results", name, stem + ".json")
    os.makedirs(os.path.dirname(result_path), exist_ok=True)
    save_result(run.result, result_path)
    stamps, estimate = trajectory.trajectory_from_result(run.result)
    t_ref, reference = trajectory.trajectory_from_scenario(scenario)
    for who, (t, poses) in (("truth", (t_ref, reference)), (name, (stamps, estimate))):
        tum = os.path.join(folder, "tum", who, stem + ".tum")
        os.makedirs(os.path.dirname(tum), exist_ok=True)
        trajectory.write_tum(tum, t, poses)
    smoothed = trajectory.smoothed_trajectory_from_result(run.result)
    if smoothed is not None:
        tum = os.path.join(folder, "tum", name + "-smoothed", stem + ".tum")
        os.makedirs(os.path.dirname(tum), exist_ok=True)
        trajectory.write_tum(tum, *smoothed)
    step_s = run.result.timing["step_s"]
    return {
        "cell": _cell(name, trace, seed),
        "errors": trajectory.trajectory_errors(reference, estimate),
        # The final smoothed trajectory (the thesis's "smoothed" APE/RPE), absent when filtering.
        "errors_smoothed": None if smoothed is None else trajectory.trajectory_errors(reference, smoothed[1]),
        "compile_s": run.result.timing["compile_s"],
        "step_ms_median": 1e3 * float(np.median(step_s)),
        "num_warnings": len(warnings),
        "warnings": warnings[:5],
        "result": os.path.relpath(result_path, folder),
        # Loop closure during the run: the hypotheses it added (ClosureHypothesis text each).
        **({"closures": [str(c) for c in hook.closures]} if hook is not None else {}),
    }


def _cell(name: str, trace: float, seed: int) -> dict:
    """A cell's key: the estimator's settings (``estimator.settings()``), the noise level and the seed.

    The detection slots every cell is padded to (``max_detections``, the largest step of any
    scenario of the run) are left out of the key, as before, so that resuming with more seeds or
    levels does not rerun the finished cells.
    """
    settings = {k: v for k, v in estimator(name).settings().items() if k != "max_detections"}
    if name in ONLINE_NAMES:
        settings["loop_closure"] = dataclasses.asdict(LOOPS)
    return {"estimator": name, "trace": trace, "seed": seed, "settings": settings}


def final_error(folder: str, record: dict) -> float:
    """Translation error of the last pose (m), after the loop has closed: for a filter this, not the
    APE over the run, shows how well the loop closure corrected the estimate (read from the TUM files)."""
    cell = record["cell"]
    stem = os.path.splitext(hallway.scenario_name(cell["trace"], cell["seed"]))[0]
    _, truth = trajectory.read_tum(os.path.join(folder, "tum", "truth", stem + ".tum"))
    _, estimate = trajectory.read_tum(os.path.join(folder, "tum", cell["estimator"], stem + ".tum"))
    return float(np.linalg.norm(estimate[-1, :2] - truth[-1, :2]))


def _write_csv(folder: str, records: list[dict]) -> str:
    path = os.path.join(folder, "errors.csv")
    rows = []
    for r in records:
        row = dict(r["cell"])
        for metric, stats in r["errors"].items():
            row.update({f"{metric}_{k}": v for k, v in stats.items()})
        for metric, stats in (r.get("errors_smoothed") or {}).items():
            row.update({f"smoothed_{metric}_{k}": v for k, v in stats.items()})
        row.update(final_translation=final_error(folder, r), step_ms_median=r["step_ms_median"],
                   compile_s=r["compile_s"], num_warnings=r["num_warnings"])
        rows.append(row)
    tmp = path + ".tmp"
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)
    return path


def summarize(records: list[dict], estimators: list[str], levels: list[float]) -> dict[str, tuple]:
    """Print mean APE translation per estimator and level, with the least-squares line; return the lines."""
    lines = {}
    print(f"\naverage translation error (APE translation mean, m), mean over seeds; line: error = a + b tr(Λ_t)")
    print(f"{'estimator':<12} " + " ".join(f"{t:>8.4f}" for t in levels) + f" {'a':>8} {'b':>8} {'step ms':>8} "
          f"{'smoothed':>8}")
    for name in estimators:
        cells = [r for r in records if r["cell"]["estimator"] == name and r["cell"]["trace"] in levels]
        if not cells:
            continue
        x = np.array([r["cell"]["trace"] for r in cells])
        y = np.array([r["errors"]["ape_translation"]["mean"] for r in cells])
        means = [float(np.mean(y[x == t])) if np.any(x == t) else float("nan") for t in levels]
        b, a = np.polyfit(x, y, 1) if len(set(x)) > 1 else (float("nan"), float(np.mean(y)))
        lines[name] = (a, b)
        ms = np.median([r["step_ms_median"] for r in cells])
        sm = [r["errors_smoothed"]["ape_translation"]["mean"] for r in cells if r.get("errors_smoothed")]
        smoothed = float(np.mean(sm)) if sm else float("nan")  # the smoothed trajectory's APE, all levels
        print(f"{name:<12} " + " ".join(f"{m:>8.3f}" for m in means) + f" {a:>8.3f} {b:>8.2f} {ms:>8.1f} "
              f"{smoothed:>8.3f}")
    return lines


def summarize_final(folder: str, records: list[dict], estimators: list[str], levels: list[float]) -> None:
    """Print the mean translation error of the last pose (after the loop closure) per estimator and level."""
    print("\ntranslation error of the last pose, after the loop closure (m), mean over seeds")
    print(f"{'estimator':<12} " + " ".join(f"{t:>8.4f}" for t in levels) + f" {'all':>8}")
    for name in estimators:
        cells = [r for r in records if r["cell"]["estimator"] == name and r["cell"]["trace"] in levels]
        if not cells:
            continue
        err = {t: [final_error(folder, r) for r in cells if r["cell"]["trace"] == t] for t in levels}
        means = [float(np.mean(err[t])) if err[t] else float("nan") for t in levels]
        every = [e for t in levels for e in err[t]]
        print(f"{name:<12} " + " ".join(f"{m:>8.3f}" for m in means) + f" {np.mean(every):>8.3f}")


def summarize_map(folder: str, records: list[dict], estimators: list[str], levels: list[float]) -> None:
    """Print the mean map error per estimator and level (smoothers; read from the result files):
    each estimated object with a detection against the true landmark most of its detections came
    from (:func:`hybridslam.analysis.map_error.map_error`)."""
    print("\nmap error: mean distance (m) of each object to its majority landmark, mean over seeds (smoothers)")
    print(f"{'estimator':<12} " + " ".join(f"{t:>8.4f}" for t in levels) + f" {'all':>8}")
    for name in estimators:
        cells = [r for r in records if r["cell"]["estimator"] == name and r["cell"]["trace"] in levels]
        err: dict[float, list[float]] = {t: [] for t in levels}
        for r in cells:
            _, scenario = _scenario(folder, r["cell"]["trace"], r["cell"]["seed"], None)
            mapped = map_error(scenario, load_result(os.path.join(folder, r["result"])))
            if "mean_m" in mapped:
                err[r["cell"]["trace"]].append(mapped["mean_m"])
        every = [e for t in levels for e in err[t]]
        if every:
            means = [float(np.mean(err[t])) if err[t] else float("nan") for t in levels]
            print(f"{name:<12} " + " ".join(f"{m:>8.3f}" for m in means) + f" {np.mean(every):>8.3f}")


def summarize_recall(folder: str, records: list[dict], estimators: list[str], steps: int | None) -> None:
    """Print, per estimator, the recall of the true loop closure over its runs
    (:func:`hybridslam.analysis.recall.closure_recall`): re-detections the top component closes right,
    runs it closes whole, runs where some kept component does, and the mean final-pose error of the top
    component and, where one holds the truth, of the highest-weight one that does."""
    print("\nloop closure against the truth: re-detections closed right by the top component; runs closed "
          "whole by the top / by some kept component; final-pose error (m) of the top and of that component")
    print(f"{'estimator':<13} {'re-dets':>9} {'top runs':>9} {'kept runs':>9} {'top err':>8} {'kept err':>9} "
          f"{'components':>10}")
    for name in estimators:
        cells = [r for r in records if r["cell"]["estimator"] == name]
        recs = []
        for r in cells:
            _, scenario = _scenario(folder, r["cell"]["trace"], r["cell"]["seed"], steps)
            recs.append(closure_recall(scenario, load_result(os.path.join(folder, r["result"]))))
        if not recs:
            continue
        kept = [x.kept_error for x in recs if x.kept_error is not None]
        print(f"{name:<13} {sum(x.top_closed for x in recs):>4}/{sum(x.redetections for x in recs):<4} "
              f"{sum(x.top_right for x in recs):>4}/{len(recs):<4} {sum(x.kept for x in recs):>4}/{len(recs):<4} "
              f"{np.mean([x.top_error for x in recs]):>8.2f} {np.mean(kept) if kept else float('nan'):>9.2f} "
              f"{np.mean([x.components for x in recs]):>10.1f}")


def plot_errors(folder: str, records: list[dict], estimators: list[str], levels: list[float], lines: dict) -> str:
    fig = Figure(figsize=(6.5, 4.5), layout="constrained")
    ax = fig.subplots()
    grid = np.linspace(min(levels), max(levels), 50)
    for i, name in enumerate(n for n in estimators if n in lines):
        cells = [r for r in records if r["cell"]["estimator"] == name and r["cell"]["trace"] in levels]
        x = np.array([r["cell"]["trace"] for r in cells])
        y = np.array([r["errors"]["ape_translation"]["mean"] for r in cells])
        ax.scatter(x, y, s=14, color=f"C{i}", alpha=0.6)
        a, b = lines[name]
        ax.plot(grid, a + b * grid, color=f"C{i}", label=f"{name} (slope {b:.1f})")
    ax.set_xlabel(r"tr($\Lambda_t$)")
    ax.set_ylabel("average translation error [m]")
    ax.set_title("Hallway: translation error against odometry noise (thesis Fig. 5-3d)", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    path = os.path.join(folder, "hallway_error.png")
    fig.savefig(path, dpi=120)
    return path


def plot_examples(folder: str, records: list[dict], estimators: list[str]) -> str:
    cells = {r["cell"]["estimator"]: r for r in records if r["cell"]["trace"] == EXAMPLE_TRACE}
    names = [n for n in estimators if n in cells]
    fig = Figure(figsize=(4.2 * len(names), 3.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(names)))
    for ax, name in zip(axes, names):
        r = cells[name]
        scenario = load_scenario(os.path.join(folder, "scenarios", hallway.scenario_name(EXAMPLE_TRACE,
                                                                                          r["cell"]["seed"])))
        plot_trajectory(ax, scenario, load_result(os.path.join(folder, r["result"])),
                        title=f"{name}: APE {r['errors']['ape_translation']['mean']:.2f} m")
    path = os.path.join(folder, "hallway_trajectories.png")
    fig.savefig(path, dpi=120)
    return path


def main(output: str = os.path.join("runs", "hallway"), seeds: int = 3, estimators=DEFAULT_ESTIMATORS,
         levels=hallway.LEVELS, steps: int | None = None, smoother: str = "full", first_seed: int = 0,
         new_landmark: str = "density", loop_threshold: float = 0.0, loop_tries: int = 8,
         prune_ratio: float | None = None, loop_misses: str = LoopClosureSettings.misses,
         capacity: int | None = None, merge: float | None = None) -> list[dict]:
    global SMOOTHER, NEW_LANDMARK, LOOPS, PRUNE_RATIO, CAPACITY, MERGE
    SMOOTHER, NEW_LANDMARK, PRUNE_RATIO, CAPACITY, MERGE = smoother, new_landmark, prune_ratio, capacity, merge
    LOOPS = LoopClosureSettings(threshold=loop_threshold, tries=loop_tries, misses=loop_misses)
    estimators, levels = list(estimators), [float(t) for t in levels]
    unknown = [n for n in estimators if n not in ESTIMATORS and n not in ONLINE_NAMES]
    if unknown:
        raise SystemExit(f"--estimators: unknown {', '.join(unknown)} (known: {', '.join([*ESTIMATORS, *ONLINE_NAMES])})")
    os.makedirs(output, exist_ok=True)
    with Records(output, {"study": "hallway", "steps": steps}) as records:  # the folder is locked until the end
        cells = [(n, t, s) for t in levels for s in range(first_seed, first_seed + seeds) for n in estimators]
        cells += [(n, EXAMPLE_TRACE, first_seed) for n in estimators if (n, EXAMPLE_TRACE, first_seed) not in cells]
        todo = [c for c in cells if _cell(*c) not in records]
        print(f"{len(cells)} cells ({len(estimators)} estimators x {len(levels)} levels x {seeds} seeds from "
              f"{first_seed}, and the example at tr = {EXAMPLE_TRACE}); {len(cells) - len(todo)} done already",
              flush=True)
        max_detections = max(max(_scenario(output, t, s, steps)[1].max_detections, 1) for _, t, s in cells)
        t0 = time.perf_counter()
        for name, trace, seed in tqdm(todo, desc="hallway cells", unit="cell"):
            records.append(run_cell(output, name, trace, seed, steps, max_detections))
        keys = {json.dumps(_cell(*c), sort_keys=True) for c in cells}
        done = [r for k, r in records.done.items() if k in keys]  # this run's cells, not older settings
    print(f"ran {len(todo)} cells in {time.perf_counter() - t0:.0f} s; wrote {_write_csv(output, done)}")
    lines = summarize(done, estimators, levels)
    summarize_final(output, done, estimators, levels)
    summarize_map(output, done, estimators, levels)
    summarize_recall(output, done, estimators, steps)
    print(f"wrote {plot_errors(output, done, estimators, levels, lines)}")
    print(f"wrote {plot_examples(output, done, estimators)}")
    return done


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", default=os.path.join("runs", "hallway"))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--estimators", default=",".join(DEFAULT_ESTIMATORS))
    parser.add_argument("--steps", type=int, default=None, help="steps per run (default: one loop)")
    parser.add_argument("--levels", default=",".join(str(t) for t in hallway.LEVELS),
                        help="odometry noise levels tr(Λ_t) (default: the thesis's five)")
    parser.add_argument("--smoother", default="full", help="full, lag:L, incremental:L or filter")
    parser.add_argument("--first-seed", type=int, default=0, help="the first seed (default 0)")
    parser.add_argument("--new-landmark", default="density",
                        help="every estimator's new-landmark rule: density (default) or mahalanobis:TAU")
    parser.add_argument("--loop-threshold", type=float, default=0.0,
                        help="+loops: the least log odds of a closure against the component searched (default 0)")
    parser.add_argument("--loop-tries", type=int, default=8,
                        help="+loops: the merge sets re-solved and verified per round (default 8)")
    parser.add_argument("--loop-misses", choices=MISS_MODELS, default=LoopClosureSettings.misses,
                        help="+loops: a miss weighed by how surely the object was in view (marginal, default) or "
                             "counted at the point estimate (point)")
    parser.add_argument("--prune-ratio", type=float, default=None,
                        help="the hybrid belief's: drop components below w_max / R (default: 150, the paper's)")
    parser.add_argument("--capacity", type=int, default=None,
                        help="the hybrid belief's and multimodal's components (default 16)")
    parser.add_argument("--merge-threshold", type=float, default=None,
                        help="the hybrid belief's Hybrid.merge_threshold (squared Mahalanobis; default: none)")
    a = parser.parse_args()
    main(a.output, a.seeds, a.estimators.split(","), [float(t) for t in a.levels.split(",")], a.steps, a.smoother,
         a.first_seed, a.new_landmark, a.loop_threshold, a.loop_tries, a.prune_ratio, a.loop_misses, a.capacity,
         a.merge_threshold)
