"""``hybridslam demo``: a few simulated tracks × the classifier models, one run each, with plots."""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time

from tqdm import tqdm

from ..driver import run
from ..io.result import Result, StepRecord, save_result
from ..io.scenario import save_scenario
from ..sim.paper import simulate
from .common import CLASSIFIERS, CLIError, add_estimator_options, csv_number, estimator_from_args, warn
from .tables import summary_table

CSV_COLUMNS = (
    "model", "track", "step", "entropy", "det_cov", "err_wmax", "err_wavg", "num_components", "step_ms",
)


def csv_rows(model: str, track: int, result: Result) -> list[dict]:
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
    # Two detection slots (the simulator's detector limit): every run shares one compiled step per model.
    estimators = {m: estimator_from_args(args, classifier=m, max_detections=2) for m in models}
    out = args.output
    for sub in ("", "scenarios", "results"):
        os.makedirs(os.path.join(out, sub), exist_ok=True)
    csv_path = os.path.join(out, "metrics.csv")
    any_est = estimators[models[0]]
    print(f"demo: {args.tracks} tracks x {len(models)} classifier models, {args.steps} steps; estimator="
          f"{any_est.name}; {any_est.describe().split('; ', 1)[-1]}; writing to {out}", flush=True)

    rows: list[dict] = []
    posterior: dict[str, list[StepRecord]] = {}
    show = _posterior_steps(args.steps)
    with open(csv_path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        f.flush()
        bar = tqdm(total=args.tracks * len(models), desc="demo", unit="run", file=sys.stderr, dynamic_ncols=True)
        with bar:
            for track, scenario in enumerate(scenarios):
                save_scenario(scenario, os.path.join(out, "scenarios", f"track{track:02d}.json"))
                for model in models:
                    bar.set_postfix_str(f"track {track}, {model}")
                    result_run = run(estimators[model], scenario, seed=args.seed)
                    for info in result_run.infos:
                        for line in info.warnings():
                            warn(f"track {track}, {model}, {line}", stream=sys.stderr)
                    save_result(result_run.result, os.path.join(out, "results", f"{model}_track{track:02d}.json"))
                    new = csv_rows(model, track, result_run.result)
                    writer.writerows([[csv_number(r[c]) if c != "model" else r[c] for c in CSV_COLUMNS]
                                      for r in new])
                    f.flush()
                    rows.extend(new)
                    if track == 0:
                        posterior[model] = [result_run.result.steps[k - 1] for k in show]
                    bar.update(1)

    from ..analysis import plot  # here: matplotlib costs every other command 0.3-0.5 s of start-up

    plot.plot_metrics(rows, os.path.join(out, "metrics.png"))
    plot.plot_posterior_panels(scenarios[0], posterior, os.path.join(out, "posterior.png"))
    print(f"wrote {csv_path}, metrics.png, posterior.png, {args.tracks} scenario and "
          f"{args.tracks * len(models)} result files")
    print(f"\nmean over {args.tracks} track(s) at the last step (k = {args.steps}); step_ms: mean over all steps")
    print(summary_table(rows, models))
    print(f"\ndemo finished in {time.perf_counter() - t_start:.1f} s")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="a few tracks x classifier models, one run each, metrics and plots")
    p.add_argument("-o", "--output", default=os.path.join("runs", "demo"), help="output folder")
    p.add_argument("--tracks", type=int, default=4, help="number of simulated tracks")
    p.add_argument("--steps", type=int, default=10, help="steps per track")
    p.add_argument("--alpha", type=float, default=0.25, help="classifier alpha of Eq. 18")
    add_estimator_options(p, seed_help="track t is simulated with seed + t; every run uses seed for its weights")
    p.set_defaults(func=cmd_demo)
