"""The ``hybridslam`` command: simulate scenarios, run the estimator on them, run the demo study.

    hybridslam simulate --seed 0 --steps 10 --alpha 0.25 -o scenario.json
    hybridslam run scenario.json -o result.json [--classifier mirror] [--samples 1000] ...
    hybridslam run scenario.json -o result.json --estimator {hybrid,ml,gpda,max-mixture,multimodal}
    hybridslam demo [-o runs/demo] [--tracks 4] [--steps 10]
    hybridslam sweep [--alphas 0,0.25,0.5] [--models mirror,independent,none] [--tracks 8] -o runs/sweep
    hybridslam sweep --scenarios 'logs/*.json' [--models ...] -o runs/logs
    hybridslam plot runs/sweep
    hybridslam hallway -o runs/hallway [--levels 0.005,0.01625,...] [--seeds 5] [--steps 60] [--known-map]

Every user error (bad option, missing or malformed file, invalid setting, unwritable output)
ends with exit status 2 and one line ``hybridslam: error: <message>`` on stderr.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from collections.abc import Sequence
from typing import NoReturn, TextIO

import numpy as np
import optimistix as optx
from tqdm import tqdm

from . import plot, study
from .estimators.base import ESTIMATORS, run_estimator, step_warnings
from .sweep import device_mesh
from .model import model_from_scenario
from .result import Result, StepRecord, save_result
from .run import Run, config_for, run_scenario
from .scenario import Scenario, ScenarioError, load_scenario, save_scenario
from .simulate import simulate
from .step import StepInfo

PROG = "hybridslam"
CLASSIFIERS = ("mirror", "independent", "none")
WEIGHTS = ("laplace-is", "sampled", "linearized")
CSV_COLUMNS = (
    "model", "track", "step", "entropy", "det_cov", "err_wmax", "err_wavg", "num_components", "step_ms",
)
LOW_ESS = 0.01  # below this, one weight estimate rests on ~1% of its draws
SUMMARY_METRICS = ("entropy", "det_cov", "err_wmax", "err_wavg", "num_components")


class CLIError(Exception):
    """A user error: reported as one line ``hybridslam: error: <message>``, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse, but usage errors raise :class:`CLIError` instead of printing usage and exiting."""

    def error(self, message: str) -> NoReturn:
        raise CLIError(message)


# --------------------------------------------------------------------------- #
# Small helpers
# --------------------------------------------------------------------------- #


def _warn(message: str, stream: TextIO | None = None) -> None:
    """One ``WARNING:`` line on stderr (through tqdm while a progress bar is open)."""
    line = f"WARNING: {message}"
    if stream is None:
        print(line, file=sys.stderr, flush=True)
    else:
        tqdm.write(line, file=stream)


def _step_warnings(k: int, info: StepInfo) -> list[str]:
    """The warnings worth a line for step ``k``: capacity drops, ignored visibility, failed solves."""
    out = []
    dropped = int(info.prune.dropped_capacity)
    if dropped > 0:
        out.append(
            f"step {k}: {dropped} {'hypothesis' if dropped == 1 else 'hypotheses'} above the pruning "
            "threshold dropped for lack of capacity (the belief is truncated); rerun with a larger --capacity"
        )
    if bool(info.visibility_ignored):
        out.append(
            f"step {k}: no hypothesis has every detected object in view; the visibility model was "
            "ignored for this step (weights from the measurement likelihood alone)"
        )
    alive = int(info.num_alive)
    ok = np.atleast_1d(np.asarray(info.solver_result == optx.RESULTS.successful))
    failed = int(np.sum(~ok[:alive]))
    if failed:
        out.append(f"step {k}: the Gauss-Newton update did not converge for {failed} of {alive} components")
    ess = np.asarray(info.ess)[:alive]
    if alive and np.nanmin(ess) < LOW_ESS:
        out.append(
            f"step {k}: a kept weight rests on few draws (effective sample size {np.nanmin(ess):.3g} of 1); "
            "its value is luck: prefer --weights laplace-is or more --samples"
        )
    if int(info.is_solver_failures):
        out.append(f"step {k}: the laplace-is mode search did not converge for {int(info.is_solver_failures)} "
                   f"of {alive} components (their weights stay unbiased but are noisier)")
    return out


def _fmt(value: float | None, spec: str) -> str:
    """A table cell: blank for a missing value, ``-0`` shown as ``0``."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return format(value + 0.0, spec)


