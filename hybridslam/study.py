"""Simulation studies and batch runs over scenario files: grids of cells, resumable records, a table.

A study is a grid of **cells**. Each cell is one batched run (:func:`hybridslam.sweep.run_batch`)
of a set of tracks:

- :class:`AlphaStudy` (the paper's Fig. 5): one cell per (alpha, classifier model); its tracks
  are ``tracks`` paper-setup scenarios simulated with seeds ``seed + t`` at that alpha (the same
  trajectories for every alpha: only the scores change), run with the given model.
- :class:`FileStudy`: one cell per (group of scenario files of equal shape and model, model);
  every file also gets a result file.

Every finished cell is appended as one JSON line to ``cells.jsonl`` in the output folder (flushed
and fsynced), after a header line with the settings that fix the numbers. Started again on the
same folder, a study skips the cells already recorded — a run killed half way and restarted ends
with the same table as one that never stopped — and refuses to mix in records made with other
settings. The table (``table.csv``, one row per track and step) is rewritten from the records
after every cell.
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import json
import math
import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import jax
import numpy as np

from .belief import Config
from .classifier import ClassifierModel
from .result import Result, save_result
from .run import config_for, describe
from .scenario import Scenario, load_scenario
from .simulate import simulate
from .sweep import BatchRun, batch_inputs, device_mesh, run_batch, step_records

RECORDS = "cells.jsonl"
TABLE = "table.csv"
RECORD_FORMAT = "hybridslam-sweep/1"
METRICS = ("entropy", "det_cov", "err_wmax", "err_wavg", "num_components")
DIAGNOSTICS = ("dropped_capacity", "visibility_ignored", "gn_failures", "min_ess", "is_failures")
ALPHA_COLUMNS = ("alpha", "model", "track", "seed", "step", *METRICS)
FILE_COLUMNS = ("scenario", "model", "track", "step", *METRICS)


class StudyError(ValueError):
    """A study that cannot run as asked (bad grid, records made with other settings)."""


@dataclasses.dataclass(frozen=True)
class Estimator:
    """Estimator settings shared by every cell of a study (they fix the numbers)."""

    weights: str = "laplace-is"
    samples: int | None = None  # draws of the weight method; None: its default
    capacity: int = 16  # small: a batch pays for the largest live set of any of its tracks
    prune_ratio: float = 150.0

    def config(self, scenario: Scenario, max_detections: int) -> Config:
        return config_for(scenario, capacity=self.capacity, num_samples=self.samples, weights=self.weights,
                          max_detections=max_detections)


@dataclasses.dataclass(frozen=True)
class AlphaStudy:
    """The paper's statistical study (Sec. V, Fig. 5): alphas × models × tracks of paper-setup scenarios."""

    alphas: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
    models: tuple[str, ...] = ("mirror", "independent", "none")
    tracks: int = 50
    steps: int = 10
    K: float = 15.0
    seed: int = 0  # track t: scenario seed and weights seed seed + t
    estimator: Estimator = Estimator()

    def __post_init__(self):
        if not self.alphas or not all(math.isfinite(a) for a in self.alphas):
            raise StudyError(f"alphas: expected finite numbers, got {list(self.alphas)}")
        if len(set(self.alphas)) != len(self.alphas) or len(set(self.models)) != len(self.models):
            raise StudyError("alphas and models must not repeat")
        for name in ("tracks", "steps"):
            if getattr(self, name) < 1:
                raise StudyError(f"{name}: expected a positive number, got {getattr(self, name)}")

    def header(self) -> dict:
        """The settings every record of this study depends on (not the grid: cells carry their own)."""
        return {"kind": "alpha", "tracks": self.tracks, "steps": self.steps, "K": self.K, "seed": self.seed,
                **dataclasses.asdict(self.estimator)}

    def cells(self) -> list[dict]:
        return [{"alpha": float(a), "model": m} for a in self.alphas for m in self.models]


@dataclasses.dataclass(frozen=True)
class FileStudy:
    """Runs over scenario files; ``models=None`` runs each file with the classifier it names."""

    paths: tuple[str, ...]
    models: tuple[str, ...] | None = None
    seed: int = 0  # the weights' PRNG seed of every run (as ``hybridslam run --seed``)
    estimator: Estimator = Estimator()

    def header(self) -> dict:
        return {"kind": "files", "seed": self.seed, **dataclasses.asdict(self.estimator)}


