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

import dataclasses
import glob
import math
import os
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from ..driver import object_poses
from ..estimators.base import AbstractEstimator, summarize_counts
from ..estimators.hybrid.estimator import Hybrid
from ..io.result import Result, save_result
from ..models.scenario import Scenario
from ..io.scenario import load_scenario
from ..models.classifier import ClassifierModel
from ..sim.paper import simulate
from .batch import BatchRun, batch_inputs, batched, device_mesh, run_batch, step_records
from .records import RECORD_FORMAT as RECORD_FORMAT
from .records import RECORDS as RECORDS
from .records import Records as Records
from .records import StudyError as StudyError
from .records import cell_key, write_table, is_writer
from .records import read_table as read_table
from .strategies import BatchStrategy

TABLE = "table.csv"
METRICS = ("entropy", "det_cov", "err_wmax", "err_wavg", "num_components")
DIAGNOSTICS = ("num_components", "dropped_capacity", "dropped_budget", "dropped_mass", "visibility_ignored",
               "solver_failures", "is_failures", "min_ess", "skipped", "rejected", "unmapped", "object_overflow",
               "inconsistent", "merged")
ALPHA_COLUMNS = ("alpha", "model", "track", "seed", "step", *METRICS)
FILE_COLUMNS = ("scenario", "model", "track", "step", *METRICS)


def default_estimator() -> AbstractEstimator:
    """A study's default: the hybrid belief with a small capacity (a batch pays for the largest live
    set of any of its tracks)."""
    return Hybrid(capacity=16)


def estimator_header(estimator: AbstractEstimator) -> dict:
    """What a study's records depend on about its estimator (compared when a study resumes)."""
    return {"estimator": estimator.name, **estimator.settings()}


@dataclasses.dataclass(frozen=True)
class AlphaStudy:
    """The paper's statistical study (Sec. V, Fig. 5): alphas × models × tracks of paper-setup scenarios."""

    alphas: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
    models: tuple[str, ...] = ("mirror", "independent", "none")
    tracks: int = 50
    steps: int = 10
    K: float = 15.0
    seed: int = 0  # track t: scenario seed and weights seed seed + t
    estimator: AbstractEstimator = dataclasses.field(default_factory=default_estimator)

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
                **estimator_header(self.estimator)}

    def cells(self) -> list[dict]:
        return [{"alpha": float(a), "model": m} for a in self.alphas for m in self.models]


@dataclasses.dataclass(frozen=True)
class FileStudy:
    """Runs over scenario files; ``models=None`` runs each file with the classifier it names."""

    paths: tuple[str, ...]
    models: tuple[str, ...] | None = None
    seed: int = 0  # the weights' PRNG seed of every run (as ``hybridslam run --seed``)
    estimator: AbstractEstimator = dataclasses.field(default_factory=default_estimator)

    def header(self) -> dict:
        return {"kind": "files", "seed": self.seed, **estimator_header(self.estimator)}


LEARNED_PREFIX = "learned:"


def resolve_model(name: str) -> str | ClassifierModel:
    """A study's model name as :func:`~hybridslam.sweep.batch_inputs` takes it.

    ``"mirror"``, ``"independent"``, ``"none"`` stay names (alpha and K come from each scenario);
    ``"learned:PATH"`` loads the learned classifier in the model file ``PATH`` (its fitted h_c and
    Σ_c replace the true model's, for every alpha).
    """
    if name.startswith(LEARNED_PREFIX):
        from ..models.learned import load_classifier

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


def _record(cell: dict, run: BatchRun, extra: dict | None = None) -> dict:
    t = run.trace
    return {
        "cell": cell,
        **(extra or {}),
        "metrics": {name: np.asarray(getattr(t.metrics, name)).tolist() for name in METRICS},
        "diagnostics": {name: np.asarray(getattr(t.info, name)).tolist() for name in DIAGNOSTICS},
        "compile_s": run.compile_s,
        "run_s": run.run_s,
        "devices": run.num_devices,
        "batches": None if run.plan is None else run.plan.slices,
        "batch_gib": None if run.plan is None else run.plan.bytes / (1 << 30),
        "batching": run.strategy,
    }


