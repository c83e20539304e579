"""Many runs at once: a batch of tracks as one compiled, sharded computation.

:func:`run_batch` takes an estimator and a :class:`Batch` (``B`` initial states stacked on a
leading axis, each carrying its own model, so tracks may differ in alpha, K or covariances, and
the ``B`` tracks' inputs) and runs every step of every track in one call: the driver's ``lax.scan``
over steps (:func:`hybridslam.driver.scan`) of every track, so a track gets the numbers
:func:`hybridslam.run` gives it alone. How the tracks share the program is a
:mod:`~hybridslam.studies.strategies` choice made by backend: one ``jax.vmap`` over the tracks on an
accelerator (:class:`~hybridslam.studies.strategies.VmapBatches`), a ``lax.map`` over them on a CPU
(:class:`~hybridslam.studies.strategies.MapBatches`), where a vmap would make every track run every
branch of every other. The batch axis is sharded over a ``jax.sharding.Mesh`` of all devices (one
CPU or one per core, several GPUs, several hosts after ``jax.distributed.initialize()``), padded to
a multiple of the device count. With several processes, every process runs the same study and
gets the whole trace back (``process_allgather``); only process 0 writes files
(:mod:`hybridslam.studies.study`).

Under a vmap the axis is named (:data:`BATCH_AXIS`) and the estimator is told so
(``estimator.with_batch_axis``): the hybrid belief then still skips chunks of component slots that
are empty in every track (:func:`hybridslam.inference.batching.map_live`), so a batch pays for its
largest live set, not for the capacity.

What comes back is the driver's :class:`~hybridslam.driver.Trace` with leading axes ``(B, T)``.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import time
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Float, Key, UInt32

from ..driver import Inputs, Trace, inputs_from_scenario, trace_record
from ..estimators.base import AbstractEstimator
from ..io.result import StepRecord
from ..models.scenario import Scenario
from ..models.classifier import AlphaK
from .exported import compiled_exported
from .strategies import BATCH_AXIS, BatchStrategy, MapBatches, VmapBatches, default_strategy

MAX_TRACKS_PER_DEVICE = 64


class Batch(eqx.Module):
    """Everything the tracks of a batch read, with a leading batch axis ``B`` on every leaf."""

    state: Any  # the initial states
    inputs: Inputs  # leaves (B, T, ...)
    key: Key[Array, " B"] | UInt32[Array, "B 2"]  # each track's PRNG key (step k draws with fold_in(key, k - 1))

    @property
    def size(self) -> int:
        return self.key.shape[0]


def _run_batch(estimator: AbstractEstimator, batch: Batch,
               strategy: BatchStrategy | None = None) -> tuple[Trace, Float[Array, "B T1 3"] | None, Any]:
    """Every track's trace and, for smoothers, its final smoothed trajectory and objects with their
    count (:func:`~hybridslam.studies.strategies.track_outputs`), stacked on a leading axis, run as
    ``strategy`` says (default :class:`~hybridslam.studies.strategies.VmapBatches`)."""
    return (VmapBatches() if strategy is None else strategy).run(estimator, batch)


def device_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh over ``devices`` (default: every device of every process) named :data:`BATCH_AXIS`."""
    return Mesh(np.asarray(jax.devices() if devices is None else list(devices)), (BATCH_AXIS,))


@dataclasses.dataclass
class BatchRun:
    """What :func:`run_batch` returns: the trace on the host, and where the time went."""

    trace: Trace  # numpy leaves, leading axes (B, T)
    compile_s: float  # 0 when an executable of these shapes was already compiled
    run_s: float  # wall time of the batched run (all tracks, all steps)
    num_devices: int
    plan: BatchPlan | None = None  # how the batch was split to fit in memory
    trajectories: np.ndarray | None = None  # (B, T+1, 3): each track's final smoothed x_0..x_T (smoothers)
    objects: tuple[np.ndarray, np.ndarray] | None = None  # (B, N, 3) smoothed objects, (B,) how many exist
    strategy: str = "vmap"  # how the tracks shared the program (strategies.BatchStrategy.describe())