LEARNED_PREFIX = "learned:"


def resolve_model(name: str) -> str | ClassifierModel:
    """A study's model name as :func:`~hybridslam.sweep.batch_inputs` takes it.

    ``"mirror"``, ``"independent"``, ``"none"`` stay names (alpha and K come from each scenario);
    ``"learned:PATH"`` loads the learned classifier in the model file ``PATH`` (its fitted h_c and
    Σ_c replace the true model's, for every alpha).
    """
    if name.startswith(LEARNED_PREFIX):
        from .learned import load_classifier

        return load_classifier(name[len(LEARNED_PREFIX):])
    return name


def scenario_paths(pattern: str) -> list[str]:
    """The scenario files named by a folder (its ``*.json``) or a glob pattern, sorted."""
    if os.path.isdir(pattern):
        paths = sorted(glob.glob(os.path.join(pattern, "*.json")))
    else:
        paths = sorted(p for p in glob.glob(pattern, recursive=True) if os.path.isfile(p))
    if not paths:
        raise StudyError(f"--scenarios {pattern!r}: no scenario files found")
    return paths


# --------------------------------------------------------------------------- #
# The append-only record file
# --------------------------------------------------------------------------- #


def _cell_key(cell: dict) -> str:
    return json.dumps(cell, sort_keys=True)


class Records:
    """``cells.jsonl``: a header line, then one line per finished cell. Append-only.

    A last line cut short by a kill is discarded (the file is truncated back to the last complete
    line before anything is appended).
    """

    def __init__(self, folder: str, header: dict):
        self.path = os.path.join(folder, RECORDS)
        self.done: dict[str, dict] = {}
        head = {"format": RECORD_FORMAT, **header}
        if not os.path.exists(self.path) and not _writer():
            return
        if not os.path.exists(self.path):
            with open(self.path, "w", encoding="utf-8") as f:
                f.write(json.dumps(head) + "\n")
            return
        with open(self.path, "rb") as f:
            data = f.read()
        end = data.rfind(b"\n") + 1
        lines = data[:end].decode("utf-8").splitlines()
        if not lines:
            raise StudyError(f"{self.path}: empty or cut-off header; remove the file to start afresh")
        try:
            old = json.loads(lines[0])
        except json.JSONDecodeError:
            raise StudyError(f"{self.path}: line 1 is not a sweep header; remove the file to start afresh") from None
        if old != head:
            diff = [f"{k}: {old.get(k)!r} there, {head.get(k)!r} now" for k in sorted(set(old) | set(head))
                    if old.get(k) != head.get(k)]
            raise StudyError(
                f"{self.path} holds a study with other settings ({'; '.join(diff)}); use another output "
                "folder, or the same settings to resume it"
            )
        for n, line in enumerate(lines[1:], start=2):
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                raise StudyError(f"{self.path}: line {n} is not valid JSON") from None
            self.done[_cell_key(rec["cell"])] = rec
        if end < len(data):  # a record cut short by a kill: drop it, the cell runs again
            with open(self.path, "r+b") as f:
                f.truncate(end)

    def __contains__(self, cell: dict) -> bool:
        return _cell_key(cell) in self.done

    def append(self, record: dict) -> None:
        self.done[_cell_key(record["cell"])] = record
        if not _writer():
            return
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(json.dumps(record, allow_nan=True) + "\n")
            f.flush()
            os.fsync(f.fileno())


def _record(cell: dict, run: BatchRun, extra: dict | None = None) -> dict:
    t = run.trace
    diag = {name: np.asarray(getattr(t, name)).tolist() for name in DIAGNOSTICS}
    return {
        "cell": cell,
        **(extra or {}),
        "metrics": {name: np.asarray(getattr(t.metrics, name)).tolist() for name in METRICS},
        "diagnostics": diag,
        "compile_s": run.compile_s,
        "run_s": run.run_s,
        "devices": run.num_devices,
    }


