"""The contract every association strategy keeps, and one runner for all of them.

An estimator is a module of :mod:`hybridslam.estimators` that defines

* ``NAME`` — the name ``hybridslam run --estimator NAME`` selects;
* ``init(scenario, settings) -> state`` — host-side: the state before step 1, an ``eqx.Module``
  pytree of fixed shapes (``settings`` is a :class:`Settings`);
* ``step(state, odometry, detections, key) -> (state, info)`` — pure and ``jax.jit``-compiled:
  odometry ``Float[Array, "3"]`` (``u_k``), :class:`~hybridslam.belief.Detections` padded to
  ``settings.max_detections`` slots, a PRNG key (``fold_in(PRNGKey(seed), k)``);
  ``info`` an ``eqx.Module`` of diagnostics;
* ``view(state) -> Mixture`` — the belief as a weighted set of components, which is all the
  result file (SCENARIO_FORMAT.md, "Result file") and the paper's metrics need;
* ``describe(settings) -> str`` — the result file's ``estimator`` text;
* optionally ``warnings(info) -> list[str]`` — one line per thing a user must hear about
  (capacity overflow, solver failure), printed by the CLI after each step.

:func:`run_estimator` runs any of them over a scenario and writes nothing: it returns a
:class:`~hybridslam.run.Run` whose ``result`` is a ``hybridslam-result/1``.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from types import ModuleType
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..metrics import metrics
from ..result import Result, StepRecord
from ..scenario import Scenario

# name -> module (relative to this package). "hybrid" is the Tchuiev et al. belief of hybridslam.run.
ESTIMATORS: dict[str, str] = {
    "hybrid": "hybrid",
    "ml": "ml",
    "gpda": "gpda",
    "max-mixture": "maxmix",
    "multimodal": "multimodal",
}


class Mixture(eqx.Module):
    """A belief as ``K`` weighted Gaussian components over the current robot pose.

    A single-Gaussian estimator (``ml``, ``gpda``, ``max-mixture``) is a mixture with one live slot.
    Field names match :class:`~hybridslam.belief.Belief`, so :func:`hybridslam.metrics.metrics`
    and :func:`hybridslam.marginals.association_probabilities` take either.
    """

    log_weights: Float[Array, " K"]  # -inf marks an empty slot; need not be normalized
    mean: Float[Array, "K 3"]  # robot pose x_k = [x, y, theta]
    cov: Float[Array, "K 3 3"]
    classes: Int[Array, "K N"]  # class estimate or realization per object, -1 = none yet
    history: Int[Array, "K T Dmax"]  # object index of each detection of steps 1..T, -1 = empty slot
    k: Int[Array, ""]  # steps taken

    @property
    def alive(self) -> Bool[Array, " K"]:
        return self.log_weights > -jnp.inf

    @property
    def weights(self) -> Float[Array, " K"]:
        return jnp.exp(self.log_weights)


@dataclasses.dataclass(frozen=True)
class Settings:
    """What every estimator is configured by; each estimator reads the fields it uses.

    ``capacity`` is the number of components (mixture / particle slots) for the multi-hypothesis
    estimators; the single-Gaussian ones ignore it. ``extra`` holds estimator-specific options
    (documented in each module).
    """

    max_detections: int
    max_steps: int
    capacity: int = 64
    classifier: str | None = None  # override of scenario.classifier.model
    num_samples: int | None = None  # Monte Carlo draws, where the estimator draws any
    gn_max_steps: int = 20
    extra: tuple[tuple[str, Any], ...] = ()

    def option(self, name: str, default: Any) -> Any:
        return dict(self.extra).get(name, default)


def get_estimator(name: str) -> ModuleType:
    """The module of estimator ``name``; a clear error for an unknown or unavailable one."""
    if name not in ESTIMATORS:
        raise ValueError(f"estimator: unknown {name!r} (known: {', '.join(ESTIMATORS)})")
    return importlib.import_module(f".{ESTIMATORS[name]}", __package__)


_metrics = jax.jit(metrics)


def mixture_record(mix: Mixture, num_detections: list[int], true_pose: np.ndarray | None) -> StepRecord:
    """The host-side record of one belief view (SCENARIO_FORMAT.md, "Result file")."""
    from ..run import record_from_arrays

    m = jax.device_get(_metrics(mix, None if true_pose is None else jnp.asarray(true_pose)))
    b = jax.device_get(mix)
    return record_from_arrays(int(b.k), b.log_weights, b.classes, b.history, b.mean, b.cov,
                              num_detections, m, has_truth=true_pose is not None)


def run_estimator(
    scenario: Scenario,
    estimator: str = "hybrid",
    *,
    seed: int = 0,
    on_step: Callable[[StepRecord, Any, float], None] | None = None,
    **settings,
):
    """Run estimator ``estimator`` over every step of ``scenario``; returns a :class:`~hybridslam.run.Run`.

    ``settings`` are :class:`Settings` fields (for ``"hybrid"``: the arguments of
    :func:`hybridslam.run.run_scenario`). Unknown fields go to ``Settings.extra``.
    """
    from ..run import Run, drive, run_scenario

    module = get_estimator(estimator)
    if estimator == "hybrid":
        return run_scenario(scenario, seed=seed, on_step=on_step, **settings)
    fields = {f.name for f in dataclasses.fields(Settings)} - {"extra"}
    known = {k: v for k, v in settings.items() if k in fields and v is not None}
    extra = tuple(sorted((k, v) for k, v in settings.items() if k not in fields))
    known.setdefault("max_detections", max(scenario.max_detections, 1))
    known.setdefault("max_steps", max(scenario.num_steps, 1))
    config = Settings(**known, extra=extra)
    state = module.init(scenario, config)

    def record(state, num_detections, true_pose):
        return mixture_record(module.view(state), num_detections, true_pose)

    state, records, infos, timing = drive(module.step, state, scenario, config.max_detections, seed, record, on_step)
    result = Result(estimator=module.describe(config), steps=records, timing=timing)
    return Run(result, infos, state)


def step_warnings(estimator: str, info: Any) -> list[str]:
    """The estimator's warning lines for one step's ``info`` (none if it defines no ``warnings``)."""
    module = get_estimator(estimator)
    return list(module.warnings(info)) if hasattr(module, "warnings") else []
