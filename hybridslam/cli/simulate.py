"""``hybridslam simulate`` and ``hybridslam hallway``: write simulated scenario files."""

from __future__ import annotations

import argparse
import math
import os

from ..io.scenario import save_scenario
from ..sim import hallway
from ..sim.paper import simulate
from .common import CLIError, check_folder, check_writable, floats


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write one paper-setup scenario (Sec. V) to ``args.output``."""
    if args.steps < 1:
        raise CLIError(f"--steps: expected a positive number of steps, got {args.steps}")
    if not math.isfinite(args.alpha):
        raise CLIError(f"--alpha: expected a finite number, got {args.alpha}")
    if not (math.isfinite(args.K) and args.K > 0):
        raise CLIError(f"--K: expected a positive number, got {args.K}")
    check_writable(args.output)
    scenario = simulate(args.seed, steps=args.steps, alpha=args.alpha, K=args.K)
    save_scenario(scenario, args.output)
    num_det = sum(len(s.detections) for s in scenario.steps)
    print(f"wrote {args.output}: {scenario.num_steps} steps, {scenario.num_objects} objects, "
          f"{num_det} detections (seed {args.seed}, alpha {args.alpha:g}, K {args.K:g})")
    return 0


def cmd_hallway(args: argparse.Namespace) -> int:
    """Write the hallway study's scenarios (thesis Sec. 5.4.1): one file per (noise level, seed)."""
    levels = hallway.LEVELS if args.levels is None else floats(args.levels, "--levels")
    if not all(v > 0 for v in levels):
        raise CLIError(f"--levels: expected positive traces of the odometry covariance, got {args.levels!r}")
    if args.seeds < 1:
        raise CLIError(f"--seeds: expected a positive number, got {args.seeds}")
    if args.steps is not None and args.steps < 1:
        raise CLIError(f"--steps: expected a positive number of steps, got {args.steps}")
    check_folder(args.output)
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


def add_parsers(sub) -> None:
    p = sub.add_parser("simulate", help="write a paper-setup scenario file (Sec. V)")
    p.add_argument("--seed", type=int, default=0, help="track and measurement seed")
    p.add_argument("--steps", type=int, default=10, help="number of steps T")
    p.add_argument("--alpha", type=float, default=0.25, help="classifier alpha of Eq. 18")
    p.add_argument("--K", type=float, default=15.0, help="classifier K of Eq. 18")
    p.add_argument("-o", "--output", required=True, help="scenario file to write")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("hallway", help="write the hallway study's scenario files (thesis Sec. 5.4.1)")
    p.add_argument("-o", "--output", required=True, help="folder for hallway_tr<level>_seed<s>.json")
    p.add_argument("--levels", default=None,
                   help="traces of the odometry covariance, comma-separated (default: 0.005 to 0.05 in 5 steps)")
    p.add_argument("--seeds", type=int, default=1, help="seeds 0..N-1 per level")
    p.add_argument("--steps", type=int, default=None, help="steps per run (default: one loop, 60)")
    p.add_argument("--known-map", action="store_true",
                   help="list every landmark as a prior object (no discovery section)")
    p.set_defaults(func=cmd_hallway)