def cell_warnings(record: dict) -> list[str]:
    """One line per kind of trouble in a cell (capacity drops, failed solves, low ESS, ...), in the
    words every estimator's :class:`~hybridslam.estimators.StepInfo` uses."""
    return summarize_counts({name: np.asarray(v) for name, v in record["diagnostics"].items()})


# --------------------------------------------------------------------------- #
# The table
# --------------------------------------------------------------------------- #


def _metric_rows(record: dict, track: int) -> Iterable[dict]:
    m = record["metrics"]
    lengths = record.get("steps")  # file studies: each file's own length (shorter ones were padded)
    for j in range(len(m["entropy"][track]) if lengths is None else lengths[track]):
        row = {name: m[name][track][j] for name in METRICS}
        row["num_components"] = int(row["num_components"])
        yield {"step": j + 1, **row}


def alpha_rows(study: AlphaStudy, records: Records) -> list[dict]:
    """Table rows of the finished cells, in grid order: alpha, model, track, step."""
    rows = []
    for cell in study.cells():
        if cell not in records:
            continue
        rec = records.done[cell_key(cell)]
        for t in range(study.tracks):
            for row in _metric_rows(rec, t):
                rows.append({"alpha": cell["alpha"], "model": cell["model"], "track": t,
                             "seed": study.seed + t, **row})
    return rows


# --------------------------------------------------------------------------- #
# Running
# --------------------------------------------------------------------------- #

Progress = Callable[[str, dict | None], None]  # (event, record): "start <cell>", "done <cell>"


def run_alpha_study(study: AlphaStudy, folder: str, *, mesh=None, on_cell: Progress | None = None,
                    strategy: BatchStrategy | None = None) -> list[dict]:
    """Run every unfinished cell of ``study`` into ``folder``; return the table rows.

    ``strategy``: how a cell's tracks share its program (:mod:`hybridslam.studies.strategies`;
    default by backend); it changes no number, so it is not part of the records' settings.

    ``on_cell(cell_description, record)`` is called before (record ``None``) and after each cell
    that runs. The scenarios of one alpha are simulated once and shared by its models.
    """
    os.makedirs(folder, exist_ok=True)
    with Records(folder, study.header()) as records:  # the folder is locked until the run ends
        mesh = device_mesh() if mesh is None else mesh
        table = os.path.join(folder, TABLE)
        seeds = [study.seed + t for t in range(study.tracks)]
        resolved = {m: resolve_model(m) for m in study.models}  # a bad model file fails before any run
        for alpha in study.alphas:
            todo = [m for m in study.models if {"alpha": float(alpha), "model": m} not in records]
            if not todo:
                continue
            scenarios = [simulate(s, steps=study.steps, alpha=alpha, K=study.K) for s in seeds]
            for model in todo:
                cell = {"alpha": float(alpha), "model": model}
                if on_cell:
                    on_cell(f"alpha {alpha:g}, {model}", None)
                # Two detection slots: the simulator's detector reports at most the 2 nearest objects.
                # (the fields of the concrete estimator, which mypy reads as AbstractEstimator's)
                estimator = batched(dataclasses.replace(study.estimator, classifier=resolved[model],  # type: ignore[call-arg]
                                                        max_detections=2), scenarios)
                record = _record(cell, run_batch(estimator, batch_inputs(estimator, scenarios, seeds), mesh,
                                                  strategy=strategy))
                records.append(record)
                write_table(table, ALPHA_COLUMNS, alpha_rows(study, records))
                if on_cell:
                    on_cell(f"alpha {alpha:g}, {model}", record)
        rows = alpha_rows(study, records)
        write_table(table, ALPHA_COLUMNS, rows)
        return rows


def _result_name(path: str, model: str | None) -> str:
    stem = os.path.splitext(os.path.basename(path))[0]
    return f"{stem}.json" if model is None else f"{stem}.{model}.json"


