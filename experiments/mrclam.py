"""Real data: every association strategy on the UTIAS MRCLAM dataset (issue 15 §3).

Leung et al., IJRR 2011: five robots driving among 15 identical, surveyed landmarks (cylinders
with barcodes, no class), range and bearing detections, velocity-command odometry and a Vicon
ground truth. Each robot's log, cut to windows of ``--duration`` seconds starting at ``--windows``
seconds after its first odometry record, is imported with :func:`hybridslam.datasets.mrclam.import_mrclam`
(0.5 s steps: 100 s are 200 steps; detections motion-compensated to the step times; the noise
calibrated from the window's ground truth) with the surveyed map known (every landmark an object
with its survey sd) or unknown (a discovery section: objects are created as detections arrive).
Every estimator runs on the same files; the landmarks stand in clusters 0.18-0.33 m apart, so the
data association is genuinely ambiguous for a range-bearing sensor.

Per cell (dataset, robot, window, map, estimator, smoother):

- **APE / RPE** (evo's definitions, :mod:`hybridslam.analysis.trajectory`, no alignment: x_0 is the
  ground truth) of the *online* estimate, the best component's ``pose_mean`` after each step
  ``k = 1..T``, and, where the estimator returns one (every smoother), of the *smoothed*
  trajectory ``result.trajectory`` (x_1..x_T of the final best component).
- **Dead reckoning**: the odometry ``u_k`` of the scenario composed from ``x_0``, APE / RPE the same way
  (the baseline every estimator should beat).
- **Association accuracy** against the ground truth (``true_object`` of each detection):

  * ``assoc_accuracy``: the associations of the *final* best component (its whole history, the
    hypothesis the smoothed trajectory belongs to);
  * ``assoc_accuracy_online``: the association each step's best component made for that step's
    detections, at that step.

  Known map: a detection is right when its object index equals its ``true_object`` (the map's
  objects are the landmarks in subject order). Unknown map: object indices are the estimator's own
  slots, so each estimated object is first mapped to the true landmark most of its detections came
  from (its *majority landmark*; ties to the lower index), and a detection is right when its
  object's majority landmark is its ``true_object``. This is a purity score: it counts a wrong
  merge (two landmarks in one object) against the minority's detections, but not a duplicate (one
  landmark split into two objects, both majority-mapped to it); ``num_objects`` and
  ``duplicate_objects`` (objects whose majority landmark another object also has) show those, and
  ``mixed_objects`` (objects holding detections of two or more landmarks) the merges.
  Unassociated detections (``-1``: skipped, explained as clutter, or unmapped objects when the
  object slots are full) count as wrong in both maps; ``skipped``, ``rejected`` and ``unmapped``
  (from the step infos) say how many detections each concerns.
- **Map error** (smoothers): the distance from each estimated object that has a detection (the
  result's ``objects``) to the landmark it stands for (the majority landmark on the unknown map),
  mean and median over those objects (``map_error`` in the records).
- **Time**: median and mean ms per step (``timing["step_s"]``) and the compile seconds (0 when an
  equal program was compiled earlier in the same process: the robots of one map share shapes).

Writes, under ``--output`` (default ``runs/mrclam``):

- ``scenarios/*.json``: the imported scenario files;
- ``results/<estimator>-<smoother>/*.json``: result files; ``tum/...`` trajectories (``truth``,
  ``dead-reckoning``, ``<estimator>-<smoother>`` online and ``-smoothed``) for ``evo_ape`` / ``evo_rpe``;
- ``cells.jsonl``: one record per cell, keyed by the cell and the estimator's settings
  (``estimator.settings()``), appended as each finishes: a killed run resumes where it stopped. An
  estimator that raises on a cell leaves a record with its ``error`` string (rerun those cells with
  ``--retry-errors``);
- ``errors.csv``: every cell's numbers; ``mrclam_trajectories.png``: one robot's online (red),
  smoothed (blue) and dead-reckoning (grey) trajectories against the ground truth on the landmark
  map, one panel per estimator. The table printed at the end is the mean over robots and windows
  per estimator, map and smoother.

    python experiments/mrclam.py --dataset /path/to/MRCLAM_Dataset7 [-o runs/mrclam] [--robots 1,2,3,4,5]
        [--windows 20] [--duration 100] [--maps known,unknown,unknown:N] [--estimators ml,gpda,...]
        [--smoothers full,filter,lag:L] [--motion-noise-from steps|drift] [--figure-robot N] [--retry-errors]
        [--report-only]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from collections import Counter

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from hybridslam import driver
from hybridslam.analysis import trajectory
from hybridslam.analysis.map_error import map_error, majority
from hybridslam.analysis.plot import plot_trajectory
from hybridslam.estimators import ESTIMATORS, AbstractEstimator, make_estimator
from hybridslam.estimators.smoothers import Lag, parse_smoother
from hybridslam.datasets.mrclam import import_mrclam
from hybridslam.datasets.mrclam_calibration import compose
from hybridslam.datasets.mrclam_files import MRCLAMError
from hybridslam.io.result import Result, ResultWriter, StepRecord, load_result
from hybridslam.io.scenario import Scenario, load_scenario, save_scenario
from hybridslam.studies.study import Records
from hybridslam.config import setup

setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

DEFAULT_ESTIMATORS = ("ml", "gpda", "max-mixture", "multimodal", "hybrid")
# As in the hallway study and scripts/bench_goals.py (MRCLAM): both mixtures keep 16 components; the
# hybrid gates to 3 candidate objects per detection and uses the deterministic linearized weights.
SETTINGS: dict[str, dict] = {
    "ml": {}, "gpda": {}, "max-mixture": {},
    "multimodal": {"capacity": 16},
    "hybrid": {"capacity": 16, "gate": 3, "weights": "linearized"},
}
MAPS = ("known", "unknown")
# How the importer calibrates the noise (keys of its generator.calibration); part of every cell's key,
# so that cells of files calibrated otherwise (older studies) are run again, not resumed.
NOISE_CALIBRATION = {"measurement_noise_from": "written", "motion_noise_from": "steps"}
SMOOTHERS = ("full", "filter")  # and lag:L (fixed-lag, L steps)


def _is_lag(text: str) -> bool:
    try:
        return isinstance(parse_smoother(text), Lag)
    except ValueError:
        return False

DT = 0.5


def estimator(name: str, smoother: str, max_detections: int | None = None) -> AbstractEstimator:
    """Estimator ``name`` with the study's :data:`SETTINGS` and ``smoother``; ``max_detections`` pads every
    step to that many detection slots (one compile serves every robot of a map)."""
    return make_estimator(name, smoother=smoother, max_detections=max_detections, **SETTINGS.get(name, {}))


# --------------------------------------------------------------------------- #
# Scenarios
# --------------------------------------------------------------------------- #


def parse_map(text: str) -> tuple[bool, int | None]:
    """``known``, ``unknown`` or ``unknown:N`` (an unknown map with ``N`` object slots; default the
    landmarks + 10): whether the map is unknown, and its slots if given. Raises ``ValueError``."""
    kind, _, slots = text.partition(":")
    if kind not in MAPS or (slots and kind != "unknown"):
        raise ValueError(f"{text!r}: expected known, unknown or unknown:N")
    if not slots:
        return kind == "unknown", None
    if not slots.isdigit() or int(slots) < 2:
        raise ValueError(f"{text!r}: N must be an integer >= 2 (object slots)")
    return True, int(slots)


def scenario_name(dataset: str, robot: int, start: float, duration: float, map_: str,
                  motion_noise: str = "steps") -> str:
    kind = map_.replace(":", "_slots")  # unknown:50 -> unknown_slots50
    noise = "" if motion_noise == "steps" else f"_motion-{motion_noise}"
    stem = os.path.basename(os.path.normpath(dataset))
    return f"{stem}_robot{robot}_t{start:g}_d{duration:g}_{kind}{noise}.json"


def scenario(folder: str, dataset: str, robot: int, start: float, duration: float, map_: str,
             motion_noise: str = "steps") -> tuple[str, Scenario]:
    """The imported scenario (written under ``folder/scenarios`` the first time, read back after);
    ``motion_noise``: the importer's ``motion_noise_from``. A file written by an importer that
    calibrated the noise otherwise (before 2026-11-26, or with another
    ``motion_noise``) is imported anew."""
    name = scenario_name(dataset, robot, start, duration, map_, motion_noise)
    path = os.path.join(folder, "scenarios", name)
    if os.path.exists(path):
        s = load_scenario(path)
        filtered = ((s.metadata or {}).get("generator") or {}).get("identities", {}).get("identity_filter", True)
        if _calibration(s) == {**NOISE_CALIBRATION, "motion_noise_from": motion_noise} and not filtered:
            return path, s  # a file of the oracle-assisted conversion (older importers) is imported anew
    unknown, slots = parse_map(map_)
    s = import_mrclam(dataset, robot, start=start, duration=duration, dt=DT, unknown_map=unknown,
                      max_objects=slots, motion_noise_from=motion_noise)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    save_scenario(s, path)
    return path, load_scenario(path)


def _calibration(s: Scenario) -> dict:
    """How the importer calibrated ``s``'s noise (empty for files of older importers)."""
    calibration = ((s.metadata or {}).get("generator") or {}).get("calibration") or {}
    return {k: calibration[k] for k in NOISE_CALIBRATION if k in calibration}


