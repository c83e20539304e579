"""The ``hybridslam`` command: one module per subcommand, :func:`main` is the entry point.

    hybridslam simulate --seed 0 --steps 10 --alpha 0.25 -o scenario.json
    hybridslam run scenario.json -o result.json [--estimator hybrid|ml|gpda|max-mixture|multimodal] [--plot PNG] ...
    hybridslam sweep [--alphas 0,0.25,0.5] [--models mirror,independent,none] [--tracks 8] -o runs/sweep
    hybridslam sweep --scenarios 'logs/*.json' [--estimator ...] -o runs/logs
    hybridslam plot runs/sweep
    hybridslam plot result.json --scenario scenario.json [-o result.png]
    hybridslam demo [-o runs/demo] [--tracks 4] [--steps 10]
    hybridslam hallway -o runs/hallway [--levels ...] [--seeds 5] [--steps 60] [--known-map]
    hybridslam import mrclam DATASET_DIR --robot N -o FILE [--start S] [--duration D] [--unknown-map] [--identity-filter]
    hybridslam close-loops scenario.json result.json -o closed.json [--revisit-log-odds X]

Every user error (bad option, missing or malformed file, invalid setting, unwritable output) ends
with exit status 2 and one line ``hybridslam: error: <message>`` on stderr. Compiled steps are kept
in JAX's persistent cache between runs (:mod:`.cache`; ``HYBRIDSLAM_NO_CACHE=1`` turns it off).

Environment: ``HYBRIDSLAM_CACHE_DIR`` (the cache's folder), ``HYBRIDSLAM_NO_CACHE=1`` (no cache),
``HYBRIDSLAM_BUCKETS`` (compiled sizes of the smoother's live-prefix solves, default 4; 1: the whole
graph only), ``HYBRIDSLAM_XLA_DEFAULTS=1`` (XLA's default compile options instead of the elemental
emitters on the CPU, :func:`hybridslam.driver.compiler_options`), ``HYBRIDSLAM_CPU_DEVICES`` (the CPU
devices ``sweep`` splits the host into, default one per core,
:func:`hybridslam.studies.strategies.split_cpu_into_cores`). Bad values are one-line errors.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from ..config import setup
from ..io.scenario import ScenarioError
from . import cache, demo, importers, loops, plot, run, simulate, sweep
from .common import PROG, CLIError, Parser
from .tables import alpha_summary as alpha_summary
from .tables import summary_table as summary_table

__all__ = ["CLIError", "alpha_summary", "build_parser", "main", "summary_table"]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog=PROG, description="Semantic SLAM with ambiguous data association.")
    sub = parser.add_subparsers(dest="command", required=True,
                                metavar="{simulate,run,demo,sweep,plot,hallway,import,close-loops}")
    simulate.add_parsers(sub)
    run.add_parser(sub)
    demo.add_parser(sub)
    sweep.add_parsers(sub)
    plot.add_parser(sub)
    importers.register(sub)
    loops.add_parser(sub)
    return parser


def _check_environment() -> None:
    """The package's environment variables (``HYBRIDSLAM_BUCKETS``, ``HYBRIDSLAM_XLA_DEFAULTS``), checked
    before any work: a bad value is a one-line error naming the variable."""
    from ..driver import xla_defaults_from_environment
    from ..inference.buckets import buckets_from_environment

    try:
        buckets_from_environment()
        xla_defaults_from_environment()
    except ValueError as e:
        raise CLIError(f"environment: {e}") from None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``hybridslam`` console script; returns the exit status."""
    setup()  # float64, XLA's thread pool, OpenBLAS's threads: before any array (hybridslam.config)
    try:
        args = build_parser().parse_args(argv)
        _check_environment()
        cache.enable()
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
