"""Run the hybrid-belief estimator over a scenario and record a ``hybridslam-result/1``.

The step is compiled ahead of time (so compile time is measured apart from step time), then
called once per scenario step; after each step the belief is copied to the host and turned into a
:class:`~hybridslam.result.StepRecord`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .belief import Belief, Config, Detections, init_belief, priors_from_scenario
from .classifier import ClassifierModel
from .metrics import metrics
from .model import model_from_scenario
from .result import ComponentRecord, Result, StepRecord
from .scenario import Scenario, stack_steps
from .step import StepInfo, step

_metrics = jax.jit(metrics)
_COMPILED: dict = {}  # one executable per (step function, state structure, shapes): equal runs share it


def compiled_step(belief: Belief, *args, step_fn: Callable = step) -> tuple[Callable, float]:
    """The ahead-of-time compiled ``step_fn`` (a ``jax.jit`` function) for these argument shapes, and
    the seconds spent compiling (0 if cached)."""
    leaves, treedef = jax.tree_util.tree_flatten((belief, args))
    key = (step_fn, treedef, tuple((jnp.shape(x), jnp.result_type(x)) for x in leaves))
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    t0 = time.perf_counter()
    _COMPILED[key] = step_fn.lower(belief, *args).compile()
    return _COMPILED[key], time.perf_counter() - t0


def drive(
    step_fn: Callable, state, scenario: Scenario, max_detections: int, seed: int,
    record: Callable[[object, list[int], np.ndarray | None], StepRecord],
    on_step: Callable[[StepRecord, object, float], None] | None = None,
):
    """Run a jitted ``step_fn(state, odometry, detections, key)`` over every step of ``scenario``.

    Compiles once ahead of time (cached across runs of equal shapes), times each step after
    compilation, and turns each state into a result record with ``record(state, num_detections,
    true_pose)``. The per-step keys are ``fold_in(PRNGKey(seed), k)``. Returns the final state, the
    records, the step infos and the timing dict of the result file.
    """
    stacked = stack_steps(scenario, max_detections)
    num_det = [int(n) for n in stacked.mask.sum(axis=1)]
    key = jax.random.PRNGKey(seed)
    truth = scenario.true_robot_poses

    def inputs(k: int):
        det = Detections(jnp.asarray(stacked.geo[k]), jnp.asarray(stacked.scores[k]), jnp.asarray(stacked.mask[k]))
        return jnp.asarray(stacked.odometry[k]), det, jax.random.fold_in(key, k)

    compiled, compile_s = (compiled_step(state, *inputs(0), step_fn=step_fn) if scenario.num_steps
                           else (None, 0.0))
    records, infos, step_s = [], [], []
    for k in range(scenario.num_steps):
        args = inputs(k)
        t0 = time.perf_counter()
        state, info = jax.block_until_ready(compiled(state, *args))
        step_s.append(time.perf_counter() - t0)
        records.append(record(state, num_det, None if truth is None else truth[k + 1]))
        infos.append(info)
        if on_step is not None:
            on_step(records[-1], info, step_s[-1])
    return state, records, infos, {"compile_s": compile_s, "step_s": step_s}


@dataclasses.dataclass
class Run:
    """What :func:`run_scenario` returns: the result file's content plus per-step diagnostics."""

    result: Result
    infos: list[StepInfo]
    belief: Belief  # the final belief


def config_for(scenario: Scenario, **settings) -> Config:
    """A :class:`Config` sized for ``scenario`` (history length, detection slots) plus ``settings``.

    ``num_samples`` names the draws of the chosen weight method: ``n_s`` per parent for
    ``sampled``, draws per candidate child for ``laplace-is``; ``None`` keeps the method's default.
    """
    samples = settings.pop("num_samples", None)
    if samples is not None:
        settings["is_samples" if settings.get("weights", Config.weights) == "laplace-is" else "num_samples"] = samples
    settings.setdefault("max_detections", max(scenario.max_detections, 1))
    settings.setdefault("max_steps", max(scenario.num_steps, 1))
    return Config(**settings)


