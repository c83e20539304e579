"""Many runs at once: a batch of tracks as one compiled, vmapped, sharded computation.

:func:`run_batch` takes ``B`` beliefs (leaves stacked on a leading axis, each carrying its own
model, so tracks may differ in alpha, K or covariances) and their ``B`` scenarios' inputs, and
runs every step of every track in one call: ``jax.vmap`` over tracks of a ``lax.scan`` over steps
of :func:`hybridslam.step._step` (Algorithm 1). The batch axis is sharded over a
``jax.sharding.Mesh`` of all devices (one CPU, several GPUs, several hosts after
``jax.distributed.initialize()``), padded to a multiple of the device count. With several
processes, every process runs the same study and gets the whole trace back
(``process_allgather``); only process 0 writes files (:mod:`hybridslam.study`).

The vmap axis is named (:data:`BATCH_AXIS`) and the beliefs carry ``Config.batch_axis``, so the
step still skips chunks of component slots that are empty in every track
(:func:`hybridslam.batching.map_live`): the batch pays for the largest live set, not the capacity.

What comes back is a :class:`Trace`: per track and step the metrics of Sec. V, the diagnostics
the CLI warns about, and the pose marginals of every component (enough to write result files).
The grid of a study (alphas × models × tracks), its records and its resumption live in
:mod:`hybridslam.study`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from .belief import Belief, Config, Detections, init_belief, priors_from_scenario
from .classifier import ClassifierModel
from .metrics import Metrics, metrics
from .model import model_from_scenario
from .result import StepRecord
from .run import record_from_arrays
from .scenario import Scenario, stack_steps
from .step import _step

BATCH_AXIS = "tracks"
MAX_TRACKS_PER_DEVICE = 64


class Inputs(eqx.Module):
    """Everything one track's run reads, with a leading batch axis ``B`` on every leaf."""

    belief: Belief  # the initial beliefs (Config.batch_axis == BATCH_AXIS)
    odometry: Float[Array, "B T 3"]
    detections: Detections  # leaves (B, T, Dmax, ...)
    key: PRNGKeyArray  # (B, 2): step k draws with fold_in(key, k - 1), as run_scenario does
    truth: Float[Array, "B T 3"]  # true x_k (NaN where unknown: the errors are NaN)


class Trace(eqx.Module):
    """Per track and step (leading axes ``B, T``): metrics, diagnostics and the pose marginals."""

    metrics: Metrics  # each field (B, T)
    log_weights: Float[Array, "B T K"]
    classes: Int[Array, "B T K N"]
    history: Int[Array, "B T K Tmax Dmax"]
    pose_mean: Float[Array, "B T K 3"]
    pose_cov: Float[Array, "B T K 3 3"]
    dropped_capacity: Int[Array, "B T"]  # hypotheses above the pruning threshold lost to capacity
    visibility_ignored: Bool[Array, "B T"]
    gn_failures: Int[Array, "B T"]  # kept components whose Gauss-Newton update did not converge
    min_ess: Float[Array, "B T"]  # smallest normalized ESS of a kept weight
    is_failures: Int[Array, "B T"]  # laplace-is mode searches that did not converge


def _run_track(inputs: Inputs) -> Trace:
    """One track (no batch axis): ``lax.scan`` of the step over its ``T`` steps."""

    def body(belief: Belief, xs):
        odometry, detections, k, truth = xs
        belief, info = _step(belief, odometry, detections, jax.random.fold_in(inputs.key, k))
        alive = belief.alive
        out = Trace(
            metrics=metrics(belief, truth),
            log_weights=belief.log_weights,
            classes=belief.classes,
            history=belief.history,
            pose_mean=belief.mean[:, :3],
            pose_cov=belief.cov[:, :3, :3],
            dropped_capacity=info.prune.dropped_capacity,
            visibility_ignored=info.visibility_ignored,
            gn_failures=jnp.sum(alive & (info.solver_result != optx.RESULTS.successful)),
            # The ESS is that of the with-visibility estimate, which a visibility-ignored step does not use.
            min_ess=jnp.where(info.visibility_ignored, jnp.nan, jnp.min(jnp.where(alive, info.ess, jnp.inf))),
            is_failures=info.is_solver_failures,
        )
        return belief, out

    steps = jnp.arange(inputs.odometry.shape[0])
    _, trace = jax.lax.scan(body, inputs.belief, (inputs.odometry, inputs.detections, steps, inputs.truth))
    return trace


_run_batch = jax.jit(jax.vmap(_run_track, axis_name=BATCH_AXIS))
_COMPILED: dict = {}


def _compiled(inputs: Inputs):
    """The ahead-of-time compiled batch run for these shapes and shardings, and its compile seconds."""
    leaves, treedef = jax.tree_util.tree_flatten(inputs)
    key = (treedef, tuple((x.shape, x.dtype, x.sharding) for x in leaves))
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    t0 = time.perf_counter()
    _COMPILED[key] = _run_batch.lower(inputs).compile()
    return _COMPILED[key], time.perf_counter() - t0


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