def shared_shapes(estimator: AbstractEstimator, scenarios: Sequence[Scenario]) -> AbstractEstimator:
    """``estimator`` with one number of detection slots (the largest step of any of ``scenarios``)
    and one history length (the longest run) for all of them, where it does not fix them itself: files
    of different lengths and detection counts then share one compiled program."""
    if not scenarios:
        raise ValueError("shared_shapes: no scenarios")
    slots = getattr(estimator, "max_detections", None) or max(1, max(s.max_detections for s in scenarios))
    steps = getattr(estimator, "max_steps", None) or max(1, max(s.num_steps for s in scenarios))
    if hasattr(estimator, "max_detections"):
        estimator = dataclasses.replace(estimator, max_detections=slots, max_steps=steps)  # type: ignore[call-arg]
    return estimator


def shared_classifier(estimator: AbstractEstimator, scenarios: Sequence[Scenario]) -> AbstractEstimator:
    """``estimator`` with the classifier ``"mirror"`` or ``"independent"`` (by name, or the scenarios'
    own when it names none) as one :class:`~hybridslam.models.classifier.AlphaK` of the scenarios'
    alpha and K, where they all share them: the choice of model is then a traced leaf, and batches
    of the two models run one compiled program (a study's cells of both: one compile, not two).
    Any other classifier, or scenarios of several alphas or K, leave ``estimator`` as it is."""
    name = getattr(estimator, "classifier", "")
    if not (name is None or isinstance(name, str)):
        return estimator
    specs = {(s.classifier.model if name is None else name, s.classifier.alpha, s.classifier.K)
             for s in scenarios}
    if len(specs) != 1:
        return estimator
    ((model, alpha, K),) = specs
    if model not in ("mirror", "independent") or alpha is None or K is None:
        return estimator
    shared = AlphaK(alpha, K, 1.0 if model == "mirror" else 0.0)
    return dataclasses.replace(estimator, classifier=shared)  # type: ignore[call-arg]


def batched(estimator: AbstractEstimator, scenarios: Sequence[Scenario]) -> AbstractEstimator:
    """``estimator`` as it runs a batch of ``scenarios``: :func:`shared_shapes`, :func:`shared_classifier`,
    the vmap axis named."""
    return shared_classifier(shared_shapes(estimator, scenarios), scenarios).with_batch_axis(BATCH_AXIS)


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.asarray(np.stack(xs)), *trees)


def batch_inputs(estimator: AbstractEstimator, scenarios: Sequence[Scenario], seeds: Sequence[int]) -> Batch:
    """Stack ``scenarios`` (equal objects and classes) into a :class:`Batch` for ``estimator`` (as
    returned by :func:`batched`); track ``b`` draws with PRNG seed ``seeds[b]``. Shorter runs are
    padded with inactive steps (the state stays; their records are dropped)."""
    if not scenarios:
        raise ValueError("batch_inputs: no scenarios")
    if len(seeds) != len(scenarios):
        raise ValueError(f"batch_inputs: {len(seeds)} seeds for {len(scenarios)} scenarios")
    shapes = {(s.num_objects, s.num_classes, None if s.discovery is None else s.discovery.max_objects)
              for s in scenarios}
    if len(shapes) > 1:
        raise ValueError(f"batch_inputs: scenarios differ in (objects, classes, object capacity): {sorted(shapes)}")
    states = [estimator.init(s) for s in scenarios]
    history = estimator.view(states[0]).history
    slots, steps = history.shape[-1], history.shape[-2]
    return Batch(
        state=_stack(states),
        inputs=_stack([inputs_from_scenario(s, slots, num_steps=steps) for s in scenarios]),
        key=jnp.asarray(np.stack([np.asarray(jax.random.PRNGKey(seed)) for seed in seeds])),
    )