def samples_of(config: Config) -> int:
    """The draws the configured weight method uses (0 for the deterministic ``linearized``)."""
    return {"sampled": config.num_samples, "laplace-is": config.is_samples}.get(config.weights, 0)


def describe(config: Config, classifier: str, prune_ratio: float, seed: int) -> str:
    from . import __version__

    return (
        f"hybridslam {__version__} hybrid belief (Tchuiev et al. 2019, Alg. 1); classifier={classifier}, "
        f"weights={config.weights}, samples={samples_of(config)}, capacity={config.capacity}, "
        f"prune_ratio={prune_ratio:g}, seed={seed}"
        + ("" if config.gate_candidates is None else f", gate_candidates={config.gate_candidates}")
    )


def step_record(belief: Belief, num_detections: list[int], true_pose: np.ndarray | None) -> StepRecord:
    """The host-side record of one belief (SCENARIO_FORMAT.md, "Result file")."""
    m = jax.device_get(_metrics(belief, None if true_pose is None else jnp.asarray(true_pose)))
    b = jax.device_get(belief)
    return record_from_arrays(
        int(b.k), b.log_weights, b.classes, b.history, b.mean[:, :3], b.cov[:, :3, :3],
        num_detections, m, has_truth=true_pose is not None,
    )


def record_from_arrays(
    k: int, log_weights: np.ndarray, classes: np.ndarray, history: np.ndarray, pose_mean: np.ndarray,
    pose_cov: np.ndarray, num_detections: list[int], m, *, has_truth: bool,
) -> StepRecord:
    """A :class:`StepRecord` from host arrays of one belief (``K`` slots) and its :class:`Metrics` ``m``.

    Components with non-zero weight, sorted by weight (highest first, ties by slot), weights
    renormalized to sum to one; ``history[:, j, :num_detections[j]]`` are the associations of step
    ``j + 1``.
    """
    w = np.exp(np.asarray(log_weights))
    order = [i for i in np.argsort(-w, kind="stable") if w[i] > 0]
    total = float(np.sum(w[order]))
    components = [
        ComponentRecord(
            weight=float(w[i] / total),
            associations=[[int(o) for o in history[i, j, : num_detections[j]]] for j in range(k)],
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


def run_scenario(
    scenario: Scenario,
    *,
    classifier: str | ClassifierModel | None = None,
    capacity: int = 64,
    num_samples: int | None = None,
    weights: str = "laplace-is",
    prune_ratio: float = 150.0,
    seed: int = 0,
    max_detections: int | None = None,
    on_step: Callable[[StepRecord, StepInfo, float], None] | None = None,
    **settings,
) -> Run:
    """Run Algorithm 1 over every step of ``scenario``.

    ``on_step(record, info, seconds)`` is called after each step (the CLI prints its table row).
    The same arguments give the same result (the per-step keys are ``fold_in(PRNGKey(seed), k)``).
    ``max_detections`` fixes the detection slots (default: the scenario's maximum); runs with equal
    shapes reuse one compiled step. Further ``settings`` are :class:`Config` fields
    (``is_samples``, ``is_candidates``, ``gn_max_steps``).
    """
    if max_detections is not None:
        settings["max_detections"] = max_detections
    config = config_for(scenario, capacity=capacity, num_samples=num_samples, weights=weights, **settings)
    model = model_from_scenario(scenario, classifier, prune_ratio)
    belief = init_belief(priors_from_scenario(scenario), model, config)
    belief, records, infos, timing = drive(step, belief, scenario, config.max_detections, seed, step_record, on_step)
    name = classifier if isinstance(classifier, str) else scenario.classifier.model if classifier is None else type(classifier).__name__
    result = Result(estimator=describe(config, name, prune_ratio, seed), steps=records, timing=timing)
    return Run(result, infos, belief)