def cell_warnings(record: dict) -> list[str]:
    """One line per kind of trouble in a cell: capacity drops, ignored visibility, failed solves, low ESS."""
    d = {k: np.asarray(v, dtype=float) for k, v in record["diagnostics"].items()}
    out = []
    if (n := int(np.sum(d["dropped_capacity"]))) > 0:
        out.append(f"{n} hypotheses above the pruning threshold were dropped for lack of capacity in "
                   f"{int(np.sum(d['dropped_capacity'] > 0))} track-steps; rerun with a larger --capacity")
    if (n := int(np.sum(d["visibility_ignored"]))) > 0:
        out.append(f"{n} track-steps had no hypothesis with every detected object in view (visibility ignored)")
    if (n := int(np.sum(d["gn_failures"]))) > 0:
        out.append(f"the Gauss-Newton update did not converge for {n} components")
    if (n := int(np.sum(d["is_failures"]))) > 0:
        out.append(f"the laplace-is mode search did not converge for {n} kept components")
    ess = d["min_ess"][np.isfinite(d["min_ess"])]
    if ess.size and ess.min() < 0.01:
        out.append(f"some kept weights rest on few draws (smallest effective sample size {ess.min():.3g} of 1)")
    return out


# --------------------------------------------------------------------------- #
# The table
# --------------------------------------------------------------------------- #


def _csv_value(value: Any) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else format(value + 0.0, ".10g")
    return str(value)


def _writer() -> bool:
    """Only process 0 writes files when a study runs on several hosts (``jax.distributed``)."""
    return jax.process_index() == 0


def _write_table(path: str, columns: Sequence[str], rows: Iterable[dict]) -> None:
    if not _writer():
        return
    tmp = path + ".tmp"
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for row in rows:
            writer.writerow([_csv_value(row[c]) for c in columns])
    os.replace(tmp, path)  # atomic: a kill never leaves half a table


def _metric_rows(record: dict, track: int) -> Iterable[dict]:
    m = record["metrics"]
    for j in range(len(m["entropy"][track])):
        row = {name: m[name][track][j] for name in METRICS}
        row["num_components"] = int(row["num_components"])
        yield {"step": j + 1, **row}


def alpha_rows(study: AlphaStudy, records: Records) -> list[dict]:
    """Table rows of the finished cells, in grid order: alpha, model, track, step."""
    rows = []
    for cell in study.cells():
        if cell not in records:
            continue
        rec = records.done[_cell_key(cell)]
        for t in range(study.tracks):
            for row in _metric_rows(rec, t):
                rows.append({"alpha": cell["alpha"], "model": cell["model"], "track": t,
                             "seed": study.seed + t, **row})
    return rows


def read_table(path: str) -> list[dict]:
    """``table.csv`` as a list of dicts of strings (what :mod:`hybridslam.plot` reads)."""
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


# --------------------------------------------------------------------------- #
# Running
# --------------------------------------------------------------------------- #

Progress = Callable[[str, dict | None], None]  # (event, record): "start <cell>", "done <cell>"


def _max_detections(scenarios: Sequence[Scenario]) -> int:
    return max(1, max(s.max_detections for s in scenarios))


def run_alpha_study(study: AlphaStudy, folder: str, *, mesh=None, on_cell: Progress | None = None) -> list[dict]:
    """Run every unfinished cell of ``study`` into ``folder``; return the table rows.

    ``on_cell(cell_description, record)`` is called before (record ``None``) and after each cell
    that runs. The scenarios of one alpha are simulated once and shared by its models.
    """
    os.makedirs(folder, exist_ok=True)
    records = Records(folder, study.header())
    mesh = device_mesh() if mesh is None else mesh
    table = os.path.join(folder, TABLE)
    seeds = [study.seed + t for t in range(study.tracks)]
    resolved = {m: resolve_model(m) for m in study.models}  # a bad model file fails before any run
    for alpha in study.alphas:
        todo = [m for m in study.models if {"alpha": float(alpha), "model": m} not in records]
        if not todo:
            continue
        scenarios = [simulate(s, steps=study.steps, alpha=alpha, K=study.K) for s in seeds]
        config = study.estimator.config(scenarios[0], max_detections=2)  # the simulator's detector limit
        for model in todo:
            cell = {"alpha": float(alpha), "model": model}
            if on_cell:
                on_cell(f"alpha {alpha:g}, {model}", None)
            inputs = batch_inputs(scenarios, config, classifier=resolved[model],
                                  prune_ratio=study.estimator.prune_ratio, seeds=seeds)
            record = _record(cell, run_batch(inputs, mesh))
            records.append(record)
            _write_table(table, ALPHA_COLUMNS, alpha_rows(study, records))
            if on_cell:
                on_cell(f"alpha {alpha:g}, {model}", record)
    rows = alpha_rows(study, records)
    _write_table(table, ALPHA_COLUMNS, rows)
    return rows


