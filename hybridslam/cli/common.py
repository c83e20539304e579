"""What every subcommand shares: the error type, warnings, number formatting, estimator options."""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NoReturn, TextIO

from tqdm import tqdm

from ..estimators import ESTIMATORS, make_estimator
from ..estimators.base import AbstractEstimator
from ..estimators.options import Option, option_help
from ..estimators.options import clutter_density as _clutter_density
from ..estimators.loops.settings import MISS_MODELS, LoopClosureSettings
from ..estimators.registry import DEFAULT, estimator_options

PROG = "hybridslam"
CLASSIFIERS = ("mirror", "independent", "none")


def add_misses_option(p: argparse.ArgumentParser, flag: str, what: str) -> None:
    """``flag`` (``LoopClosureSettings.misses``): how an undetected (step, object) pair in view counts
    against ``what`` (a merge, a closure)."""
    p.add_argument(flag, choices=MISS_MODELS, default=LoopClosureSettings.misses,
                   help=f"how a (step, object) pair in view yet undetected counts against {what}: marginal "
                        "(default: weighed by how surely the object was in view, under the solved graph's "
                        "covariance) or point (in view at the estimate, 0.5 m and 0.2 rad inside the edge)")


class CLIError(Exception):
    """A user error: reported as one line ``hybridslam: error: <message>``, exit status 2."""


class Parser(argparse.ArgumentParser):
    """argparse, but usage errors raise :class:`CLIError` instead of printing usage and exiting."""

    def error(self, message: str) -> NoReturn:
        raise CLIError(message)


def warn(message: str, stream: TextIO | None = None) -> None:
    """One ``WARNING:`` line on stderr (through tqdm while a progress bar is open)."""
    line = f"WARNING: {message}"
    if stream is None:
        print(line, file=sys.stderr, flush=True)
    else:
        tqdm.write(line, file=stream)


def fmt(value: float | None, spec: str) -> str:
    """A table cell: blank for a missing value, ``-0`` shown as ``0``."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return format(value + 0.0, spec)


def csv_number(value: float | int | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return str(value) if isinstance(value, int) else format(value + 0.0, ".10g")


def check_writable(path: str) -> None:
    """Fail early (before a long run) when ``path`` cannot be created."""
    parent = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise CLIError(f"cannot write {path!r}: is a directory")
    if not os.path.isdir(parent):
        raise CLIError(f"cannot write {path!r}: directory {parent!r} does not exist")
    if not os.access(parent, os.W_OK):
        raise CLIError(f"cannot write {path!r}: permission denied")


def check_folder(folder: str, option: str = "-o") -> None:
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise CLIError(f"{option} {folder!r}: exists and is not a folder")


def floats(text: str, option: str) -> tuple[float, ...]:
    """Comma-separated finite numbers, or a :class:`CLIError` naming the option."""
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise CLIError(f"{option}: expected comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise CLIError(f"{option}: expected finite comma-separated numbers, got {text!r}")
    return values


def add_result_format_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--result-format", type=int, choices=(1, 2), default=2,
                   help="result file format (docs/file_format.md): 2, each step's parents and own associations "
                        "(linear in the run); 1, every whole history at every step, for readers of format 1 only "
                        "(a 1700-step log's file: 300 MB)")


# --------------------------------------------------------------------------- #
# Estimator options
# --------------------------------------------------------------------------- #


def command_line_options() -> dict[str, Option]:
    """The estimator options the commands offer, by name (every registered estimator's)."""
    return {name: o for name, o in estimator_options().items() if o.command_line}


def _argument_type(parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """``parse`` for argparse: its ``ValueError`` an argparse error with its message (the option's
    name, which argparse adds, taken off the front)."""
    if parse in (int, float, str):
        return parse  # argparse's own message ("invalid int value: 'x'")

    def typed(text: str) -> Any:
        try:
            return parse(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(re.sub(r"^--[\w-]+: ", "", str(e))) from None

    typed.__name__ = parse.__name__
    return typed


clutter_density = _argument_type(_clutter_density)  # --clutter's, and the importers' --clutter-log-density


def add_estimator_options(p: argparse.ArgumentParser, seed_help: str = "PRNG seed of the Monte-Carlo draws",
                          defaults: Mapping[str, str] | None = None) -> None:
    """``--estimator`` and the settings it may take (each estimator rejects the ones it has no use for).

    The options and their help come from the registered estimators' fields
    (:mod:`hybridslam.estimators.options`); ``defaults``: a default this command chooses instead of
    the estimators' own, by option name, for the help."""
    p.add_argument("--estimator", choices=tuple(ESTIMATORS), default=DEFAULT,
                   help="association strategy: " + ", ".join(f"{name} ({cls.reference})"
                                                             for name, cls in ESTIMATORS.items())
                        + f"; default {DEFAULT}")
    for name, option in command_line_options().items():
        text = option_help(option, ESTIMATORS, (defaults or {}).get(name))
        if option.parse is None:
            p.add_argument(option.flag, action="store_true", default=None, help=text)
        else:
            p.add_argument(option.flag, type=_argument_type(option.parse), choices=option.choices, default=None,
                           metavar=option.metavar, help=text)
    p.add_argument("--seed", type=int, default=0, help=seed_help)


def estimator_from_args(args: argparse.Namespace, *, classifier=None, **overrides) -> AbstractEstimator:
    """The estimator the options name; a setting it cannot take is a :class:`CLIError` naming it."""
    offered = command_line_options()
    options = {name: getattr(args, name, None) for name in offered}
    for name, value in options.items():
        if offered[name].parse is int and value is not None and value < 1:  # counts
            raise CLIError(f"{offered[name].flag}: expected a positive number, got {value}")
    options.update({k: v for k, v in overrides.items() if v is not None or k not in options})
    try:
        return make_estimator(args.estimator, classifier=classifier, **options)
    except ValueError as e:
        raise CLIError(str(e)) from None


def settings_line(estimator: AbstractEstimator) -> str:
    """The estimator's settings for a command's first line of output."""
    return estimator.describe().split("; ", 1)[-1]


def names(values: Sequence[str]) -> str:
    return ", ".join(values)