def memory_budget(mesh: Mesh) -> int:
    """Bytes one batch may use per device: half of the host's available memory on CPU (several
    devices of one host share it), 80% of a GPU's own memory. With several processes, process 0's
    budget for all of them: every process must slice a batch the same way (the slices meet in
    collectives)."""
    budget = _local_budget(mesh)
    if jax.process_count() > 1:
        _barrier(f"hybridslam-budget-{_next_barrier()}")
        budget = int(multihost_utils.broadcast_one_to_all(np.int64(budget)))
    return budget


def _local_budget(mesh: Mesh) -> int:
    mine = [d for d in mesh.devices.flat if d.process_index == jax.process_index()]
    device = (mine or jax.local_devices())[0]  # memory_stats() exists for this process's devices only
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    if device.platform != "cpu" and stats and "bytes_limit" in stats:
        return int(0.8 * stats["bytes_limit"])
    try:
        available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # not a POSIX host: assume 8 GiB
        available = 8 << 30
    local = max(1, sum(d.process_index == jax.process_index() for d in mesh.devices.flat))
    return int(0.5 * available / local)


def batch_bytes(executable) -> int:
    """Bytes one device needs to run a compiled batch (XLA's memory analysis of the executable)."""
    stats = executable.compiled.memory_analysis()
    return int(stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes
               - stats.alias_size_in_bytes)


@dataclasses.dataclass
class BatchPlan:
    """How a batch runs: ``slices`` slices of ``width`` tracks, each needing ``bytes`` per device."""

    slices: int
    width: int
    bytes: int
    budget: int

    def describe(self, size: int) -> str:
        gib = 1 << 30
        return (f"{size} tracks in {self.slices} batch(es) of {self.width} ({self.bytes / gib:.2f} GiB per device "
                f"each, budget {self.budget / gib:.1f} GiB)")


def check_batchable(estimator: AbstractEstimator) -> None:
    """A ``ValueError`` for an estimator whose run closes with a program of its own
    (:meth:`~hybridslam.estimators.AbstractEstimator.closing`: ``incremental:L``): the tracks of a
    batch share one scan, and a padded track has no last step of its own."""
    if estimator.closing() is not estimator:
        raise ValueError(f"smoother={getattr(estimator, 'smoother', None)}: a batched study runs every track in one "
                         "scan, with no last step of its own to re-solve the whole graph; use full or lag:L here "
                         "(hybridslam run and hs.run_many close incremental:L runs)")