def dead_reckoning(s: Scenario) -> np.ndarray:
    """x_1..x_T of the odometry composed from the prior mean x_0 (the ground truth at t_0)."""
    x, out = np.asarray(s.robot_prior_mean, dtype=float), []
    for step in s.steps:
        x = compose(x, np.asarray(step.odometry, dtype=float))
        out.append(x)
    return np.stack(out)


# --------------------------------------------------------------------------- #
# Association accuracy
# --------------------------------------------------------------------------- #


def _score(pairs: list[tuple[int, int]], known_map: bool) -> dict:
    """Accuracy of (estimated object, true landmark) pairs, one per detection (module docstring)."""
    n = len(pairs)
    if not n:
        return {"accuracy": float("nan"), "detections": 0, "unassociated": 0, "num_objects": 0,
                "duplicate_objects": 0, "mixed_objects": 0}
    unassociated = sum(o < 0 for o, _ in pairs)
    if known_map:
        right = sum(o == t for o, t in pairs)
        objects, duplicates, mixed = len({o for o, _ in pairs if o >= 0}), 0, 0
    else:
        votes: dict[int, Counter] = {}
        for o, t in pairs:
            if o >= 0:
                votes.setdefault(o, Counter())[t] += 1
        landmark = majority(votes)  # of each estimated object; ties to the lower landmark index
        right = sum(o >= 0 and landmark[o] == t for o, t in pairs)
        objects = len(landmark)
        duplicates = objects - len(set(landmark.values()))
        mixed = sum(len(c) > 1 for c in votes.values())
    return {"accuracy": right / n, "detections": n, "unassociated": unassociated, "num_objects": objects,
            "duplicate_objects": duplicates, "mixed_objects": mixed}


