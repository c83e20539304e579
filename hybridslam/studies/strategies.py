"""How the tracks of a batch share a compiled program: one wide ``vmap``, or one track after another.

A batch of ``B`` tracks (:class:`hybridslam.studies.batch.Batch`) runs as one compiled program
either way; what differs is how the tracks share it.

* :class:`VmapBatches` — one ``jax.vmap`` over every track of a slice. On an accelerator the tracks
  fill the device's lanes. On a CPU a ``vmap`` over tracks turns every ``lax.cond`` of the step
  into a select that runs both branches, and every ``while_loop`` (Gauss-Newton, Levenberg-Marquardt,
  the live-chunk maps of :func:`hybridslam.inference.batching.map_live`) into one that runs until
  the slowest track is done: each track pays for the hardest one.
* :class:`MapBatches` — a ``lax.map`` over chunks of ``chunk`` tracks (a ``vmap`` inside each chunk;
  ``chunk=1``: no ``vmap`` at all, every track runs the program :func:`hybridslam.run` runs), split
  over the devices of the mesh with ``jax.shard_map``. A track then pays for its own branches only.

:func:`default_strategy` picks by backend (``jax.default_backend()``): :class:`MapBatches` on the
CPU, :class:`VmapBatches` elsewhere; measured in ``docs/performance_batching.md``. Either gives
every track the numbers :func:`hybridslam.run` gives it alone (to floating-point rounding: a
vmapped program may round differently).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, ClassVar

import jax
from jax.sharding import Mesh, PartitionSpec

from ..driver import Inputs, scan
from ..estimators.base import AbstractEstimator

BATCH_AXIS = "tracks"  # the vmap axis over a whole slice, and the mesh axis the slice is sharded over
CHUNK_AXIS = "chunk"  # the vmap axis inside one chunk of MapBatches


def track_outputs(estimator: AbstractEstimator, state: Any, inputs: Inputs, key: Any) -> tuple:
    """One track's trace (:func:`hybridslam.driver.scan`) and, for smoothers, its final smoothed
    trajectory and objects with their count (``None`` for filters)."""
    final, trace = scan(estimator, state, inputs, key)
    return trace, estimator.trajectory(final), estimator.objects(final)


@dataclasses.dataclass(frozen=True)
class VmapBatches:
    """One ``jax.vmap`` over every track of a slice (the accelerators' strategy)."""

    name: ClassVar[str] = "vmap"

    def run(self, estimator: AbstractEstimator, batch: Any) -> tuple:
        """Every track's :func:`track_outputs`, stacked on a leading axis ``B``."""
        one = lambda s, i, k: track_outputs(estimator.with_batch_axis(BATCH_AXIS), s, i, k)
        return jax.vmap(one, axis_name=BATCH_AXIS)(batch.state, batch.inputs, batch.key)

    def describe(self) -> str:
        return "vmap"


@dataclasses.dataclass(frozen=True)
class MapBatches:
    """A ``lax.map`` over chunks of ``chunk`` tracks, each chunk a ``vmap`` (``chunk=1``: none), every
    device of ``mesh`` mapping over its own share of the tracks (the CPU's strategy).

    ``mesh`` is set by :func:`hybridslam.studies.batch.run_batch` (``None``: one device)."""

    chunk: int = 1
    mesh: Mesh | None = None
    name: ClassVar[str] = "map"

    def __post_init__(self):
        if not (isinstance(self.chunk, int) and not isinstance(self.chunk, bool) and self.chunk >= 1):
            raise ValueError(f"MapBatches.chunk: expected a positive int, got {self.chunk!r}")

    def run(self, estimator: AbstractEstimator, batch: Any) -> tuple:
        """Every track's :func:`track_outputs`, stacked on a leading axis ``B`` (a multiple of
        ``chunk`` times the mesh's devices)."""
        chunk = self.chunk

        def local(b):  # this device's tracks, leading axis n
            xs = (b.state, b.inputs, b.key)
            if chunk == 1:
                alone = estimator.with_batch_axis(None)
                return jax.lax.map(lambda x: track_outputs(alone, *x), xs)
            n = b.key.shape[0]
            together = estimator.with_batch_axis(CHUNK_AXIS)
            parts = jax.tree.map(lambda x: x.reshape((n // chunk, chunk) + x.shape[1:]), xs)
            vmapped = jax.vmap(lambda s, i, k: track_outputs(together, s, i, k), axis_name=CHUNK_AXIS)
            out = jax.lax.map(lambda x: vmapped(*x), parts)
            return jax.tree.map(lambda y: y.reshape((n,) + y.shape[2:]), out)

        if self.mesh is None or self.mesh.size == 1:
            return local(batch)
        spec = PartitionSpec(BATCH_AXIS)
        # check_vma off: the step's lax.conds return zeros built outside the map (unvarying across
        # devices) beside per-device values, which the checker rejects; no collective crosses devices.
        return jax.shard_map(local, mesh=self.mesh, in_specs=(spec,), out_specs=spec, check_vma=False)(batch)

    def describe(self) -> str:
        return f"map:{self.chunk}"


BatchStrategy = VmapBatches | MapBatches

# Tracks per chunk of MapBatches on a CPU (measured: docs/performance_batching.md).
CPU_CHUNK = 1


def default_strategy(backend: str | None = None) -> BatchStrategy:
    """:class:`MapBatches` (chunks of :data:`CPU_CHUNK`) on the CPU backend, :class:`VmapBatches` on
    others; ``backend`` defaults to ``jax.default_backend()``."""
    return MapBatches(CPU_CHUNK) if (backend or jax.default_backend()) == "cpu" else VmapBatches()


def parse_strategy(text: str | None) -> BatchStrategy:
    """``"auto"`` (or ``None``: :func:`default_strategy`), ``"vmap"``, ``"map"`` or ``"map:N"`` (chunks of
    ``N`` tracks); a ``ValueError`` naming ``--batching`` otherwise."""
    if text is None or text.strip() in ("", "auto"):
        return default_strategy()
    name, _, chunk = text.strip().partition(":")
    if name == "vmap" and not chunk:
        return VmapBatches()
    if name == "map":
        try:
            return MapBatches(int(chunk) if chunk else 1)
        except ValueError:
            pass
    raise ValueError(f"--batching {text!r}: expected auto, vmap, map or map:N (N tracks vmapped per chunk)")


CPU_DEVICES_ENV = "HYBRIDSLAM_CPU_DEVICES"  # how many CPU devices a study splits the host into (0: JAX's default)


def split_cpu_into_cores() -> int:
    """Give JAX one CPU device per core (``jax_num_cpu_devices``), so that a study's
    :class:`MapBatches` maps over a share of the tracks on every core at once (a sharded program's
    devices run in parallel; one CPU device runs the whole ``lax.map`` on one core).

    Only before JAX starts its backends (the CLI calls it first thing), and only where nobody chose a
    count already (``jax_num_cpu_devices``, ``--xla_force_host_platform_device_count`` in
    ``XLA_FLAGS``). ``$HYBRIDSLAM_CPU_DEVICES`` overrides the core count (``0`` or ``1``: leave JAX's
    single CPU device). Accelerators are untouched (the CPU devices are then not the default ones).
    Returns the count set, or 0 when it set none; a ``ValueError`` naming the variable for a bad value.
    """
    given = os.environ.get(CPU_DEVICES_ENV, "").strip()
    if given and not given.isdigit():
        raise ValueError(f"{CPU_DEVICES_ENV}={given!r}: expected a number of CPU devices (0 or 1: one)")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    count = int(given) if given else cores
    if (count <= 1 or jax.config.jax_num_cpu_devices != -1  # type: ignore[attr-defined]
            or "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", "")):
        return 0
    try:
        jax.config.update("jax_num_cpu_devices", count)
    except RuntimeError:  # the backends have started: too late, keep one device
        return 0
    return count