def file_groups(study: FileStudy, scenarios: dict[str, Scenario]) -> list[dict]:
    """The cells of a file study: files of equal (objects, classes, object capacity, model), per model.

    Files of different lengths and detection counts share a cell (one compiled program): the
    shorter ones are padded with inactive steps.
    """
    models = [None] if study.models is None else list(study.models)
    cells = []
    for model in models:
        groups: dict[tuple, list[str]] = {}
        for path, s in scenarios.items():
            name = s.classifier.model if model is None else model
            capacity = None if s.discovery is None else s.discovery.max_objects
            groups.setdefault((s.num_objects, s.num_classes, capacity, name), []).append(path)
        for key, paths in groups.items():
            cells.append({"model": model, "run_as": key[3], "scenarios": sorted(paths)})
    return cells


def file_rows(cells: Sequence[dict], records: Records) -> list[dict]:
    rows = []
    for cell in cells:
        if cell not in records:
            continue
        rec = records.done[cell_key(cell)]
        for t, path in enumerate(cell["scenarios"]):
            for row in _metric_rows(rec, t):
                rows.append({"scenario": os.path.basename(path), "model": cell["run_as"], "track": t, **row})
    rows.sort(key=lambda r: (r["model"], r["scenario"], r["step"]))
    order = {name: i for i, name in enumerate(sorted({r["scenario"] for r in rows}))}
    for r in rows:  # a stable number per scenario, for plots that index tracks
        r["track"] = order[r["scenario"]]
    return rows


def run_file_study(study: FileStudy, folder: str, *, mesh=None, on_cell: Progress | None = None,
                   strategy: BatchStrategy | None = None) -> list[dict]:
    """Run every unfinished cell of ``study`` into ``folder``: result files in ``folder/results``, the table.
    ``strategy``: as in :func:`run_alpha_study`."""
    scenarios = {p: load_scenario(p) for p in study.paths}  # validate every file before any run
    os.makedirs(os.path.join(folder, "results"), exist_ok=True)
    with Records(folder, study.header()) as records:  # the folder is locked until the run ends
        mesh = device_mesh() if mesh is None else mesh
        cells = file_groups(study, scenarios)
        table = os.path.join(folder, TABLE)
        for cell in cells:
            if cell in records:
                continue
            group = [scenarios[p] for p in cell["scenarios"]]
            label = f"{cell['run_as']}, {len(group)} file(s) of {min(g.num_steps for g in group)}-" \
                    f"{max(g.num_steps for g in group)} steps"
            if on_cell:
                on_cell(label, None)
            model = resolve_model(cell["run_as"])
            chosen = dataclasses.replace(study.estimator, classifier=model)  # type: ignore[call-arg]
            estimator = batched(chosen, group)
            run = run_batch(estimator, batch_inputs(estimator, group, [study.seed] * len(group)), mesh,
                            strategy=strategy)
            # The result files name the model (the batch may run it as an AlphaK: batch.shared_classifier).
            named = dataclasses.replace(estimator, classifier=model)  # type: ignore[call-arg]
            _write_results(study, cell, group, run, named, folder)
            record = _record(cell, run, {"steps": [g.num_steps for g in group]})
            records.append(record)
            write_table(table, FILE_COLUMNS, file_rows(cells, records))
            if on_cell:
                on_cell(label, record)
        rows = file_rows(cells, records)
        write_table(table, FILE_COLUMNS, rows)
        return rows


def _write_results(study: FileStudy, cell: dict, group: Sequence[Scenario], run: BatchRun,
                   estimator: AbstractEstimator, folder: str) -> None:
    if not is_writer():
        return
    per_step = run.run_s / max(sum(g.num_steps for g in group), 1)  # wall time amortized over the batch
    for t, (path, scenario) in enumerate(zip(cell["scenarios"], group)):
        steps = scenario.num_steps
        result = Result(
            estimator=f"{estimator.describe(scenario)}, seed={study.seed}"
            + f"; batched sweep of {len(group)} runs on {run.num_devices} device(s) ({run.strategy}), "
            "step_s amortized",
            steps=step_records(run.trace, t, scenario),
            timing={"compile_s": run.compile_s, "step_s": [per_step] * steps},
            # A file shorter than the batch's padded length: its poses after x_T are padding.
            trajectory=None if run.trajectories is None else run.trajectories[t][: steps + 1],
            objects=None if run.objects is None else object_poses(run.objects[0][t], run.objects[1][t]),
        )
        save_result(result, os.path.join(folder, "results", _result_name(path, cell["model"])))
