"""What every subcommand shares: the error type, warnings, number formatting, estimator options."""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from typing import NoReturn, TextIO

from tqdm import tqdm

from ..estimators import ESTIMATORS, make_estimator
from ..estimators.base import AbstractEstimator
from ..estimators.hybrid.weighers import WEIGHERS
from ..estimators.smoothing import parse_smoother

PROG = "hybridslam"
CLASSIFIERS = ("mirror", "independent", "none")
WEIGHTS = tuple(WEIGHERS)


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

ESTIMATOR_OPTIONS = ("capacity", "samples", "weights", "prune_ratio", "gate", "max_children", "exhaustive", "clutter",
                     "max_detections", "max_steps", "smoother", "new_landmark")


def add_estimator_options(p: argparse.ArgumentParser, seed_help: str = "PRNG seed of the Monte-Carlo draws",
                          capacity_default: str = "64") -> None:
    """``--estimator`` and the settings it may take (each estimator rejects the ones it has no use for)."""
    p.add_argument("--estimator", choices=tuple(ESTIMATORS), default="hybrid",
                   help="association strategy: hybrid (Tchuiev et al., default), ml, gpda, max-mixture (Doherty's "
                        "thesis Ch. 3-4) or multimodal (Ch. 5)")
    p.add_argument("--samples", type=int, default=None,
                   help="Monte-Carlo draws: per parent for --weights sampled (n_s of Eq. 16, default 1000), per "
                        "candidate child for laplace-is (default 64), per child for multimodal (default 256)")
    p.add_argument("--capacity", type=int, default=None,
                   help=f"most components kept (hybrid, multimodal; default {capacity_default})")
    p.add_argument("--prune-ratio", type=float, default=None,
                   help="hybrid: drop components below w_max / ratio (the paper's 150)")
    p.add_argument("--weights", choices=WEIGHTS, default=None,
                   help="hybrid: association weights, laplace-is (low-variance Eq. 16, default), sampled (the paper's "
                        "Monte-Carlo Eq. 16) or linearized (deterministic)")
    p.add_argument("--gate", type=int, default=None,
                   help="candidate objects per detection after Mahalanobis gating (ml, gpda, max-mixture, "
                        "multimodal: default 3; hybrid: default every object)")
    p.add_argument("--max-children", type=int, default=None,
                   help="hypotheses kept while a step's associations are built one detection at a time: the hybrid's "
                        "children (default 64), ml/gpda/max-mixture's joint assignments (default 64); drops near "
                        "the best are counted and reported")
    p.add_argument("--exhaustive", action="store_true", default=None,
                   help="hybrid: enumerate every child (exponential in the detections; the exact reference)")
    p.add_argument("--clutter", type=clutter_density, default=None, metavar="{LOG_DENSITY,none}",
                   help="a detection may be clutter, with this log density over [range, bearing] (e.g. "
                        "log(0.01 / (max_range * fov))); default: the file's sensor.clutter_log_density (written by "
                        "hybridslam import), none without it; 'none': every detection is of an object (ml, gpda, "
                        "max-mixture, multimodal: a known map only; hybrid: both)")
    p.add_argument("--smoother", type=_smoother, default=None, metavar="{full,lag:L,filter}",
                   help="full (default): every component keeps its trajectory and relinearizes it at every step, "
                        "as the papers' smoothers do; lag:L: only the last L steps and the map, older poses "
                        "marginalized (bounded cost per step); filter: the joint Gaussian over the current pose "
                        "and the map only")
    p.add_argument("--new-landmark", default=None, metavar="{density,mahalanobis:TAU}",
                   help="an unknown map's rule for a new object: density (default: the file's new-object density "
                        "competes with the known objects) or mahalanobis:TAU (thesis Sec. 3.2.1: new only where "
                        "every known object lies beyond the squared Mahalanobis distance TAU, e.g. 9.21)")
    p.add_argument("--max-detections", type=int, default=None,
                   help="detection slots per step (default: the largest step); a shared value lets files share "
                        "one compiled step")
    p.add_argument("--max-steps", type=int, default=None,
                   help="history length (default: the file's steps); a shared value lets files share one compiled step")
    p.add_argument("--seed", type=int, default=0, help=seed_help)


def estimator_from_args(args: argparse.Namespace, *, classifier=None, **overrides) -> AbstractEstimator:
    """The estimator the options name; a setting it cannot take is a :class:`CLIError` naming it."""
    options = {name: getattr(args, name, None) for name in ESTIMATOR_OPTIONS}
    for name, value in options.items():
        if isinstance(value, (int, float)) and not isinstance(value, bool) and name not in ("prune_ratio", "clutter") \
                and value < 1:
            raise CLIError(f"--{name.replace('_', '-')}: expected a positive number, got {value}")
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


def clutter_density(text: str) -> float | str:
    """``--clutter``'s (and the importers' ``--clutter-log-density``) value: a finite log density or ``none`` (an argparse error otherwise)."""
    if text.strip().lower() == "none":
        return "none"
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite log density or 'none', got {text!r}")
    return value


def _smoother(text: str) -> str:
    """``--smoother``'s value, checked here so that a typo is an argparse error naming the option."""
    try:
        parse_smoother(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--smoother: ")) from None
    return text