def run_batch(inputs: Inputs, mesh: Mesh | None = None) -> BatchRun:
    """Run every track of ``inputs`` to its last step, sharded over ``mesh`` (default: all devices).

    The batch is padded to a multiple of the device count with copies of track 0 (the copies
    are dropped from the result); more than :data:`MAX_TRACKS_PER_DEVICE` tracks per device run
    as equal slices one after the other. Each track's numbers depend only on its own inputs (its PRNG key
    included), not on the batch it runs in or on the number of devices.
    """
    if inputs.belief.config.batch_axis != BATCH_AXIS:
        raise ValueError(
            f"the beliefs' Config.batch_axis must be {BATCH_AXIS!r} (use hybridslam.sweep.batch_inputs)"
        )
    mesh = device_mesh() if mesh is None else mesh
    size = inputs.odometry.shape[0]
    # Batches wider than MAX_TRACKS_PER_DEVICE run as equal slices in sequence (one executable):
    # XLA:CPU was seen to hang on a single 256-wide batch of the step.
    slices = -(-size // (MAX_TRACKS_PER_DEVICE * mesh.size))
    width = -(-size // (slices * mesh.size)) * mesh.size
    pad = slices * width - size
    padded = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)]), inputs)
    compile_s = run_s = 0.0
    traces = []
    for i in range(slices):
        part = jax.tree.map(lambda x: x[i * width : (i + 1) * width], padded)
        sharded = jax.device_put(part, NamedSharding(mesh, PartitionSpec(BATCH_AXIS)))
        compiled, seconds = _compiled(sharded)
        compile_s += seconds
        t0 = time.perf_counter()
        trace = jax.block_until_ready(compiled(sharded))
        run_s += time.perf_counter() - t0
        if jax.process_count() > 1:  # several hosts: every process gets the whole batch
            trace = multihost_utils.process_allgather(trace, tiled=True)
        traces.append(jax.device_get(trace))
    trace = jax.tree.map(lambda *xs: np.concatenate(xs)[:size], *traces)
    return BatchRun(trace, compile_s, run_s, mesh.size)


_init_batch = jax.jit(jax.vmap(init_belief, in_axes=(0, 0, None)), static_argnums=2)


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.asarray(np.stack(xs)), *trees)


def batch_inputs(
    scenarios: Sequence[Scenario],
    config: Config,
    *,
    classifier: str | ClassifierModel | None = None,
    prune_ratio: float = 150.0,
    seeds: Sequence[int],
) -> Inputs:
    """Stack ``scenarios`` (equal objects, classes and steps) into batched :class:`Inputs`.

    Track ``b`` runs ``scenarios[b]`` with the model the file names (``classifier`` overrides the
    model name, alpha and K stay the file's), the weights' PRNG seed ``seeds[b]`` and ``config``
    (whose ``max_detections`` must cover every step of every scenario).
    """
    if not scenarios:
        raise ValueError("batch_inputs: no scenarios")
    if len(seeds) != len(scenarios):
        raise ValueError(f"batch_inputs: {len(seeds)} seeds for {len(scenarios)} scenarios")
    shapes = {(s.num_objects, s.num_classes, s.num_steps) for s in scenarios}
    if len(shapes) > 1:
        raise ValueError(f"batch_inputs: scenarios differ in (objects, classes, steps): {sorted(shapes)}")
    config = dataclasses.replace(config, batch_axis=BATCH_AXIS)
    models = _stack([model_from_scenario(s, classifier, prune_ratio) for s in scenarios])
    priors = _stack([priors_from_scenario(s) for s in scenarios])
    steps = [stack_steps(s, config.max_detections) for s in scenarios]
    truth = [np.full((s.num_steps, 3), np.nan) if s.true_robot_poses is None else s.true_robot_poses[1:]
             for s in scenarios]
    return Inputs(
        belief=_init_batch(priors, models, config),
        odometry=jnp.asarray(np.stack([st.odometry for st in steps]), dtype=float),
        detections=Detections(
            jnp.asarray(np.stack([st.geo for st in steps]), dtype=float),
            jnp.asarray(np.stack([st.scores for st in steps]), dtype=float),
            jnp.asarray(np.stack([st.mask for st in steps])),
        ),
        key=jnp.stack([jax.random.PRNGKey(seed) for seed in seeds]),
        truth=jnp.asarray(np.stack(truth), dtype=float),
    )


def step_records(trace: Trace, track: int, scenario: Scenario) -> list[StepRecord]:
    """The result-file records (one per step) of track ``track`` of a host-side ``trace``."""
    num_det = [len(s.detections) for s in scenario.steps]
    has_truth = scenario.true_robot_poses is not None
    records = []
    for j in range(trace.log_weights.shape[1]):
        m = jax.tree.map(lambda x: x[track, j], trace.metrics)
        records.append(record_from_arrays(
            j + 1, trace.log_weights[track, j], trace.classes[track, j], trace.history[track, j],
            trace.pose_mean[track, j], trace.pose_cov[track, j], num_det, m, has_truth=has_truth,
        ))
    return records
