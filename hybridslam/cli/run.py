"""``hybridslam run``: one estimator over one scenario file, a per-step table, a result file."""

from __future__ import annotations

import argparse
import dataclasses
import re
from collections import Counter

from ..analysis.map_error import map_error
from ..analysis.trajectory import error_summary
from ..driver import run
from ..estimators.base import AbstractEstimator, StepInfo
from ..estimators.loops.settings import LoopClosureSettings
from ..estimators.profiles import LONG_RUN_STEPS, PROFILES, Profile, file_summary, recommended
from ..io.result import ResultWriter, StepRecord
from ..models.scenario import Scenario
from ..io.scenario import ScenarioError, load_scenario
from .common import (
    CLASSIFIERS,
    CLIError,
    add_estimator_options,
    add_misses_option,
    command_line_options,
    add_result_format_option,
    check_writable,
    estimator_from_args,
    fmt,
    warn,
)

TABLE_HEADER = (f"{'k':>4} {'det':>4} {'alive':>6} {'entropy':>9} {'det_cov':>11} "
                f"{'err_wmax':>9} {'err_wavg':>9} {'step_ms':>9}")


def table_row(record: StepRecord, num_detections: int, seconds: float) -> str:
    m = record.metrics
    return (f"{record.k:>4} {num_detections:>4} {int(m['num_components']):>6} "
            f"{fmt(m['entropy'], '.4f'):>9} {fmt(m['det_cov'], '.4e'):>11} "
            f"{fmt(m.get('err_wmax'), '.4f'):>9} {fmt(m.get('err_wavg'), '.4f'):>9} "
            f"{fmt(1e3 * seconds, '.1f'):>9}")


REPEATS = 3  # per-step warnings of one kind printed before the rest are only counted


class WarningThrottle:
    """Prints a run's per-step warnings, each kind (the text with its numbers blanked) at most
    :data:`REPEATS` times, and at the end how many more steps each silenced kind had: a real log
    can raise the same warning at dozens of steps, and the table must stay readable."""

    def __init__(self) -> None:
        self.seen: Counter[str] = Counter()
        self.example: dict[str, str] = {}

    def __call__(self, line: str) -> None:
        message = line.split(": ", 1)[-1]  # without "step k: "
        kind = re.sub(r"\d+(\.\d+)?(e[-+]?\d+)?", "#", message)
        self.seen[kind] += 1
        self.example.setdefault(kind, message)
        if self.seen[kind] < REPEATS:
            warn(line)
        elif self.seen[kind] == REPEATS:
            warn(f"{line} (this warning is not repeated; its count follows at the end)")

    def finish(self) -> None:
        for kind, count in self.seen.items():
            if count > REPEATS:
                warn(f"and at {count - REPEATS} more step(s): {self.example[kind]}")


def closure_summary(hook) -> str:
    """The line ``hybridslam run --close-loops`` prints after the run: each added hypothesis's
    changes against its parent (:class:`~hybridslam.estimators.loops.online.ClosureHypothesis`)."""
    added = "; ".join(str(c) for c in hook.closures)
    return (f"loop closure during the run: {len(hook.closures)} hypotheses added"
            f"{': ' + added if added else ''}"
            + (f"; {hook.declined} declined (no likelier than a full belief's weakest component)" if hook.declined else "")
            + f"; its searches took {hook.seconds:.2f} s")


def long_run_note(estimator: AbstractEstimator, scenario: Scenario) -> str | None:
    """The note ``run`` prints before a long file under the full smoother, else ``None``.

    The full smoother re-solves the whole trajectory at every step, so its steps slow as the run
    goes (docs/studies/mrclam.md, "Whole logs": 871 s of MRCLAM, the hybrid belief from 20 to about 550 ms
    per step, past the log's 0.5 s steps near the end); ``incremental:L`` keeps them bounded and
    still ends at the batch solution.
    """
    smoother = getattr(estimator, "smoother", None)
    if smoother is None or not smoother.whole_trajectory or scenario.num_steps <= LONG_RUN_STEPS:
        return None
    return (f"note: {scenario.num_steps} steps under the full smoother, which re-solves the whole trajectory at "
            f"every step: the steps slow as the run goes; --smoother incremental:50 keeps them bounded and ends at "
            f"the same batch solution (docs/performance.md, Whole logs)")


def chosen_settings(args: argparse.Namespace, profile: Profile) -> dict:
    """The profile's options that no flag of ``args`` overrides (:meth:`Profile.merged`)."""
    explicit = {name: getattr(args, name, None) for name in command_line_options()}
    return {k: v for k, v in profile.merged(**explicit).items() if explicit.get(k) is None}


def settings_note(scenario: Scenario, profile: Profile, chosen: dict, close_loops: int | None) -> str:
    """The line ``run`` prints about the settings it chose for the file (:mod:`hybridslam.estimators.profiles`)."""
    flags = Profile(profile.estimator, profile.kind, chosen, close_loops, profile.reason).flags()
    if profile.options == {} and profile.reason.startswith("--profile"):  # recommended(..., "paper")
        return f"settings: {profile.reason}"
    head = f"settings for {file_summary(scenario)}: "
    if not flags and not profile.options and profile.close_loops is None:
        return head + f"the {profile.estimator} estimator's own defaults ({profile.reason})"
    overridden = [f"--{k.replace('_', '-')}" for k in profile.options if k not in chosen]
    overridden += ["--close-loops"] if profile.close_loops is not None and close_loops is None else []
    return (head + (flags or "none of the chosen settings") + f" ({profile.reason}"
            + (f"; overridden: {', '.join(overridden)}" if overridden else "")
            + "; explicit flags override them; --profile paper for the estimator's own defaults)")