def association_accuracy(s: Scenario, result: Result, online: list[list[int]] | None = None) -> dict:
    """``final`` (the last step's best component's history) and ``online`` (each step's best component,
    that step's associations) scores against ``true_object``. ``online[j]``: step ``j + 1``'s
    associations of that step's best component (default: read from ``result``)."""
    known_map = s.discovery is None
    final = result.steps[-1].components[0].associations
    if online is None:
        online = [list(result.steps[j].components[0].associations[j]) for j in range(len(s.steps))]
    final_pairs, online_pairs = [], []
    for j, step in enumerate(s.steps):
        for i, d in enumerate(step.detections):
            if d.true_object is None or d.true_object < 0:
                continue
            final_pairs.append((int(final[j][i]), int(d.true_object)))
            online_pairs.append((int(online[j][i]), int(d.true_object)))
    return {"final": _score(final_pairs, known_map), "online": _score(online_pairs, known_map)}


# --------------------------------------------------------------------------- #
# Cells
# --------------------------------------------------------------------------- #


def cell_key(dataset: str, robot: int, start: float, duration: float, map_: str, name: str, smoother: str,
             motion_noise: str = "steps") -> dict:
    """A cell's key: where the data come from and the estimator's settings (``max_detections``, the
    padding shared by every cell of a run, left out) and the importer's noise calibration."""
    settings = {k: v for k, v in estimator(name, smoother).settings().items() if k != "max_detections"}
    return {"dataset": os.path.basename(os.path.normpath(dataset)), "robot": robot, "start_s": start,
            "duration_s": duration, "dt_s": DT, "map": map_, "estimator": name, "smoother": smoother,
            "settings": settings, "noise": {**NOISE_CALIBRATION, "motion_noise_from": motion_noise}}


