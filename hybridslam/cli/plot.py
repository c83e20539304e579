"""``hybridslam plot``: a study's plots redrawn from its table, or one run drawn from its result file."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence

from ..io.result import load_result
from ..io.scenario import load_scenario
from ..studies import study
from .common import CLIError, check_writable


def draw(folder: str, rows: Sequence[dict]) -> list[str]:
    """The study's plots from its table rows; returns the files written."""
    # Imported here: matplotlib costs every other command 0.3-0.5 s of start-up.
    from ..analysis import plot

    if not rows:
        return []
    if "alpha" in rows[0]:
        path = os.path.join(folder, "alpha_sweep.png")
        plot.plot_alpha_sweep(rows, path)
    else:
        path = os.path.join(folder, "metrics.png")
        plot.plot_metrics(rows, path)
    return [path]


def cmd_plot(args: argparse.Namespace) -> int:
    """Redraw a study's plots from its table, or draw one run from its result file."""
    if os.path.isfile(args.path):
        return _plot_run(args)
    if args.scenario is not None or args.output is not None:
        raise CLIError(f"{args.path!r}: --scenario and -o are for a result file, not a study folder")
    path = os.path.join(args.path, study.TABLE)
    if not os.path.isfile(path):
        raise CLIError(f"{args.path!r}: no {study.TABLE} (run hybridslam sweep -o {args.path} first)")
    rows = study.read_table(path)
    if not rows:
        raise CLIError(f"{path}: the table is empty (no finished cell yet)")
    written = draw(args.path, rows)
    print("wrote " + ", ".join(written))
    return 0


def _plot_run(args: argparse.Namespace) -> int:
    """``hybridslam plot RESULT --scenario SCENARIO [-o PNG]``: :func:`hybridslam.analysis.plot.plot_run`."""
    if args.scenario is None:
        raise CLIError(f"{args.path!r} is a result file: name the scenario it was run on with --scenario FILE")
    scenario = load_scenario(args.scenario)
    result = load_result(args.path)
    output = args.output if args.output is not None else os.path.splitext(args.path)[0] + ".png"
    check_writable(output)
    from ..analysis.plot import plot_run  # here: matplotlib costs every other command 0.3-0.5 s

    try:
        plot_run(scenario, result, output)
    except ValueError as e:
        raise CLIError(f"{args.path}: {e}") from None
    print(f"wrote {output}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("plot", help="redraw a study's plots from its table.csv, or draw one run's result file")
    p.add_argument("path", help="a study's output folder, or a result file (then --scenario)")
    p.add_argument("--scenario", default=None, help="with a result file: the scenario file it was run on")
    p.add_argument("-o", "--output", default=None,
                   help="with a result file: the image to write (default: the result's name with .png)")
    p.set_defaults(func=cmd_plot)
