"""``hybridslam sweep``: a resumable study over simulated tracks or scenario files."""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any

from tqdm import tqdm

from ..estimators.options import options_of
from ..estimators.registry import ESTIMATORS
from ..io.scenario import ScenarioError
from ..studies import study
from ..studies.batch import check_batchable, device_mesh
from ..studies.strategies import parse_strategy, split_cpu_into_cores
from .common import (
    CLASSIFIERS,
    CLIError,
    add_estimator_options,
    check_folder,
    estimator_from_args,
    floats,
    warn,
)
from .plot import draw
from .tables import alpha_summary, summary_table

SWEEP_DEFAULTS = {"alphas": "0,0.25,0.5", "tracks": 8, "steps": 10, "K": 15.0}
SWEEP_CAPACITY = 16  # small: a batch pays for the largest live set of any of its tracks


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


def _spec(args: argparse.Namespace, models, estimator) -> tuple[study.AlphaStudy | study.FileStudy, str]:
    spec: study.AlphaStudy | study.FileStudy
    if args.scenarios is not None:
        given = [f"--{k}" for k in SWEEP_DEFAULTS if getattr(args, k) is not None]
        if given:
            raise CLIError(f"{', '.join(given)}: only for simulated studies; scenario files carry their own settings")
        files = study.FileStudy(tuple(study.scenario_paths(args.scenarios)), models, args.seed, estimator)
        return files, f"{len(files.paths)} scenario file(s) x {', '.join(models) if models else 'their own model'}"
    opts: dict[str, Any] = {k: SWEEP_DEFAULTS[k] if getattr(args, k) is None else getattr(args, k) for k in SWEEP_DEFAULTS}
    alphas = study.AlphaStudy(
        alphas=floats(str(opts["alphas"]), "--alphas"), models=models or CLASSIFIERS,
        tracks=int(opts["tracks"]), steps=int(opts["steps"]), K=float(opts["K"]), seed=args.seed,
        estimator=estimator)
    return alphas, (f"{len(alphas.alphas)} alpha(s) x {len(alphas.models or ())} model(s) x {alphas.tracks} tracks "
                    f"of {alphas.steps} steps")


def cmd_sweep(args: argparse.Namespace) -> int:
    """A study: alphas x models x simulated tracks (Fig. 5), or runs over scenario files; resumable."""
    if args.batching in ("auto", "map") or args.batching.startswith("map:"):
        try:
            split_cpu_into_cores()  # before anything starts JAX's backends: the tracks then run on every core
        except ValueError as e:
            raise CLIError(str(e)) from None
    capacity = args.capacity
    if capacity is None and "capacity" in options_of(ESTIMATORS[args.estimator]):
        capacity = SWEEP_CAPACITY
    estimator = estimator_from_args(args, capacity=capacity)
    try:
        check_batchable(estimator)
    except ValueError as e:
        raise CLIError(str(e)) from None
    models = _models(args.models)
    try:
        strategy = parse_strategy(args.batching)
    except ValueError as e:
        raise CLIError(str(e)) from None
    folder = args.output
    check_folder(folder)
    try:
        spec, what = _spec(args, models, estimator)
        os.makedirs(folder, exist_ok=True)
        # Refuses records made with other settings, or a study already writing there; released for the run.
        with study.Records(folder, spec.header()) as records:
            done = sum(c in records for c in spec.cells()) if isinstance(spec, study.AlphaStudy) else 0
        mesh = device_mesh()
        print(f"sweep: {what}; estimator={estimator.name}; {estimator.describe().split('; ', 1)[-1]}, "
              f"seed={args.seed}; {mesh.size} device(s) ({mesh.devices.flat[0].platform}, batching "
              f"{strategy.describe()}); writing to {folder}",
              flush=True)
        t_start = time.perf_counter()
        cells = len(spec.cells()) if isinstance(spec, study.AlphaStudy) else None
        if done:
            print(f"resuming: {done} of {cells} cells already recorded in {study.RECORDS}", flush=True)
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
                warn(f"{label}: {line}", stream=sys.stderr)
            if (record.get("batches") or 1) > 1:
                tqdm.write(f"{label}: split into {record['batches']} batches to fit in memory "
                           f"({record['batch_gib']:.2f} GiB per device each)", file=sys.stderr)
            bar.update(1)

        with bar:
            if isinstance(spec, study.AlphaStudy):
                bar.update(done)
                rows = study.run_alpha_study(spec, folder, mesh=mesh, on_cell=on_cell, strategy=strategy)
            else:
                rows = study.run_file_study(spec, folder, mesh=mesh, on_cell=on_cell, strategy=strategy)
    except study.StudyError as e:
        raise CLIError(str(e)) from None
    except ValueError as e:
        if isinstance(e, ScenarioError):
            raise
        raise CLIError(str(e)) from None
    written = draw(folder, rows)
    print(f"wrote {os.path.join(folder, study.TABLE)} ({len(rows)} rows), {study.RECORDS}"
          + "".join(f", {os.path.basename(p)}" for p in written)
          + (", results/" if isinstance(spec, study.FileStudy) else ""))
    if isinstance(spec, study.AlphaStudy):
        print(f"\nmean over tracks of each track's mean over steps 1-{spec.steps} (± 95% half-width)")
        print(alpha_summary(rows))
    else:
        print("\nmean over scenario files at each file's last step")
        print(summary_table(rows, list(dict.fromkeys(r["model"] for r in rows))))
    total = time.perf_counter() - t_start
    print(f"\nsweep finished in {total:.1f} s (this run: compile {compile_s:.1f} s, batched runs "
          f"{run_s:.1f} s; {len(rows)} track-steps in the table)")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("sweep", help="a resumable study: alphas x models x tracks (Fig. 5), or scenario files")
    p.add_argument("-o", "--output", default=os.path.join("runs", "sweep"),
                   help="output folder (a folder with a finished or interrupted study resumes it)")
    p.add_argument("--alphas", default=None,
                   help=f"alphas of Eq. 18, comma-separated (default {SWEEP_DEFAULTS['alphas']})")
    p.add_argument("--models", default=None,
                   help="classifier models, comma-separated: mirror, independent, none, or learned:PATH (a "
                        "model file of scripts/fit_classifier.py) (default: mirror,independent,none; with "
                        "--scenarios: each file's own)")
    p.add_argument("--tracks", type=int, default=None,
                   help=f"simulated tracks per cell (default {SWEEP_DEFAULTS['tracks']})")
    p.add_argument("--steps", type=int, default=None, help=f"steps per track (default {SWEEP_DEFAULTS['steps']})")
    p.add_argument("--K", type=float, default=None, help=f"classifier K of Eq. 18 (default {SWEEP_DEFAULTS['K']:g})")
    p.add_argument("--scenarios", default=None, metavar="DIR_OR_GLOB",
                   help="run over these scenario files instead of simulating (files of equal shape are batched)")
    p.add_argument("--batching", default="auto", metavar="{auto,vmap,map,map:N}",
                   help="how a batch's tracks share its compiled program: vmap (one vmap over all of them, "
                        "accelerators), map (one track after another, CPU), map:N (N tracks vmapped at a "
                        "time); auto (default): map on a CPU, vmap elsewhere. Changes no number")
    add_estimator_options(p, seed_help="track t is simulated with seed + t and weighed with PRNG seed seed + t",
                          defaults={"capacity": str(SWEEP_CAPACITY)})
    p.set_defaults(func=cmd_sweep)