def _tum(folder: str, who: str, stem: str, poses: np.ndarray) -> None:
    path = os.path.join(folder, "tum", who, stem + ".tum")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    trajectory.write_tum(path, np.arange(1, len(poses) + 1, dtype=float), poses)


def run_cell(folder: str, dataset: str, robot: int, start: float, duration: float, map_: str, name: str,
             smoother: str, max_detections: int, motion_noise: str = "steps") -> dict:
    """Run one estimator on one scenario; write its result and TUM files; return the cell's record."""
    cell = cell_key(dataset, robot, start, duration, map_, name, smoother, motion_noise)
    t0 = time.perf_counter()
    try:
        path, s = scenario(folder, dataset, robot, start, duration, map_, motion_noise)
        stem = os.path.splitext(os.path.basename(path))[0]
        warnings: list[str] = []
        chosen: list[list[int]] = []  # each step's best component's associations of that step
        label = f"{name}-{smoother}"
        result_path = os.path.join(folder, "results", label, stem + ".json")
        os.makedirs(os.path.dirname(result_path), exist_ok=True)

        def on_step(record: StepRecord, info, seconds: float) -> None:
            writer.add(record)
            chosen.append(list(record.components[0].associations[-1]))
            warnings.extend(info.warnings())

        # Records written as they come: a whole log's fill gigabytes.
        with ResultWriter(result_path) as writer:
            run = driver.run(estimator(name, smoother, max_detections), s, on_step=on_step,
                             keep_associations=False)
            writer.finish(run.result)
        _, reference = trajectory.trajectory_from_scenario(s)
        _, online = trajectory.trajectory_from_result(run.result)
        reckoned = dead_reckoning(s)
        _tum(folder, "truth", stem, reference)
        _tum(folder, "dead-reckoning", stem, reckoned)
        _tum(folder, label, stem, online)
        smoothed = None
        if run.result.trajectory is not None:
            smoothed = trajectory.trajectory_errors(reference, run.result.trajectory[1:])
            _tum(folder, label + "-smoothed", stem, run.result.trajectory[1:])
        step_s = np.asarray(run.result.timing["step_s"])
        return {
            "cell": cell,
            "errors": trajectory.trajectory_errors(reference, online),
            "smoothed_errors": smoothed,
            "dead_reckoning": trajectory.trajectory_errors(reference, reckoned),
            "association": association_accuracy(s, run.result, chosen),
            "map_error": map_error(s, run.result),  # hybridslam.analysis.map_error
            "num_steps": s.num_steps,
            "detections": sum(len(st.detections) for st in s.steps),
            "compile_s": run.result.timing["compile_s"],
            "step_ms_median": 1e3 * float(np.median(step_s)),
            "step_ms_mean": 1e3 * float(np.mean(step_s)),
            "wall_s": time.perf_counter() - t0,
            "num_warnings": len(warnings),
            "warnings": warnings[:5],
            "skipped": int(sum(int(i.skipped) for i in run.infos)),
            "rejected": int(sum(int(i.rejected) for i in run.infos)),
            "unmapped": int(sum(int(i.unmapped) for i in run.infos)),
            "result": os.path.relpath(result_path, folder),
        }
    except Exception as e:  # noqa: BLE001 - a failing estimator (or window) is a result, not a crash
        return {"cell": cell, "error": f"{type(e).__name__}: {e}".splitlines()[0][:500],
                "wall_s": time.perf_counter() - t0}


# --------------------------------------------------------------------------- #
# Output
# --------------------------------------------------------------------------- #

CELL_COLUMNS = ("dataset", "robot", "start_s", "duration_s", "map", "estimator", "smoother")