def run_batch(estimator: AbstractEstimator, batch: Batch, mesh: Mesh | None = None,
              on_plan=None, strategy: BatchStrategy | None = None) -> BatchRun:
    """Run every track of ``batch`` to its last step, sharded over ``mesh`` (default: all devices).

    ``strategy``: how the tracks share the program (:mod:`hybridslam.studies.strategies`; default
    :func:`~hybridslam.studies.strategies.default_strategy`, chosen by backend).

    The batch runs as equal slices of at most :data:`MAX_TRACKS_PER_DEVICE` tracks per device, and of
    as many as fit in memory: XLA's memory analysis of the compiled slice (:func:`batch_bytes`) is
    compared with :func:`memory_budget`, and a slice that does not fit is halved (and recompiled)
    until it does. ``on_plan(plan)`` hears how the batch was split. The batch is padded with copies of
    track 0 (dropped from the result). Each track's numbers depend only on its own inputs (its PRNG
    key included), not on the batch it runs in, the slicing or the number of devices.
    """
    check_batchable(estimator)
    estimator = estimator.with_batch_axis(BATCH_AXIS).stepping()  # the states carry what init read
    mesh = device_mesh() if mesh is None else mesh
    strategy = default_strategy() if strategy is None else strategy
    if isinstance(strategy, MapBatches):
        strategy = dataclasses.replace(strategy, mesh=mesh)
    chunk = strategy.chunk if isinstance(strategy, MapBatches) else 1
    size = batch.size
    budget = memory_budget(mesh)
    # Batches wider than MAX_TRACKS_PER_DEVICE run as equal slices in sequence (one executable):
    # XLA:CPU was seen to hang on a single 256-wide batch of the step.
    per_device = -(-size // mesh.size)
    width_per_device = min(per_device, MAX_TRACKS_PER_DEVICE)
    compile_s = 0.0
    while True:
        slices = -(-per_device // width_per_device)
        width_per_device = -(-per_device // slices)  # equal slices
        if width_per_device > chunk:  # whole chunks of MapBatches (a slice narrower than one: a chunk of its own)
            width_per_device = -(-width_per_device // chunk) * chunk
        elif isinstance(strategy, MapBatches) and chunk > width_per_device:
            strategy = dataclasses.replace(strategy, chunk=width_per_device)
        width = width_per_device * mesh.size
        pad = slices * width - size
        # Padded and sliced on the host: on device arrays every leaf's concatenate and slice is an eager
        # op that compiles a small program of its own (a batched hybrid state has dozens of leaves;
        # 8 hard files' warm sweep, under load: 30 s of its 144 s), and none is kept on disk.
        padded = jax.tree.map(lambda x, pad=pad: np.concatenate([x, np.repeat(x[:1], pad, axis=0)]),
                              jax.device_get(batch))
        first = jax.device_put(jax.tree.map(lambda x, width=width: x[:width], padded),
                               NamedSharding(mesh, PartitionSpec(BATCH_AXIS)))
        executable, seconds = compiled_exported(_run_batch, estimator, first, strategy)
        compile_s += seconds
        need = batch_bytes(executable)
        if need <= budget or width_per_device == 1:
            break
        width_per_device = max(1, width_per_device // 2)  # does not fit: halve the slice, recompile
    plan = BatchPlan(slices, width, need, budget)
    if on_plan is not None:
        on_plan(plan)
    run_s = 0.0
    traces = []
    for i in range(slices):
        part = jax.tree.map(lambda x, i=i: x[i * width : (i + 1) * width], padded)
        sharded = jax.device_put(part, NamedSharding(mesh, PartitionSpec(BATCH_AXIS)))
        t0 = time.perf_counter()
        out = jax.block_until_ready(executable(estimator, sharded, strategy))
        run_s += time.perf_counter() - t0
        if jax.process_count() > 1:  # several hosts: every process gets the whole batch
            _barrier(f"hybridslam-batch-{_next_barrier()}")
            out = multihost_utils.process_allgather(out, tiled=True)
        traces.append(jax.device_get(out))
    trace, trajectories, objects = jax.tree.map(lambda *xs: np.concatenate(xs)[:size], *traces)
    return BatchRun(trace, compile_s, run_s, mesh.size, plan, trajectories, objects, strategy.describe())


_BARRIERS = itertools.count()  # barrier names must be unique; every process counts the same calls


def _next_barrier() -> int:
    return next(_BARRIERS)


def _barrier(name: str, timeout_s: float = 3600.0) -> None:
    """Wait until every process reaches ``name``, on the coordination service (no gloo timeout).

    gloo gives up on a collective (and on setting up its context) after 30 s; processes that compile
    or run at different speeds (a loaded node, a cold compilation cache on one of them) reach
    ``process_allgather`` further apart than that. The coordination service's barrier waits as long
    as it is told, so the collective that follows starts with everyone there.
    """
    from jax._src import distributed  # the public API has no barrier without a collective

    client = distributed.global_state.client
    if client is not None:
        client.wait_at_barrier(name, timeout_in_ms=int(timeout_s * 1000))


def track(trace: Trace, b: int) -> Trace:
    """Track ``b`` of a host-side batched trace (leading axis ``T`` left)."""
    return jax.tree.map(lambda x: x[b], trace)


def step_records(trace: Trace, b: int, scenario: Scenario) -> list[StepRecord]:
    """The result-file records (one per step) of track ``b`` of a host-side ``trace``."""
    num_det = [len(s.detections) for s in scenario.steps]
    has_truth = scenario.true_robot_poses is not None
    mine = track(trace, b)
    return [trace_record(jax.tree.map(lambda x, j=j: x[j], mine), num_det, has_truth)
            for j in range(scenario.num_steps)]
