"""``hybridslam close-loops``: a finished run's loops closed by a joint search over the whole map."""

from __future__ import annotations

import argparse
import math

from ..analysis.map_error import map_error
from ..analysis.trajectory import error_summary
from ..estimators.loops.closure import close_loops
from ..estimators.loops.settings import LoopClosureSettings
from ..io.result import load_result, save_result
from ..io.scenario import load_scenario
from .common import CLIError, add_misses_option, add_result_format_option, check_writable, warn


def _errors(label: str, result, scenario) -> str:
    e = error_summary(result, scenario)
    if not e or "ape_smoothed" not in e:
        return f"{label}: no ground truth or no smoothed trajectory"
    line = f"{label}: smoothed APE {e['ape_smoothed']:.3f} m, smoothed last pose {e['final_smoothed']:.3f} m"
    mapped = map_error(scenario, result)
    if "mean_m" in mapped:
        line += f", map error {mapped['mean_m']:.3f} m ({mapped['objects']} objects)"
    return line


def cmd_close_loops(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    result = load_result(args.result)
    try:
        settings = LoopClosureSettings(gap=args.gap, revisit_log_odds=args.revisit_log_odds, beam=args.beam,
                                       misses=args.misses)
    except ValueError as e:
        raise CLIError(str(e)) from None
    check_writable(args.output)
    try:
        closed, report = close_loops(scenario, result, settings)
    except ValueError as e:
        raise CLIError(f"{args.result}: {e}") from None
    for line in report.summary().splitlines():
        (warn if line.startswith("warning") else print)(line.removeprefix("warning: "))
    for c in report.closures:
        print(f"  merged {', '.join(f'{a}->{b}' for a, b in c.merges)}: log odds {c.log_bayes_factor:.2f}, "
              f"smoother cost {c.cost_before:.1f} -> {c.cost_after:.1f}")
    if scenario.true_robot_poses is not None:
        if result.trajectory is not None:
            print(_errors("before", result, scenario))
        print(_errors("after", closed, scenario))
    save_result(closed, args.output, args.result_format)
    print(f"wrote {args.output}")
    return 0


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def add_parser(sub) -> None:
    p = sub.add_parser("close-loops", help="close a finished run's loops (joint search over the map), "
                       "write a new result file")
    p.add_argument("scenario", help="the scenario file the run was made on (unknown map)")
    p.add_argument("result", help="its result file (the last step's top component is used)")
    p.add_argument("-o", "--output", required=True, help="result file to write")
    add_result_format_option(p)
    p.add_argument("--gap", type=int, default=20,
                   help="steps between an old object's last detection and a late object's first (default 20)")
    p.add_argument("--revisit-log-odds", type=_finite, default=0.0,
                   help="prior log odds per merge that a late object is an old one (default 0)")
    p.add_argument("--beam", type=int, default=LoopClosureSettings.beam,
                   help=f"partial merge sets kept by the search (default {LoopClosureSettings.beam}; "
                        "what it drops is counted and warned about)")
    add_misses_option(p, "--misses", "a merge")
    p.set_defaults(func=cmd_close_loops)