def _row(r: dict) -> dict:
    row = {k: r["cell"][k] for k in CELL_COLUMNS}
    row["error"] = r.get("error", "")
    if "error" in r:
        return row
    for prefix, errors in (("", r["errors"]), ("smoothed_", r["smoothed_errors"] or {}),
                           ("dr_", r["dead_reckoning"])):
        for metric in ("ape_translation", "ape_rotation", "rpe_translation", "rpe_rotation"):
            for stat in ("mean", "rmse", "max"):
                row[f"{prefix}{metric}_{stat}"] = errors.get(metric, {}).get(stat, "")
    for which in ("final", "online"):
        a = r["association"][which]
        suffix = "" if which == "final" else "_online"
        row[f"assoc_accuracy{suffix}"] = a["accuracy"]
        row[f"assoc_unassociated{suffix}"] = a["unassociated"]
        row[f"num_objects{suffix}"] = a["num_objects"]
        row[f"duplicate_objects{suffix}"] = a["duplicate_objects"]
        row[f"mixed_objects{suffix}"] = a.get("mixed_objects", "")  # studies before 2026-11-26 lack it
    row["map_error_mean_m"] = r.get("map_error", {}).get("mean_m", "")  # studies before 2026-11-26 lack it
    row["map_error_median_m"] = r.get("map_error", {}).get("median_m", "")
    row.update(detections=r["detections"], num_steps=r["num_steps"], step_ms_median=r["step_ms_median"],
               step_ms_mean=r["step_ms_mean"], compile_s=r["compile_s"], wall_s=r["wall_s"],
               num_warnings=r["num_warnings"], skipped=r["skipped"], rejected=r["rejected"],
               unmapped=r.get("unmapped", ""))  # cells of studies before unmapped objects lack it
    return row


def write_csv(folder: str, records: list[dict]) -> str:
    path = os.path.join(folder, "errors.csv")
    rows = [_row(r) for r in records]
    columns = list(dict.fromkeys(k for row in rows for k in row))
    tmp = path + ".tmp"
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)
    return path


def _mean(values) -> float:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(values)) if values else float("nan")


def summarize(records: list[dict]) -> list[dict]:
    """Print (and return) the mean over robots and windows per (estimator, map, smoother)."""
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        c = r["cell"]
        groups.setdefault((c["estimator"], c["map"], c["smoother"]), []).append(r)
    head = (f"{'estimator':<12} {'map':<10} {'smoother':<8} {'cells':>5} {'APE':>7} {'APE sm':>7} {'RPE':>7} "
            f"{'assoc':>6} {'assoc@k':>7} {'map':>6} {'ms/step':>8} {'compile':>7} {'DR APE':>7}")
    print("\nmean over robots and windows: APE translation mean (m; online, smoothed), RPE translation mean "
          "(m per 0.5 s step, online),\nassociation accuracy (final best component; online), "
          "map error (m, mean; smoothers), median ms per step, "
          "compile s (max), dead-reckoning APE (m)")
    print(head)
    table = []
    for (name, map_, smoother), cells in groups.items():
        ok = [r for r in cells if "error" not in r]
        row = {
            "estimator": name, "map": map_, "smoother": smoother, "cells": len(ok), "failed": len(cells) - len(ok),
            "ape": _mean(r["errors"]["ape_translation"]["mean"] for r in ok),
            "ape_smoothed": _mean((r["smoothed_errors"] or {}).get("ape_translation", {}).get("mean") for r in ok),
            "rpe": _mean(r["errors"]["rpe_translation"]["mean"] for r in ok),
            "assoc": _mean(r["association"]["final"]["accuracy"] for r in ok),
            "assoc_online": _mean(r["association"]["online"]["accuracy"] for r in ok),
            "map": _mean(r.get("map_error", {}).get("mean_m") for r in ok),
            "ms": float(np.median([r["step_ms_median"] for r in ok])) if ok else float("nan"),
            "compile": max((r["compile_s"] for r in ok), default=float("nan")),
            "dr_ape": _mean(r["dead_reckoning"]["ape_translation"]["mean"] for r in ok),
        }
        table.append(row)
        failed = f"  ({row['failed']} failed)" if row["failed"] else ""
        print(f"{name:<12} {map_:<10} {smoother:<8} {row['cells']:>5} {row['ape']:>7.3f} {row['ape_smoothed']:>7.3f} "
              f"{row['rpe']:>7.4f} {row['assoc']:>6.3f} {row['assoc_online']:>7.3f} {row['map']:>6.3f} {row['ms']:>8.1f} "
              f"{row['compile']:>7.1f} {row['dr_ape']:>7.3f}{failed}")
    for r in records:
        if "error" in r:
            c = r["cell"]
            print(f"failed: {c['estimator']} {c['smoother']} robot {c['robot']} {c['map']} map, t {c['start_s']:g} s: "
                  f"{r['error']}")
    return table


