"""The ``hybridslam`` command: simulate scenarios, run the estimator on them, run the demo study.

    hybridslam simulate --seed 0 --steps 10 --alpha 0.25 -o scenario.json
    hybridslam run scenario.json -o result.json [--classifier mirror] [--samples 1000] ...
    hybridslam demo [-o runs/demo] [--tracks 4] [--steps 10]

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

from . import plot
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


def cmd_run(args: argparse.Namespace) -> int:
    """Run the estimator over a scenario file, print a per-step table, write the result file."""
    scenario = load_scenario(args.scenario)
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
    sub = parser.add_subparsers(dest="command", required=True, metavar="{simulate,run,demo}")

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
    _add_estimator_options(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", help="the default study: tracks x classifier models, metrics and plots")
    p.add_argument("-o", "--output", default=os.path.join("runs", "demo"), help="output folder")
    p.add_argument("--tracks", type=int, default=4, help="number of simulated tracks")
    p.add_argument("--steps", type=int, default=10, help="steps per track")
    p.add_argument("--alpha", type=float, default=0.25, help="classifier alpha of Eq. 18")
    _add_estimator_options(p, seed_help="track t is simulated with seed + t; every run uses seed for its weights")
    p.set_defaults(func=cmd_demo)
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
