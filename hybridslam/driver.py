"""One driver for every estimator: a ``lax.scan`` over steps, and a thin host loop on top of it.

:func:`scan` advances any :class:`~hybridslam.estimators.AbstractEstimator` over a stack of
steps and returns the stacked :class:`Trace` (per step: the belief's :class:`~hybridslam.estimators.Mixture`
view, the paper's metrics, the :class:`~hybridslam.estimators.StepInfo`). It is pure: the studies
``vmap`` it over tracks (:mod:`hybridslam.studies.batch`), and gradients and planning run the same
body. :func:`run` is the host loop: it compiles the scan ahead of time for one step
(:mod:`hybridslam.compilation`; compile time is measured apart from step time), calls it once per step of a scenario, and turns each step
into a result-file record, calling ``on_step`` for progress and warnings.

Step ``k`` (1-based) draws with the key ``fold_in(key, k - 1)`` on every path, so a seed gives the
same numbers alone, in a batch, under ``jax.grad`` or inside a planner.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .analysis.metrics import Metrics, metrics
# The compile machinery (hybridslam.compilation), under the names callers know from here.
from .compilation import XLA_DEFAULTS_ENV as XLA_DEFAULTS_ENV
from .compilation import _collector_paused
from .compilation import clear_compiled as clear_compiled
from .compilation import compile_lowered as compile_lowered
from .compilation import compiled, spent
from .compilation import compiler_options as compiler_options
from .compilation import use_elemental_emitters_everywhere as use_elemental_emitters_everywhere
from .compilation import xla_defaults_from_environment as xla_defaults_from_environment
from .inference.ties import rank_key_np
from .estimators.base import AbstractEstimator, Mixture, StepInfo
from .io.result import ComponentRecord, HistoryLinker, Result, StepRecord
from .models.scenario import Scenario
from .io.scenario import stack_steps
from .models.measurement import Detections


class Inputs(eqx.Module):
    """The inputs of ``T`` steps of one run, each leaf with a leading time axis ``T``."""

    odometry: Float[Array, "T 3"]
    detections: Detections  # leaves (T, Dmax, ...)
    steps: Int[Array, " T"]  # k - 1 of each step: its PRNG key is fold_in(key, k - 1)
    truth: Float[Array, "T 3"]  # the true x_k, NaN where unknown (the errors are then NaN)
    active: Bool[Array, " T"]  # False: padding (a shorter run in a batch of longer ones), the state stays


class Trace(eqx.Module):
    """What each step leaves behind (leaves stacked on a leading ``T`` axis by :func:`scan`)."""

    view: Mixture
    metrics: Metrics
    info: StepInfo


def inputs_from_scenario(scenario: Scenario, max_detections: int, first_step: int = 0,
                         num_steps: int | None = None) -> Inputs:
    """The scenario's steps as :class:`Inputs` with ``max_detections`` slots per step, padded with
    inactive steps to ``num_steps`` (default: the scenario's)."""
    stacked = stack_steps(scenario, max_detections)
    t = scenario.num_steps
    total = t if num_steps is None else num_steps
    if total < t:
        raise ValueError(f"num_steps: {total}, but the scenario has {t} steps")
    pad = lambda a: np.concatenate([a, np.zeros((total - t,) + a.shape[1:], a.dtype)])  # noqa: E731
    truth = np.full((t, 3), np.nan) if scenario.true_robot_poses is None else scenario.true_robot_poses[1:]
    put = jax.device_put  # numpy to the device without a compile (jnp.asarray compiles a small program)
    return Inputs(
        odometry=put(pad(np.asarray(stacked.odometry, float).reshape(t, 3))),
        detections=Detections(put(pad(np.asarray(stacked.geo, float))), put(pad(np.asarray(stacked.scores, float))),
                              put(pad(np.asarray(stacked.mask, bool)))),
        steps=put(np.arange(first_step, first_step + total, dtype=np.int32)),
        truth=put(pad(np.asarray(truth, float).reshape(t, 3))),
        active=put(np.arange(total) < t),
    )


def step_body(estimator: AbstractEstimator, key: PRNGKeyArray, state: Any, xs) -> tuple[Any, Trace]:
    """One step of any estimator and what it leaves behind (the body of :func:`scan`); an inactive
    (padding) step leaves the state as it was."""
    odometry, detections, k, truth, active = xs
    new, info = estimator.step(state, odometry, detections, jax.random.fold_in(key, k))
    state = jax.tree.map(lambda a, b: jnp.where(active, a, b), new, state)
    view = estimator.view(state)
    return state, Trace(view, metrics(view, truth), info)


def scan(estimator: AbstractEstimator, state: Any, inputs: Inputs, key: PRNGKeyArray) -> tuple[Any, Trace]:
    """Run ``estimator`` over every step of ``inputs`` (``lax.scan``; pure, jittable, vmappable)."""
    xs = (inputs.odometry, inputs.detections, inputs.steps, inputs.truth, inputs.active)
    return jax.lax.scan(lambda s, x: step_body(estimator, key, s, x), state, xs)


# --------------------------------------------------------------------------- #
# Records of the result file
# --------------------------------------------------------------------------- #


def record_from_arrays(
    k: int, log_weights: ArrayLike, classes: ArrayLike, history: ArrayLike, pose_mean: ArrayLike,
    pose_cov: ArrayLike, num_detections: list[int], m, *, has_truth: bool,
) -> StepRecord:
    """A :class:`StepRecord` from host arrays of one belief view (``K`` slots) and its metrics ``m``.

    Components with non-zero weight, sorted by weight (highest first, ties to ~1e-9 by slot:
    :func:`~hybridslam.inference.ties.rank_key`), weights
    renormalized to sum to one; ``history[:, j, :num_detections[j]]`` are the associations of step
    ``j + 1``.
    """
    classes, history, pose_mean, pose_cov = (np.asarray(a) for a in (classes, history, pose_mean, pose_cov))
    w = np.exp(np.asarray(log_weights))
    # Ties (weights equal to ~1e-9, whose last bits differ between CPUs) in slot order: inference.ties.
    order = [i for i in np.argsort(-rank_key_np(np.asarray(log_weights)), kind="stable") if w[i] > 0]
    total = float(np.sum(w[order]))
    components = [
        ComponentRecord(
            weight=float(w[i] / total),
            # One conversion of the whole history (a long log's records hold millions of lists).
            associations=[row[:n] for row, n in zip(history[i, :k].tolist(), num_detections)],
            classes=[int(c) for c in classes[i]],
            pose_mean=np.asarray(pose_mean[i], dtype=float),
            pose_cov=0.5 * (np.asarray(pose_cov[i], dtype=float) + np.asarray(pose_cov[i], dtype=float).T),
        )
        for i in order
    ]
    values = {"entropy": float(m.entropy), "det_cov": float(m.det_cov), "num_components": len(components)}
    if has_truth:
        values.update(err_wmax=float(m.err_wmax), err_wavg=float(m.err_wavg))
    return StepRecord(k=k, components=components, metrics=values)


def trace_record(trace: Trace, num_detections: list[int], has_truth: bool) -> StepRecord:
    """The result-file record of one step of a host-side trace (no leading axis)."""
    v = trace.view
    return record_from_arrays(int(v.k), v.log_weights, v.classes, v.history, v.mean, v.cov, num_detections,
                              trace.metrics, has_truth=has_truth)


# --------------------------------------------------------------------------- #
# The host loop
# --------------------------------------------------------------------------- #


@dataclasses.dataclass
class Run:
    """What :func:`run` returns: the result file's content, the per-step infos and the final state."""

    result: Result
    infos: list[StepInfo]  # host-side, one per step
    state: Any  # the estimator's final state

    @property
    def belief(self) -> Any:  # the hybrid belief's name for its state
        return self.state


# One small program (cached per estimator and shapes) rather than one eager op after another, each a
# compile of its own in a fresh process.
_smoothed = eqx.filter_jit(lambda estimator, state: (estimator.trajectory(state), estimator.objects(state)))


def object_poses(objects: Any, count: Any) -> np.ndarray:
    """The result file's ``objects``: the first ``count`` rows of ``objects`` (N, 3) (the slots that
    hold an object; later slots were never created), headings wrapped to [-π, π)."""
    poses = np.array(objects, dtype=float)[: int(count)]
    poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return poses


def _first(tree):
    """The first entry of every leaf, on the host (numpy: indexing a device array compiles a program)."""
    return jax.tree.map(lambda x: np.asarray(x)[0], jax.device_get(tree))


def run(
    estimator: AbstractEstimator,
    scenario: Scenario,
    *,
    seed: int = 0,
    on_step: Callable[[StepRecord, StepInfo, float], None] | None = None,
    between_steps: Callable[[int, Any], Any] | None = None,
    keep_associations: bool = True,
) -> Run:
    """Run ``estimator`` over every step of ``scenario``; returns a :class:`Run` (writes nothing).

    ``on_step(record, info, seconds)`` is called after each step (the CLI prints its table row and
    the info's warnings). ``between_steps(k, state)``, if given, returns the state the next step
    starts from, after step ``k`` (1-based, not the last) and its record: a host-side edit of the
    same shapes, e.g.
    :class:`hybridslam.estimators.loops.online.OnlineLoopClosure`. The same estimator, scenario and
    seed give the same result.

    ``keep_associations=False``: each record (the one ``on_step`` gets and the one returned) holds
    its components' histories as :class:`hybridslam.io.result.History` links to the previous
    record's (the component's ``parent`` and that step's list): the same histories in memory linear
    in the run, where plain lists take T² (gigabytes over a whole real log), and what
    :class:`hybridslam.io.result.ResultWriter` writes without matching them again.
    """
    state = estimator.init(scenario)
    history = jax.eval_shape(estimator.view, state).history  # its shape only: nothing to compute
    if scenario.num_steps > history.shape[-2]:
        raise ValueError(f"history is full: the state has room for {history.shape[-2]} steps, the scenario has "
                         f"{scenario.num_steps} (max_steps)")
    slots = history.shape[-1]
    # Sliced on the host: slicing device arrays compiles a program per leaf shape.
    inputs = jax.tree.map(np.asarray, inputs_from_scenario(scenario, slots))
    key = jax.random.PRNGKey(seed)
    num_det = [len(s.detections) for s in scenario.steps]
    has_truth = scenario.true_robot_poses is not None

    def one(k: int) -> Inputs:
        return jax.tree.map(lambda x: x[k : k + 1], inputs)

    stepper = estimator.stepping()  # what init alone reads left out: estimators that differ only there share a program
    step_fn, compile_s = (compiled(scan, stepper, state, one(0), key, steps=scenario.num_steps)
                          if scenario.num_steps else (scan, 0.0))
    records, infos, step_s = [], [], []
    link = None if keep_associations else HistoryLinker()
    main_fn, closing = step_fn, stepper.closing()
    for k in range(scenario.num_steps):
        xs = one(k)
        if k == scenario.num_steps - 1 and closing is not stepper:
            # The smoother's closing step (incremental:L: the whole graph re-solved once), a program of
            # its own, compiled fully (steps=None): the run's longest solve.
            stepper = closing
            step_fn, seconds = compiled(scan, stepper, state, xs, key, steps=None)
            compile_s += seconds
        t0 = time.perf_counter()
        state, trace = jax.block_until_ready(step_fn(stepper, state, xs, key))
        step_s.append(time.perf_counter() - t0)
        trace = _first(trace)
        # A record is k · K lists of ints (no cycles: freed by their counts). Their number alone sets
        # off the collector's full passes over JAX's heap, which over a whole log cost more than the
        # steps (1700 MRCLAM steps written as they go: 201 s end to end, 39 s of it steps).
        # Linked to the previous one (keep_associations=False), a record keeps one list per component
        # and leaves nothing for the collector to carry into the next step's timing.
        with _collector_paused():
            record = trace_record(trace, num_det, has_truth)
            if link is not None:
                record = link(record)
            infos.append(trace.info)
            if on_step is not None:
                on_step(record, trace.info, step_s[-1])
            records.append(record)
            del record
        if between_steps is not None and k + 1 < scenario.num_steps:
            state = between_steps(k + 1, state)
    spent(main_fn, sum(step_s if step_fn is main_fn else step_s[:-1]))  # the closing step ran its own program
    extra = {}
    trajectory, objects = _smoothed(estimator, state)
    if trajectory is not None:
        # x_0..x_T of this scenario: a history longer than the scenario (max_steps) holds padding after it.
        extra["trajectory"] = np.asarray(trajectory, dtype=float)[: scenario.num_steps + 1]
        extra["objects"] = object_poses(*objects)
    result = Result(estimator=f"{estimator.describe(scenario)}, seed={seed}", steps=records,
                    timing={"compile_s": compile_s, "step_s": step_s}, **extra)
    return Run(result, infos, state)


def run_estimator(scenario: Scenario, estimator: str | AbstractEstimator = "hybrid", *, seed: int = 0,
                  on_step: Callable[[StepRecord, StepInfo, float], None] | None = None, **options) -> Run:
    """:func:`run` with the estimator given by name and options (:func:`hybridslam.estimators.make_estimator`)."""
    from .estimators.registry import make_estimator

    if isinstance(estimator, str):
        estimator = make_estimator(estimator, **options)
    elif options:
        raise TypeError(f"run_estimator: options {sorted(options)} given with an estimator object; set them on it")
    return run(estimator, scenario, seed=seed, on_step=on_step)