def plot_trajectories(folder: str, dataset: str, records: list[dict], robot: int) -> str | None:
    """One panel per estimator: robot ``robot``'s first window, the known map (if run), the first smoother."""
    mine = [r for r in records if r["cell"]["robot"] == robot and "error" not in r]
    if not mine:
        return None
    maps = sorted({r["cell"]["map"] for r in mine}, key=lambda m: (m != "known", m))  # the known map first
    first = mine[0]["cell"]
    smoothers = list(dict.fromkeys(r["cell"]["smoother"] for r in mine))
    panels: dict[str, dict] = {}
    for r in mine:
        c = r["cell"]
        if (c["map"], c["smoother"], c["start_s"]) == (maps[0], smoothers[0], first["start_s"]):
            panels.setdefault(c["estimator"], r)
    names = [n for n in dict.fromkeys((*DEFAULT_ESTIMATORS, *ESTIMATORS)) if n in panels]
    fig = Figure(figsize=(3.4 * len(names), 4.2), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(names)))
    for ax, name in zip(axes, names):
        r = panels[name]
        c = r["cell"]
        s = load_scenario(os.path.join(folder, "scenarios",
                                       scenario_name(dataset, robot, c["start_s"], c["duration_s"], c["map"],
                                                     c.get("noise", {}).get("motion_noise_from", "steps"))))
        result = load_result(os.path.join(folder, r["result"]))
        reckoned = np.concatenate([np.asarray(s.robot_prior_mean)[None], dead_reckoning(s)])
        ax.plot(reckoned[:, 0], reckoned[:, 1], ":", color="0.5", lw=1.2, label="dead reckoning")
        if result.trajectory is not None:
            ax.plot(result.trajectory[:, 0], result.trajectory[:, 1], "-", color="C0", lw=1.3, label="smoothed")
        sm = (r["smoothed_errors"] or {}).get("ape_translation", {}).get("mean")
        title = (f"{name}: APE {r['errors']['ape_translation']['mean']:.2f} m"
                 + (f" (smoothed {sm:.2f})" if sm is not None else "")
                 + f"\nassociations {100 * r['association']['final']['accuracy']:.0f}% right")
        plot_trajectory(ax, s, result, title=title, label="online (best component)")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)
    fig.suptitle(f"MRCLAM {first['dataset']}, robot {robot}, {first['start_s']:g}-"
                 f"{first['start_s'] + first['duration_s']:g} s, {maps[0]} map, smoother {smoothers[0]}",
                 fontsize=10)
    path = os.path.join(folder, "mrclam_trajectories.png")
    fig.savefig(path, dpi=110)
    return path