def _csv_number(value: float | int | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return str(value) if isinstance(value, int) else format(value + 0.0, ".10g")


def _check_writable(path: str) -> None:
    """Fail early (before a long run) when ``path`` cannot be created."""
    parent = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise CLIError(f"cannot write {path!r}: is a directory")
    if not os.path.isdir(parent):
        raise CLIError(f"cannot write {path!r}: directory {parent!r} does not exist")
    if not os.access(parent, os.W_OK):
        raise CLIError(f"cannot write {path!r}: permission denied")


def _check_settings(scenario: Scenario, *, classifier: str | None, capacity: int, samples: int,
                    weights: str, prune_ratio: float, max_detections: int | None = None) -> None:
    """Raise :class:`CLIError` for settings :func:`run_scenario` would reject (cheap, no compile)."""
    sizes = {} if max_detections is None else {"max_detections": max_detections}
    try:
        config_for(scenario, capacity=capacity, num_samples=samples, weights=weights, **sizes)
        model_from_scenario(scenario, classifier, prune_ratio)
    except ScenarioError:
        raise
    except ValueError as e:
        raise CLIError(str(e)) from None


def _run_settings(args: argparse.Namespace) -> dict:
    return dict(capacity=args.capacity, samples=args.samples, weights=args.weights,
                prune_ratio=args.prune_ratio)


# --------------------------------------------------------------------------- #
# hybridslam simulate
# --------------------------------------------------------------------------- #


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write one paper-setup scenario (Sec. V) to ``args.output``."""
    if args.steps < 1:
        raise CLIError(f"--steps: expected a positive number of steps, got {args.steps}")
    if not math.isfinite(args.alpha):
        raise CLIError(f"--alpha: expected a finite number, got {args.alpha}")
    if not (math.isfinite(args.K) and args.K > 0):
        raise CLIError(f"--K: expected a positive number, got {args.K}")
    _check_writable(args.output)
    scenario = simulate(args.seed, steps=args.steps, alpha=args.alpha, K=args.K)
    save_scenario(scenario, args.output)
    num_det = sum(len(s.detections) for s in scenario.steps)
    print(f"wrote {args.output}: {scenario.num_steps} steps, {scenario.num_objects} objects, "
          f"{num_det} detections (seed {args.seed}, alpha {args.alpha:g}, K {args.K:g})")
    return 0


# --------------------------------------------------------------------------- #
# hybridslam run
# --------------------------------------------------------------------------- #

_TABLE_HEADER = (f"{'k':>4} {'det':>4} {'alive':>6} {'entropy':>9} {'det_cov':>11} "
                 f"{'err_wmax':>9} {'err_wavg':>9} {'step_ms':>9}")


def _table_row(record: StepRecord, num_detections: int, seconds: float) -> str:
    m = record.metrics
    return (f"{record.k:>4} {num_detections:>4} {int(m['num_components']):>6} "
            f"{_fmt(m['entropy'], '.4f'):>9} {_fmt(m['det_cov'], '.4e'):>11} "
            f"{_fmt(m.get('err_wmax'), '.4f'):>9} {_fmt(m.get('err_wavg'), '.4f'):>9} "
            f"{_fmt(1e3 * seconds, '.1f'):>9}")


def _run_other(args: argparse.Namespace, scenario: Scenario) -> int:
    """``hybridslam run --estimator NAME`` for an estimator other than ``hybrid`` (:mod:`hybridslam.estimators`).

    It reads ``--classifier``, ``--capacity``, ``--samples`` and ``--seed`` (each estimator the ones it
    uses); ``--weights`` and ``--prune-ratio`` are the hybrid belief's.
    """
    _check_writable(args.output)
    print(f"{args.scenario}: {scenario.num_steps} steps, {scenario.num_objects} objects; estimator={args.estimator}, "
          f"classifier={args.classifier or scenario.classifier.model}, seed={args.seed}")
    print("compiling the step ...", flush=True)
    num_det = [len(s.detections) for s in scenario.steps]

    def on_step(record: StepRecord, info, seconds: float) -> None:
        if record.k == 1:
            print(_TABLE_HEADER)
        print(_table_row(record, num_det[record.k - 1], seconds), flush=True)
        for line in step_warnings(args.estimator, info):
            _warn(line)

    try:
        run = run_estimator(scenario, args.estimator, seed=args.seed, on_step=on_step, classifier=args.classifier,
                            capacity=args.capacity, num_samples=args.samples)
    except ImportError as e:
        raise CLIError(f"--estimator {args.estimator}: not available in this installation ({e})") from None
    except ValueError as e:
        if isinstance(e, ScenarioError):
            raise
        raise CLIError(str(e)) from None
    timing = run.result.timing or {"compile_s": 0.0, "step_s": []}
    steps_s = sum(timing["step_s"])
    print(f"compile time {timing['compile_s']:.2f} s; {scenario.num_steps} steps in {steps_s:.2f} s "
          f"({1e3 * steps_s / max(len(timing['step_s']), 1):.1f} ms/step)")
    save_result(run.result, args.output)
    print(f"wrote {args.output}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """Run the estimator over a scenario file, print a per-step table, write the result file."""
    scenario = load_scenario(args.scenario)
    if args.estimator != "hybrid":
        return _run_other(args, scenario)
    _check_settings(scenario, classifier=args.classifier, **_run_settings(args))
    _check_writable(args.output)
    name = args.classifier or scenario.classifier.model
    print(f"{args.scenario}: {scenario.num_steps} steps, {scenario.num_objects} objects; classifier={name}, "
          f"weights={args.weights}, samples={args.samples or 'default'}, capacity={args.capacity}, "
          f"prune_ratio={args.prune_ratio:g}, seed={args.seed}")
    print("compiling the step ...", flush=True)
    num_det = [len(s.detections) for s in scenario.steps]

    def on_step(record: StepRecord, info: StepInfo, seconds: float) -> None:
        if record.k == 1:
            print(_TABLE_HEADER)
        print(_table_row(record, num_det[record.k - 1], seconds), flush=True)
        for line in _step_warnings(record.k, info):
            _warn(line)

    run = run_scenario(
        scenario, classifier=args.classifier, capacity=args.capacity, num_samples=args.samples,
        weights=args.weights, prune_ratio=args.prune_ratio, seed=args.seed, on_step=on_step,
    )
    timing = run.result.timing or {"compile_s": 0.0, "step_s": []}
    steps_s = sum(timing["step_s"])
    per_step = 1e3 * steps_s / max(len(timing["step_s"]), 1)
    print(f"compile time {timing['compile_s']:.2f} s; {scenario.num_steps} steps in {steps_s:.2f} s "
          f"({per_step:.1f} ms/step)")
    save_result(run.result, args.output)
    print(f"wrote {args.output}")
    return 0


# --------------------------------------------------------------------------- #
# hybridslam demo
# --------------------------------------------------------------------------- #


def _csv_rows(model: str, track: int, result: Result) -> list[dict]:
    step_s = (result.timing or {}).get("step_s", [])
    rows = []
    for i, record in enumerate(result.steps):
        m = record.metrics
        rows.append({
            "model": model, "track": track, "step": record.k,
            "entropy": m["entropy"], "det_cov": m["det_cov"],
            "err_wmax": m.get("err_wmax"), "err_wavg": m.get("err_wavg"),
            "num_components": int(m["num_components"]),
            "step_ms": 1e3 * step_s[i] if i < len(step_s) else None,
        })
    return rows


def _posterior_steps(num_steps: int) -> list[int]:
    """Steps 1, ⌈T/2⌉, T (without repeats)."""
    return sorted({1, math.ceil(num_steps / 2), num_steps})


def summary_table(rows: Sequence[dict], models: Sequence[str]) -> str:
    """Per model: the mean over tracks of each metric at the last step, and the mean step time."""
    header = (f"{'model':<12} {'tracks':>6} {'H(w)':>8} {'det_cov':>11} {'err_wmax':>9} "
              f"{'err_wavg':>9} {'comps':>6} {'step_ms':>8}")
    lines = [header, "-" * len(header)]
    for model in models:
        mine = [r for r in rows if r["model"] == model]
        if not mine:
            continue
        last = max(r["step"] for r in mine)
        final = [r for r in mine if r["step"] == last]

        def mean(key: str, rs: Sequence[dict] = final) -> float:
            vals = [float(r[key]) for r in rs if r[key] is not None and not math.isnan(float(r[key]))]
            return float(np.mean(vals)) if vals else math.nan

        lines.append(
            f"{model:<12} {len(final):>6} {_fmt(mean('entropy'), '.4f'):>8} {_fmt(mean('det_cov'), '.4e'):>11} "
            f"{_fmt(mean('err_wmax'), '.4f'):>9} {_fmt(mean('err_wavg'), '.4f'):>9} "
            f"{_fmt(mean('num_components'), '.2f'):>6} {_fmt(mean('step_ms', mine), '.1f'):>8}"
        )
    return "\n".join(lines)


def cmd_demo(args: argparse.Namespace) -> int:
    """The small default study: tracks x classifier models, metrics.csv, metrics.png, posterior.png."""
    if args.tracks < 1:
        raise CLIError(f"--tracks: expected a positive number, got {args.tracks}")
    if args.steps < 1:
        raise CLIError(f"--steps: expected a positive number of steps, got {args.steps}")
    if not math.isfinite(args.alpha):
        raise CLIError(f"--alpha: expected a finite number, got {args.alpha}")
    models = CLASSIFIERS
    t_start = time.perf_counter()
    scenarios = [simulate(args.seed + t, steps=args.steps, alpha=args.alpha) for t in range(args.tracks)]
    for model in models:
        _check_settings(scenarios[0], classifier=model, max_detections=2, **_run_settings(args))
    out = args.output
    for sub in ("", "scenarios", "results"):
        os.makedirs(os.path.join(out, sub), exist_ok=True)
    csv_path = os.path.join(out, "metrics.csv")
    print(f"demo: {args.tracks} tracks x {len(models)} classifier models, {args.steps} steps, "
          f"{args.samples or 'default'} samples, capacity {args.capacity}; writing to {out}", flush=True)

    rows: list[dict] = []
    posterior: dict[str, list[StepRecord]] = {}
    show = _posterior_steps(args.steps)
    with open(csv_path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        f.flush()
        bar = tqdm(total=args.tracks * len(models), desc="demo", unit="run", file=sys.stderr,
                   dynamic_ncols=True)
        with bar:
            for track, scenario in enumerate(scenarios):
                save_scenario(scenario, os.path.join(out, "scenarios", f"track{track:02d}.json"))
                for model in models:
                    bar.set_postfix_str(f"track {track}, {model}")
                    run: Run = run_scenario(
                        scenario, classifier=model, capacity=args.capacity, num_samples=args.samples,
                        weights=args.weights, prune_ratio=args.prune_ratio, seed=args.seed,
                        max_detections=2,
                    )
                    for k, info in enumerate(run.infos, start=1):
                        for line in _step_warnings(k, info):
                            _warn(f"track {track}, {model}, {line}", stream=sys.stderr)
                    save_result(run.result, os.path.join(out, "results", f"{model}_track{track:02d}.json"))
                    new = _csv_rows(model, track, run.result)
                    writer.writerows([[_csv_number(r[c]) if c != "model" else r[c] for c in CSV_COLUMNS]
                                      for r in new])
                    f.flush()
                    rows.extend(new)
                    if track == 0:
                        posterior[model] = [run.result.steps[k - 1] for k in show]
                    bar.update(1)

    plot.plot_metrics(rows, os.path.join(out, "metrics.png"))
    plot.plot_posterior_panels(scenarios[0], posterior, os.path.join(out, "posterior.png"))
    print(f"wrote {csv_path}, metrics.png, posterior.png, {args.tracks} scenario and "
          f"{args.tracks * len(models)} result files")
    print(f"\nmean over {args.tracks} track(s) at the last step (k = {args.steps}); step_ms: mean over all steps")
    print(summary_table(rows, models))
    print(f"\ndemo finished in {time.perf_counter() - t_start:.1f} s")
    return 0


# --------------------------------------------------------------------------- #
# hybridslam sweep / plot
# --------------------------------------------------------------------------- #

SWEEP_DEFAULTS = {"alphas": "0,0.25,0.5", "tracks": 8, "steps": 10, "K": 15.0}


def _floats(text: str, option: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise CLIError(f"{option}: expected comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise CLIError(f"{option}: expected finite comma-separated numbers, got {text!r}")
    return values


def _models(text: str | None) -> tuple[str, ...] | None:
    if text is None:
        return None
    names = tuple(m.strip() for m in text.split(",") if m.strip())
    bad = [m for m in names if m not in CLASSIFIERS and not m.startswith(study.LEARNED_PREFIX)]
    if not names or bad:
        raise CLIError(f"--models: unknown model(s) {', '.join(bad) or repr(text)} "
                       f"(known: {', '.join(CLASSIFIERS)}, learned:PATH)")
    for m in names:
        if m.startswith(study.LEARNED_PREFIX):
            try:
                study.resolve_model(m)
            except ValueError as e:
                raise CLIError(f"--models {m}: {e}") from None
    return names


def alpha_summary(rows: Sequence[dict]) -> str:
    """Per (alpha, model): mean ± 95% half-width over tracks of each track's mean over its steps."""
    header = f"{'alpha':>6} {'model':<12} {'tracks':>6} {'H(w)':>15} {'det_cov':>11} {'err_wmax':>15} {'err_wavg':>15}"
    lines = [header, "-" * len(header)]
    curves = {m: plot.alpha_curves(rows, m) for m in ("entropy", "det_cov", "err_wmax", "err_wavg")}
    models = list(dict.fromkeys(str(r["model"]) for r in rows))
    alphas = sorted({float(r["alpha"]) for r in rows})
    for a in alphas:
        for model in models:
            cells = []
            for metric, spec in (("entropy", ".3f"), ("det_cov", ".3e"), ("err_wmax", ".3f"), ("err_wavg", ".3f")):
                xs, values = curves[metric][model]
                j = int(np.searchsorted(xs, a))
                mean, half = plot.mean_band(values[:, j : j + 1])
                text = _fmt(float(mean[0]), spec)
                if metric != "det_cov" and not math.isnan(float(half[0])):
                    text += f" ±{float(half[0]):.3f}"
                cells.append(text)
            n = curves["entropy"][model][1].shape[0]
            lines.append(f"{a:>6g} {model:<12} {n:>6} {cells[0]:>15} {cells[1]:>11} {cells[2]:>15} {cells[3]:>15}")
    return "\n".join(lines)


def _draw(folder: str, rows: Sequence[dict]) -> list[str]:
    """The study's plots from its table rows; returns the files written."""
    if not rows:
        return []
    if "alpha" in rows[0]:
        path = os.path.join(folder, "alpha_sweep.png")
        plot.plot_alpha_sweep(rows, path)
    else:
        path = os.path.join(folder, "metrics.png")
        plot.plot_metrics(rows, path)
    return [path]


def cmd_sweep(args: argparse.Namespace) -> int:
    """A study: alphas x models x simulated tracks (Fig. 5), or runs over scenario files; resumable."""
    estimator = study.Estimator(weights=args.weights, samples=args.samples, capacity=args.capacity,
                                prune_ratio=args.prune_ratio)
    models = _models(args.models)
    folder = args.output
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise CLIError(f"-o {folder!r}: exists and is not a folder")
    try:
        if args.scenarios is not None:
            given = [f"--{k}" for k in SWEEP_DEFAULTS if getattr(args, k) is not None]
            if given:
                raise CLIError(f"{', '.join(given)}: only for simulated studies; scenario files carry their own settings")
            spec: study.AlphaStudy | study.FileStudy = study.FileStudy(
                tuple(study.scenario_paths(args.scenarios)), models, args.seed, estimator)
            what = f"{len(spec.paths)} scenario file(s) x {', '.join(models) if models else 'their own model'}"
        else:
            opts = {k: SWEEP_DEFAULTS[k] if getattr(args, k) is None else getattr(args, k) for k in SWEEP_DEFAULTS}
            spec = study.AlphaStudy(
                alphas=_floats(str(opts["alphas"]), "--alphas"), models=models or CLASSIFIERS,
                tracks=int(opts["tracks"]), steps=int(opts["steps"]), K=float(opts["K"]), seed=args.seed,
                estimator=estimator)
            what = (f"{len(spec.alphas)} alpha(s) x {len(spec.models)} model(s) x {spec.tracks} tracks of "
                    f"{spec.steps} steps")
        if args.samples is not None and args.samples < 1 or args.capacity < 1:
            raise CLIError("--samples and --capacity must be positive")
        if not args.prune_ratio >= 1:
            raise CLIError(f"--prune-ratio: must be >= 1, got {args.prune_ratio}")
        os.makedirs(folder, exist_ok=True)
        records = study.Records(folder, spec.header())  # refuses records made with other settings
        mesh = device_mesh()
        print(f"sweep: {what}; weights={args.weights}, samples={args.samples or 'default'}, "
              f"capacity={args.capacity}, seed={args.seed}; {mesh.size} device(s) "
              f"({mesh.devices.flat[0].platform}); writing to {folder}", flush=True)
        t_start = time.perf_counter()
        cells = len(spec.cells()) if isinstance(spec, study.AlphaStudy) else None
        bar = tqdm(total=cells, desc="sweep", unit="cell", file=sys.stderr, dynamic_ncols=True)
        compile_s = run_s = 0.0

        def on_cell(label: str, record: dict | None) -> None:
            nonlocal compile_s, run_s
            if record is None:
                bar.set_postfix_str(label)
                return
            compile_s += record["compile_s"]
            run_s += record["run_s"]
            for line in study.cell_warnings(record):
                _warn(f"{label}: {line}", stream=sys.stderr)
            bar.update(1)

        with bar:
            if isinstance(spec, study.AlphaStudy):
                bar.update(sum(c in records for c in spec.cells()))
                rows = study.run_alpha_study(spec, folder, mesh=mesh, on_cell=on_cell)
            else:
                rows = study.run_file_study(spec, folder, mesh=mesh, on_cell=on_cell)
    except study.StudyError as e:
        raise CLIError(str(e)) from None
    except ValueError as e:
        if isinstance(e, ScenarioError):
            raise
        raise CLIError(str(e)) from None
    written = _draw(folder, rows)
    print(f"wrote {os.path.join(folder, study.TABLE)} ({len(rows)} rows), {study.RECORDS}"
          + "".join(f", {os.path.basename(p)}" for p in written)
          + (", results/" if isinstance(spec, study.FileStudy) else ""))
    if isinstance(spec, study.AlphaStudy):
        print(f"\nmean over tracks of each track's mean over steps 1-{spec.steps} (± 95% half-width)")
        print(alpha_summary(rows))
    else:
        print(summary_table(rows, list(dict.fromkeys(r["model"] for r in rows))))
    total = time.perf_counter() - t_start
    track_steps = sum(1 for _ in rows)
    print(f"\nsweep finished in {total:.1f} s (this session: compile {compile_s:.1f} s, batched runs "
          f"{run_s:.1f} s; {track_steps} track-steps in the table)")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """Redraw a study's plots from its table."""
    path = os.path.join(args.folder, study.TABLE)
    if not os.path.isfile(path):
        raise CLIError(f"{args.folder!r}: no {study.TABLE} (run hybridslam sweep -o {args.folder} first)")
    rows = study.read_table(path)
    if not rows:
        raise CLIError(f"{path}: the table is empty (no finished cell yet)")
    written = _draw(args.folder, rows)
    print("wrote " + ", ".join(written))
    return 0


# --------------------------------------------------------------------------- #
# hybridslam hallway
# --------------------------------------------------------------------------- #


def cmd_hallway(args: argparse.Namespace) -> int:
    """Write the hallway study's scenarios (thesis Sec. 5.4.1): one file per (noise level, seed)."""
    from . import hallway

    levels = hallway.LEVELS if args.levels is None else tuple(_floats(args.levels, "--levels"))
    if not all(v > 0 for v in levels):
        raise CLIError(f"--levels: expected positive traces of the odometry covariance, got {args.levels!r}")
    if args.seeds < 1:
        raise CLIError(f"--seeds: expected a positive number, got {args.seeds}")
    if args.steps is not None and args.steps < 1:
        raise CLIError(f"--steps: expected a positive number of steps, got {args.steps}")
    if os.path.exists(args.output) and not os.path.isdir(args.output):
        raise CLIError(f"-o {args.output!r}: exists and is not a folder")
    names = [hallway.scenario_name(v, 0) for v in levels]
    if len(set(names)) != len(names):
        raise CLIError(f"--levels: two levels share a file name (4 decimals): {args.levels!r}")
    os.makedirs(args.output, exist_ok=True)
    for level in levels:
        for seed in range(args.seeds):
            scenario = hallway.hallway(seed, level, steps=args.steps, known_map=args.known_map)
            save_scenario(scenario, os.path.join(args.output, hallway.scenario_name(level, seed)))
    num_det = sum(len(s.detections) for s in scenario.steps)
    landmarks = scenario.num_objects if args.known_map else len(scenario.true_objects or ())
    print(f"wrote {len(levels) * args.seeds} scenario files to {args.output}: tr(Lambda_t) in "
          f"{', '.join(f'{v:g}' for v in levels)} x seeds 0..{args.seeds - 1}; {scenario.num_steps} steps, "
          f"{landmarks} landmarks ({'known' if args.known_map else 'unknown'} map), ~{num_det} detections each")
    return 0


# --------------------------------------------------------------------------- #
# Parser and entry point
# --------------------------------------------------------------------------- #


def _add_estimator_options(p: argparse.ArgumentParser, seed_help: str = "PRNG seed of the Monte-Carlo weights") -> None:
    p.add_argument("--samples", type=int, default=None,
                   help="draws of the weight method: per parent for sampled (n_s of Eq. 16, default 1000), "
                        "per candidate child for laplace-is (default 256)")
    p.add_argument("--capacity", type=int, default=64, help="most components kept after pruning")
    p.add_argument("--prune-ratio", type=float, default=150.0,
                   help="drop components below w_max / ratio (the paper's 150)")
    p.add_argument("--weights", choices=WEIGHTS, default="laplace-is",
                   help="association weights: laplace-is (low-variance Eq. 16, default), sampled (the paper's "
                        "Monte-Carlo Eq. 16) or linearized (deterministic)")
    p.add_argument("--seed", type=int, default=0, help=seed_help)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description="Semantic SLAM with ambiguous data association (hybrid belief).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="{simulate,run,demo,sweep,plot,hallway}")

    p = sub.add_parser("simulate", help="write a paper-setup scenario file (Sec. V)")
    p.add_argument("--seed", type=int, default=0, help="track and measurement seed")
    p.add_argument("--steps", type=int, default=10, help="number of steps T")
    p.add_argument("--alpha", type=float, default=0.25, help="classifier alpha of Eq. 18")
    p.add_argument("--K", type=float, default=15.0, help="classifier K of Eq. 18")
    p.add_argument("-o", "--output", required=True, help="scenario file to write")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("run", help="run the estimator on a scenario file, write a result file")
    p.add_argument("scenario", help="scenario file (hybridslam-scenario/1)")
    p.add_argument("-o", "--output", required=True, help="result file to write")
    p.add_argument("--classifier", choices=CLASSIFIERS, default=None,
                   help="classifier model (default: the scenario's)")
    p.add_argument("--estimator", choices=tuple(ESTIMATORS), default="hybrid",
                   help="association strategy: hybrid (Tchuiev et al., default), ml, gpda, max-mixture (Doherty's "
                        "thesis Ch. 3-4) or multimodal (Ch. 5)")
    _add_estimator_options(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", help="the default study: tracks x classifier models, metrics and plots")
    p.add_argument("-o", "--output", default=os.path.join("runs", "demo"), help="output folder")
    p.add_argument("--tracks", type=int, default=4, help="number of simulated tracks")
    p.add_argument("--steps", type=int, default=10, help="steps per track")
    p.add_argument("--alpha", type=float, default=0.25, help="classifier alpha of Eq. 18")
    _add_estimator_options(p, seed_help="track t is simulated with seed + t; every run uses seed for its weights")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("sweep", help="a resumable study: alphas x models x tracks (Fig. 5), or scenario files")
    p.add_argument("-o", "--output", default=os.path.join("runs", "sweep"),
                   help="output folder (a folder with a finished or interrupted study resumes it)")
    p.add_argument("--alphas", default=None, help=f"alphas of Eq. 18, comma-separated (default {SWEEP_DEFAULTS['alphas']})")
    p.add_argument("--models", default=None,
                   help="classifier models, comma-separated: mirror, independent, none, or learned:PATH (a "
                        "model file of scripts/fit_classifier.py) (default: mirror,independent,none; with "
                        "--scenarios: each file's own)")
    p.add_argument("--tracks", type=int, default=None, help=f"simulated tracks per cell (default {SWEEP_DEFAULTS['tracks']})")
    p.add_argument("--steps", type=int, default=None, help=f"steps per track (default {SWEEP_DEFAULTS['steps']})")
    p.add_argument("--K", type=float, default=None, help=f"classifier K of Eq. 18 (default {SWEEP_DEFAULTS['K']:g})")
    p.add_argument("--scenarios", default=None, metavar="DIR_OR_GLOB",
                   help="run over these scenario files instead of simulating (files of equal shape are batched)")
    _add_estimator_options(p, seed_help="track t is simulated with seed + t and weighed with PRNG seed seed + t")
    p.set_defaults(func=cmd_sweep, capacity=16)

    p = sub.add_parser("plot", help="redraw a study's plots from its table.csv")
    p.add_argument("folder", help="the study's output folder")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("hallway", help="write the hallway study's scenario files (thesis Sec. 5.4.1)")
    p.add_argument("-o", "--output", required=True, help="folder for hallway_tr<level>_seed<s>.json")
    p.add_argument("--levels", default=None,
                   help="traces of the odometry covariance, comma-separated (default: 0.005 to 0.05 in 5 steps)")
    p.add_argument("--seeds", type=int, default=1, help="seeds 0..N-1 per level")
    p.add_argument("--steps", type=int, default=None, help="steps per run (default: one loop, 60)")
    p.add_argument("--known-map", action="store_true",
                   help="list every landmark as a prior object (no discovery section)")
    p.set_defaults(func=cmd_hallway)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``hybridslam`` console script; returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except (CLIError, ScenarioError) as e:
        message = str(e)
    except OSError as e:
        target = f" {e.filename!r}" if e.filename else ""
        message = f"cannot access{target}: {e.strerror or e}"
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    print(f"{PROG}: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