def _result_name(path: str, model: str | None) -> str:
    stem = os.path.splitext(os.path.basename(path))[0]
    return f"{stem}.json" if model is None else f"{stem}.{model}.json"


def file_groups(study: FileStudy, scenarios: dict[str, Scenario]) -> list[dict]:
    """The cells of a file study: files of equal (objects, classes, steps, model), per model."""
    models = [None] if study.models is None else list(study.models)
    cells = []
    for model in models:
        groups: dict[tuple, list[str]] = {}
        for path, s in scenarios.items():
            name = s.classifier.model if model is None else model
            groups.setdefault((s.num_objects, s.num_classes, s.num_steps, name), []).append(path)
        for key, paths in groups.items():
            cells.append({"model": model, "run_as": key[3], "scenarios": sorted(paths)})
    return cells


def file_rows(cells: Sequence[dict], records: Records) -> list[dict]:
    rows = []
    for cell in cells:
        if cell not in records:
            continue
        rec = records.done[_cell_key(cell)]
        for t, path in enumerate(cell["scenarios"]):
            for row in _metric_rows(rec, t):
                rows.append({"scenario": os.path.basename(path), "model": cell["run_as"], "track": t, **row})
    rows.sort(key=lambda r: (r["model"], r["scenario"], r["step"]))
    order = {name: i for i, name in enumerate(sorted({r["scenario"] for r in rows}))}
    for r in rows:  # a stable number per scenario, for plots that index tracks
        r["track"] = order[r["scenario"]]
    return rows


def run_file_study(study: FileStudy, folder: str, *, mesh=None, on_cell: Progress | None = None) -> list[dict]:
    """Run every unfinished cell of ``study`` into ``folder``: result files in ``folder/results``, the table."""
    scenarios = {p: load_scenario(p) for p in study.paths}  # validate every file before any run
    os.makedirs(os.path.join(folder, "results"), exist_ok=True)
    records = Records(folder, study.header())
    mesh = device_mesh() if mesh is None else mesh
    cells = file_groups(study, scenarios)
    table = os.path.join(folder, TABLE)
    for cell in cells:
        if cell in records:
            continue
        group = [scenarios[p] for p in cell["scenarios"]]
        label = f"{cell['run_as']}, {len(group)} file(s) of {group[0].num_steps} steps"
        if on_cell:
            on_cell(label, None)
        config = study.estimator.config(group[0], max_detections=_max_detections(group))
        inputs = batch_inputs(group, config, classifier=resolve_model(cell["run_as"]),
                              prune_ratio=study.estimator.prune_ratio, seeds=[study.seed] * len(group))
        run = run_batch(inputs, mesh)
        _write_results(study, cell, group, run, config, folder)
        record = _record(cell, run)
        records.append(record)
        _write_table(table, FILE_COLUMNS, file_rows(cells, records))
        if on_cell:
            on_cell(label, record)
    rows = file_rows(cells, records)
    _write_table(table, FILE_COLUMNS, rows)
    return rows


def _write_results(study: FileStudy, cell: dict, group: Sequence[Scenario], run: BatchRun, config: Config,
                   folder: str) -> None:
    if not _writer():
        return
    steps = group[0].num_steps
    per_step = run.run_s / max(len(group) * steps, 1)  # wall time amortized over the batch
    for t, (path, scenario) in enumerate(zip(cell["scenarios"], group)):
        result = Result(
            estimator=describe(config, cell["run_as"], study.estimator.prune_ratio, study.seed)
            + f"; batched sweep of {len(group)} runs on {run.num_devices} device(s), step_s amortized",
            steps=step_records(run.trace, t, scenario),
            timing={"compile_s": run.compile_s, "step_s": [per_step] * steps},
        )
        save_result(result, os.path.join(folder, "results", _result_name(path, cell["model"])))