def main(dataset: str, output: str = os.path.join("runs", "mrclam"), robots=(1, 2, 3, 4, 5), windows=(20.0,),
         duration: float = 100.0, maps=("known",), estimators=DEFAULT_ESTIMATORS, smoothers=("full",),
         figure_robot: int | None = None, retry_errors: bool = False, report_only: bool = False,
         motion_noise: str = "steps") -> list[dict]:
    estimators, maps, smoothers = list(estimators), list(maps), list(smoothers)
    for option, given, known in (("--estimators", estimators, ESTIMATORS), ("--smoothers", smoothers, SMOOTHERS)):
        unknown = [n for n in given if n not in known and not (option == "--smoothers" and _is_lag(n))]
        if unknown:
            raise SystemExit(f"{option}: unknown {', '.join(unknown)} (known: {', '.join(known)}, lag:L)")
    for map_ in maps:
        try:
            parse_map(map_)
        except ValueError as e:
            raise SystemExit(f"--maps: {e}") from None
    os.makedirs(output, exist_ok=True)
    data = [(robot, float(start), map_) for map_ in maps for robot in robots for start in windows]
    cells = [(robot, start, map_, name, smoother) for map_ in maps for smoother in smoothers
             for name in estimators for robot in robots for start in windows]
    with Records(output, {"study": "mrclam"}) as records:  # the folder is locked until the end
        def done(c):
            key = cell_key(dataset, c[0], c[1], duration, c[2], c[3], c[4], motion_noise)
            return key in records and not (retry_errors and "error" in records.done[json.dumps(key, sort_keys=True)])

        pending = [c for c in cells if not done(c)]
        todo = [] if report_only else pending
        print(f"{len(cells)} cells ({len(estimators)} estimators x {len(smoothers)} smoothers x {len(maps)} maps x "
              f"{len(robots)} robots x {len(windows)} windows of {duration:g} s); {len(cells) - len(pending)} done "
              "already" + ("; running none (--report-only)" if report_only else ""), flush=True)
        max_detections = 1
        for robot, start, map_ in data:
            try:
                max_detections = max(max_detections, scenario(output, dataset, robot, start, duration, map_, motion_noise)[1]
                                     .max_detections)
            except MRCLAMError as e:  # recorded per cell by run_cell
                print(f"robot {robot}, {start:g} s, {map_} map: {e}", flush=True)
        t0 = time.perf_counter()
        progress = tqdm(todo, desc="mrclam cells", unit="cell")
        program = None
        for robot, start, map_, name, smoother in progress:
            progress.set_postfix_str(f"{name} {smoother} robot {robot} {map_}")
            if (map_, name, smoother) != program:  # the cells of one program are consecutive
                driver.clear_compiled()  # 30 kept programs would exhaust the memory maps (see its docstring)
                program = (map_, name, smoother)
            records.append(run_cell(output, dataset, robot, start, duration, map_, name, smoother, max_detections,
                                    motion_noise))
        keys = {json.dumps(cell_key(dataset, c[0], c[1], duration, c[2], c[3], c[4], motion_noise), sort_keys=True)
                for c in cells}
        finished = [records.done[k] for k in keys if k in records.done]
    order = {json.dumps(cell_key(dataset, *c[:2], duration, *c[2:], motion_noise), sort_keys=True): i
             for i, c in enumerate(cells)}
    finished.sort(key=lambda r: order[json.dumps(r["cell"], sort_keys=True)])
    print(f"ran {len(todo)} cells in {time.perf_counter() - t0:.0f} s; wrote {write_csv(output, finished)}")
    summarize(finished)
    path = plot_trajectories(output, dataset, finished, robots[0] if figure_robot is None else figure_robot)
    if path:
        print(f"wrote {path}")
    return finished


def _numbers(text: str, kind=float) -> list:
    return [kind(v) for v in text.split(",") if v.strip()]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", default=os.environ.get("MRCLAM_DATASET", os.path.join("data", "MRCLAM_Dataset7")),
                        help="an MRCLAM dataset folder (default $MRCLAM_DATASET or data/MRCLAM_Dataset7)")
    parser.add_argument("-o", "--output", default=os.path.join("runs", "mrclam"))
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--windows", default="20", help="window start times, s after each robot's first odometry")
    parser.add_argument("--duration", type=float, default=100.0, help="seconds per window (0.5 s steps)")
    parser.add_argument("--maps", default="known",
                        help="known, unknown, unknown:N (N object slots; default the landmarks + 10), "
                             "comma-separated")
    parser.add_argument("--estimators", default=",".join(DEFAULT_ESTIMATORS))
    parser.add_argument("--smoothers", default="full", help="full, filter, lag:L, incremental:L (comma-separated)")
    parser.add_argument("--figure-robot", type=int, default=None, help="the robot drawn (default: the first)")
    parser.add_argument("--motion-noise-from", default="steps", choices=("steps", "drift"),
                        help="the importer's motion_cov calibration (default steps; drift: from 5-40 s sums)")
    parser.add_argument("--retry-errors", action="store_true", help="run the cells that failed before again")
    parser.add_argument("--report-only", action="store_true",
                        help="run nothing: the table, errors.csv and figure of the finished cells of this grid")
    a = parser.parse_args()
    from hybridslam.cli import cache

    cache.enable()  # JAX's persistent compilation cache, as the hybridslam command uses
    main(a.dataset, a.output, _numbers(a.robots, int), _numbers(a.windows), a.duration, a.maps.split(","),
         a.estimators.split(","), a.smoothers.split(","), a.figure_robot, a.retry_errors, a.report_only,
         a.motion_noise_from)