def cmd_run(args: argparse.Namespace) -> int:
    """Run the estimator over a scenario file, print a per-step table, write the result file."""
    scenario = load_scenario(args.scenario)
    if args.close_loops is not None and args.no_close_loops:
        raise CLIError("--no-close-loops: not with --close-loops")
    profile = recommended(scenario, args.estimator, args.profile)
    chosen = chosen_settings(args, profile)
    estimator = estimator_from_args(args, classifier=args.classifier, **chosen)
    try:
        estimator.init(scenario)  # every setting the scenario rejects, before compiling anything
    except ValueError as e:
        if isinstance(e, ScenarioError):
            raise
        raise CLIError(str(e)) from None
    check_writable(args.output)
    if args.plot is not None:
        check_writable(args.plot)
    hook = None
    loops = None if args.close_loops is not None or args.no_close_loops else profile.loops(smoother=args.smoother)
    if loops is not None:
        hook = profile.between_steps(estimator, scenario, loops, misses=args.loop_misses)
        loops = None if hook is None else loops
    print(settings_note(scenario, profile, chosen, loops))
    if args.close_loops is not None:
        from ..estimators.loops.online import OnlineLoopClosure

        try:
            hook = OnlineLoopClosure(estimator, scenario,
                                     LoopClosureSettings(gap=args.close_loops, misses=args.loop_misses))
        except ValueError as e:
            raise CLIError(f"--close-loops: {e}") from None
    print(f"{args.scenario}: {scenario.num_steps} steps, {scenario.num_objects} objects; estimator={estimator.name}; "
          f"{estimator.describe().split('; ', 1)[-1]}, seed={args.seed}")
    note = long_run_note(estimator, scenario)
    if note is not None:
        print(note)
    print("compiling the step ...", flush=True)
    num_det = [len(s.detections) for s in scenario.steps]
    throttle = WarningThrottle()

    with ResultWriter(args.output, args.result_format) as writer:  # each record written as it comes

        def on_step(record: StepRecord, info: StepInfo, seconds: float) -> None:
            writer.add(record)
            if record.k == 1:
                print(TABLE_HEADER)
            print(table_row(record, num_det[record.k - 1], seconds), flush=True)
            for line in info.warnings():
                throttle(line)

        result = run(estimator, scenario, seed=args.seed, on_step=on_step, between_steps=hook,
                     keep_associations=False).result
        throttle.finish()
        if hook is not None:
            result = dataclasses.replace(result, estimator=f"{result.estimator}, loop closure during the run "
                                                            f"({len(hook.closures)} hypotheses added)")
            print(closure_summary(hook))
            if hook.replaced:
                warn(f"loop closure: {hook.replaced} component(s) dropped to make room for its hypotheses "
                     "(raise --capacity)")
        timing = result.timing or {"compile_s": 0.0, "step_s": []}
        steps_s = sum(timing["step_s"])
        per_step = 1e3 * steps_s / max(len(timing["step_s"]), 1)
        print(f"compile time {timing['compile_s']:.2f} s; {scenario.num_steps} steps in {steps_s:.2f} s "
              f"({per_step:.1f} ms/step)")
        errors = error_summary(result, scenario)
        if errors:
            line = (f"translation error (m): online APE {errors['ape_online']:.3f}, "
                    f"RPE {errors.get('rpe_online', float('nan')):.3f}")
            if "ape_smoothed" in errors:
                line += (f"; smoothed APE {errors['ape_smoothed']:.3f}, "
                         f"RPE {errors.get('rpe_smoothed', float('nan')):.3f}")
            print(line + f"; last pose {errors['final']:.3f}")
        mapped = map_error(scenario, result)
        if mapped.get("objects"):
            print(f"map error (m): {mapped['objects']} objects with detections, {mapped['mean_m']:.3f} "
                  f"from their true objects on average (median {mapped['median_m']:.3f})")
        writer.finish(result)
    print(f"wrote {args.output}")
    if args.plot is not None:
        from ..analysis.plot import plot_run  # here: matplotlib costs every other command 0.3-0.5 s

        plot_run(scenario, result, args.plot)
        print(f"wrote {args.plot}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="run an estimator on a scenario file, write a result file")
    p.add_argument("scenario", help="scenario file (hybridslam-scenario/1)")
    p.add_argument("-o", "--output", required=True, help="result file to write")
    p.add_argument("--classifier", choices=CLASSIFIERS, default=None,
                   help="classifier model (default: the scenario's)")
    p.add_argument("--close-loops", type=int, nargs="?", const=20, default=None, metavar="GAP",
                   help="hybrid or multimodal, full smoother, unknown map: after each step search the best component's map for "
                        "loop closures (an object first seen more than GAP steps, default 20, after another's last "
                        "detection) and add what is found as a hypothesis (hybridslam.estimators.loops.online); "
                        "--profile auto adds it on larger unknown-map files with classes")
    add_misses_option(p, "--loop-misses", "a loop closure")
    p.add_argument("--no-close-loops", action="store_true",
                   help="no loop closure during the run, where the settings chosen for the file would add it")
    p.add_argument("--profile", choices=PROFILES, default="auto",
                   help="auto (default): the options not given are chosen by the file (docs/settings.md: the "
                        "paper's configuration on small files; capacity 16, gate 3, linearized weights and, on an "
                        "unknown map with classes, --close-loops on larger ones; past 500 steps incremental:50, "
                        "incremental:20 for ml, gpda and max-mixture); paper: the estimator's own defaults, whatever "
                        "the file")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="also draw the run (map and trajectories, error and components per step) to this image")
    add_result_format_option(p)
    add_estimator_options(p, defaults={"capacity": "64, or 16 where --profile auto chooses it"})
    p.set_defaults(func=cmd_run)
