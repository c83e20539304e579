"""Many scenarios through :func:`hybridslam.run`, compiled once: :func:`run_many`.

A loop of ``hybridslam.run`` calls over files of different lengths and detection counts compiles
one step program per shape (seconds each on a CPU). :func:`run_many` sizes the estimator for all of
them at once (:func:`~hybridslam.studies.batch.shared_shapes`: the most detections of any step,
the longest run), so every scenario of equal objects and classes runs the same executable; it is
compiled fully (not at LLVM level 0, as a lone short run is: :data:`hybridslam.compilation.QUICK_RUN_STEPS`)
when the scenarios together have more steps than a short run.

A scenario's numbers equal those :func:`hybridslam.run` gives it with the padded estimator exactly,
and those of the unpadded estimator to floating-point rounding (padded detection slots are masked,
padded history steps are never reached).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import numpy as np

from .. import compilation, driver
from ..driver import Run, inputs_from_scenario, run, scan
from ..estimators.base import AbstractEstimator
from ..models.scenario import Scenario
from .batch import shared_shapes


def shape_key(scenario: Scenario) -> tuple:
    """What must be equal for two scenarios to share a compiled step (padding cannot equalize it):
    objects, classes, object capacity of an unknown map."""
    return (scenario.num_objects, scenario.num_classes,
            None if scenario.discovery is None else scenario.discovery.max_objects)


def _compile_fully(estimator: AbstractEstimator, scenario: Scenario, seed: int) -> float:
    """Compile the step :func:`hybridslam.run` will use for ``scenario``, at the full optimization
    level, into the driver's cache (the same arguments' structure and shapes as ``run``'s)."""
    state = estimator.init(scenario)
    slots = jax.eval_shape(estimator.view, state).history.shape[-1]
    inputs = jax.tree.map(lambda x: np.asarray(x)[:1], inputs_from_scenario(scenario, slots))
    return driver.compiled(scan, estimator.stepping(), state, inputs, jax.random.PRNGKey(seed))[1]


def run_many(estimator: AbstractEstimator, scenarios: Sequence[Scenario], *, seed: int | Sequence[int] = 0,
             on_run: Callable[[int, Run], None] | None = None, **options) -> list[Run]:
    """:func:`hybridslam.run` of ``estimator`` over every scenario, with one compiled step per group of
    scenarios of equal :func:`shape_key` (one for files of the same map).

    ``seed``: every run's PRNG seed, or one per scenario. ``on_run(i, run)`` hears each run as it
    finishes (e.g. to write its result file and drop it). ``options`` go to every
    :func:`hybridslam.run` call (``on_step``, ``keep_associations``, ...). Returns the runs in the
    order of ``scenarios``; each result's ``timing.compile_s`` is the compile its run paid (the
    first run of a group, 0 for the others).
    """
    seeds = [seed] * len(scenarios) if isinstance(seed, int) else list(seed)
    if len(seeds) != len(scenarios):
        raise ValueError(f"run_many: {len(seeds)} seeds for {len(scenarios)} scenarios")
    groups: dict[tuple, list[int]] = {}
    for i, s in enumerate(scenarios):
        groups.setdefault(shape_key(s), []).append(i)
    runs: dict[int, Run] = {}
    for members in groups.values():
        group = [scenarios[i] for i in members]
        shared = shared_shapes(estimator, group)
        compile_s = None  # compiled here, before the first run (which then finds it compiled)
        if sum(s.num_steps for s in group) > compilation.QUICK_RUN_STEPS:
            compile_s = _compile_fully(shared, group[0], seeds[members[0]])
        for n, i in enumerate(members):
            r = run(shared, scenarios[i], seed=seeds[i], **options)
            if n == 0 and compile_s is not None and r.result.timing is not None:
                r.result.timing["compile_s"] += compile_s
            runs[i] = r
            if on_run is not None:
                on_run(i, r)
    return [runs[i] for i in range(len(scenarios))]
