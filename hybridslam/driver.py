"""One driver for every estimator: a ``lax.scan`` over steps, and a thin host loop on top of it.

:func:`scan` advances any :class:`~hybridslam.estimators.AbstractEstimator` over a stack of
steps and returns the stacked :class:`Trace` (per step: the belief's :class:`~hybridslam.estimators.Mixture`
view, the paper's metrics, the :class:`~hybridslam.estimators.StepInfo`). It is pure: the studies
``vmap`` it over tracks (:mod:`hybridslam.studies.batch`), and gradients and planning run the same
body. :func:`run` is the host loop: it compiles the scan ahead of time for one step (compile
time is measured apart from step time), calls it once per step of a scenario, and turns each step
into a result-file record, calling ``on_step`` for progress and warnings.

Step ``k`` (1-based) draws with the key ``fold_in(key, k - 1)`` on every path, so a seed gives the
same numbers alone, in a batch, under ``jax.grad`` or inside a planner.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import os
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .analysis.metrics import Metrics, metrics
from .inference.ties import rank_key_np
from .estimators.base import AbstractEstimator, Mixture, StepInfo
from .io.result import ComponentRecord, HistoryLinker, Result, StepRecord
from .io.scenario import Scenario, stack_steps
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
# Compilation
# --------------------------------------------------------------------------- #

_COMPILED: dict = {}  # one executable per (estimator settings, state structure, shapes): equal runs share it

# XLA's CPU fusion emitters (MLIR-based, the default in jaxlib 0.10) compile this project's programs
# 25-35% slower than XLA's elemental emitters, and the programs run no faster (2026-11-26, 2-core
# CPU, jaxlib 0.10.2: `hybridslam run` on a paper-setup file 12.5-13.6 -> 8.6-9.4 s, the hallway hybrid
# belief's program 11.2-11.7 -> 7.8-8.7 s, `multimodal`'s 15.9-16.7 -> 11.3-12.0 s, every step as
# fast or faster; a 16-track vmapped sweep's batched work ~7% slower, its end to end 4 s faster).
# LLVM's optimization level 1 instead of XLA's default 3 compiles 15-25% faster again and the steps
# run as fast (2026-11-26, alternating runs of scripts/bench_goals.py: paper4 hybrid 9.5, 10.6 -> 8.0,
# 9.1 s, hallway multimodal 14.6, 15.8 -> 12.0, 11.9 s, MRCLAM hybrid 14.1, 14.2 -> 15.6, 10.4 s; step
# times within the machine's noise; level 0 halves XLA's time but doubles the step time).
# A jaxlib that does not know an option compiles with its defaults.
CPU_COMPILER_OPTIONS: dict[str, str | bool | int] = {"xla_cpu_use_fusion_emitters": False,
                                                     "xla_backend_optimization_level": 1}
XLA_DEFAULTS_ENV = "HYBRIDSLAM_XLA_DEFAULTS"  # "1": compile with XLA's own default options


def xla_defaults_from_environment() -> bool:
    """Whether ``$HYBRIDSLAM_XLA_DEFAULTS`` is ``1``; a ``ValueError`` naming it unless unset, 0 or 1."""
    value = os.environ.get(XLA_DEFAULTS_ENV, "").strip()
    if value not in ("", "0", "1"):
        raise ValueError(f"{XLA_DEFAULTS_ENV}={value!r}: expected 0 or 1")
    return value == "1"


def compiler_options(quick: bool = False) -> dict[str, str | bool | int]:
    """The XLA options :func:`compiled` passes: :data:`CPU_COMPILER_OPTIONS` on the CPU backend,
    none on others or when ``$HYBRIDSLAM_XLA_DEFAULTS`` is ``1``. ``quick``: LLVM's optimization
    level 0 (:data:`QUICK_RUN_STEPS`)."""
    if xla_defaults_from_environment() or jax.default_backend() != "cpu":
        return {}
    return dict(CPU_COMPILER_OPTIONS) | ({"xla_backend_optimization_level": 0} if quick else {})


def _as_xla_flags(options: dict[str, str | bool | int]) -> str:
    """``{"xla_a": False, "xla_b": 2}`` as ``XLA_FLAGS`` text: ``--xla_a=false --xla_b=2``."""
    return " ".join(f"--{name}={str(value).lower() if isinstance(value, bool) else value}"
                    for name, value in options.items())


def use_elemental_emitters_everywhere() -> bool:
    """Put :data:`CPU_COMPILER_OPTIONS` into ``XLA_FLAGS`` as well: then every compile of this process
    (not only :func:`compiled`'s) and of the processes it starts uses them. Call it before JAX starts
    its backend (XLA reads the flags then); the test suite and ``scripts/make_golden.py`` do. Only if
    this jaxlib knows the options (XLA aborts on an unknown flag: a probe in a subprocess, about a
    second) and ``$HYBRIDSLAM_XLA_DEFAULTS`` is not ``1``. Returns whether the flags are set."""
    flags, wanted = os.environ.get("XLA_FLAGS", ""), _as_xla_flags(CPU_COMPILER_OPTIONS)
    if wanted in flags:
        return True
    if xla_defaults_from_environment():
        return False
    env = dict(os.environ, XLA_FLAGS=f"{flags} {wanted}".strip())
    probe = subprocess.run([sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"],
                           env=env, capture_output=True, timeout=300, check=False)
    if probe.returncode == 0:
        os.environ["XLA_FLAGS"] = env["XLA_FLAGS"]
    return probe.returncode == 0


def compile_lowered(lowered: Any, quick: bool = False) -> Any:
    """``lowered.compile()`` (a ``jax`` or ``equinox`` lowered program) with :func:`compiler_options`;
    if this jaxlib rejects an option, with XLA's defaults."""
    options = compiler_options(quick)
    if options:
        try:
            return lowered.compile(compiler_options=options)
        except TypeError:  # a jax whose compile() takes no options
            pass
        except RuntimeError as error:  # XLA's runtime error: only an unknown option falls back
            if "No such compile option" not in str(error):
                raise
    return lowered.compile()


@contextlib.contextmanager
def _collector_paused():
    """Python's cyclic garbage collector off for the block (then on again, if it was).

    Tracing a step allocates a few hundred thousand short-lived objects, and the collector's passes
    over the whole heap (JAX's modules included) cost a fifth of the tracing: the paper program's
    trace and lowering 1.75, 1.95 → 1.42, 1.56 s (2026-11-26; alternating
    processes, ``gc.freeze`` in between bought half of that). The garbage the block leaves is
    reference cycles of the tracer, collected at the collector's next pass after it.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


# A short run compiles with LLVM's optimization level 0: XLA's part of the compile takes about half
# as long and the steps twice as long, which a run of a few steps does not feel (a 10-step
# paper-setup file, `hybridslam run`, 2026-11-27, alternating: compile 4.63, 4.89 -> 3.61, 3.71 s;
# steps 4.1, 3.8 -> 7.2, 7.7 ms; results equal to 1e-14). A program that short runs reuse is compiled
# again at the default level once the step time they spent at level 0 passes TIER_UP times its
# compile (rent or buy: at most about twice the better choice made in advance).
QUICK_RUN_STEPS = 20
TIER_UP = 2.5
_QUICK: dict[int, list[float]] = {}  # id of a level-0 executable in _COMPILED -> [compile s, step s run]


def compiled(fn: Callable, *args, steps: int | None = None) -> tuple[Callable, float]:
    """``eqx.filter_jit(fn)`` compiled ahead of time for these arguments' structure and shapes, and
    the seconds spent compiling (0 when an equal program was compiled before in this process).

    ``steps``: how many times the caller will run it (:func:`run`: the scenario's steps). At most
    :data:`QUICK_RUN_STEPS` compiles it quickly (LLVM level 0, slower code), until the time spent
    running that code (:func:`spent`) says that compiling it fully pays.
    """
    quick = steps is not None and steps <= QUICK_RUN_STEPS
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    key: tuple | None = (fn, treedef, tuple((x.shape, x.dtype, getattr(x, "sharding", None)) for x in leaves),
                         static)
    try:
        hash(key)
    except TypeError:  # an unhashable static part: compile every time, correctly
        key = None
    if key is not None and key in _COMPILED:
        tally = _QUICK.get(id(_COMPILED[key]))
        if tally is None or (quick and tally[1] < TIER_UP * tally[0]):
            return _COMPILED[key], 0.0
        del _QUICK[id(_COMPILED[key])]
        quick = False  # level 0 has cost more than a full compile would: compile it fully
    t0 = time.perf_counter()
    with _collector_paused():
        executable = compile_lowered(eqx.filter_jit(fn).lower(*args), quick)  # type: ignore[attr-defined]
    seconds = time.perf_counter() - t0
    if key is not None:
        _COMPILED[key] = executable
        if quick:
            _QUICK[id(executable)] = [seconds, 0.0]
    return executable, seconds


def spent(executable: Callable, seconds: float) -> None:
    """Count ``seconds`` of running ``executable`` (from :func:`compiled`) toward compiling it fully."""
    tally = _QUICK.get(id(executable))
    if tally is not None:
        tally[1] += seconds


def clear_compiled() -> None:
    """Forget every executable :func:`compiled` kept, and JAX's own caches.

    Each executable holds its machine code in memory maps; a process that compiles many programs
    (a benchmark over every estimator, smoother and workload: about 40) reaches the kernel's map
    limit (``vm.max_map_count``, 65530 by default) and XLA then fails with "LLVM compilation error:
    Cannot allocate memory". Call this between programs that will not run again.
    """
    _COMPILED.clear()
    _QUICK.clear()
    jax.clear_caches()


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
    :class:`hybridslam.estimators.hybrid.loops.OnlineLoopClosure`. The same estimator, scenario and
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

    step_fn, compile_s = (compiled(scan, estimator, state, one(0), key, steps=scenario.num_steps)
                          if scenario.num_steps else (scan, 0.0))
    records, infos, step_s = [], [], []
    link = None if keep_associations else HistoryLinker()
    for k in range(scenario.num_steps):
        xs = one(k)
        t0 = time.perf_counter()
        state, trace = jax.block_until_ready(step_fn(estimator, state, xs, key))
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
    spent(step_fn, sum(step_s))
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
