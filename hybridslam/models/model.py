"""The generative model: motion noise, sensor (geometry + classifier), class prior, pruning rule.

A :class:`Model` holds only traced arrays, so a sweep over ``alpha``, ``K`` or a covariance reuses
one compiled step; ``jax.vmap`` over a batch of models runs such a sweep in one call.
"""

from __future__ import annotations

from typing import TypeVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .scenario import Scenario
from .classifier import ClassifierModel
from .registry import make_classifier
from .measurement import SensorModel


class NewObjects(eqx.Module):
    """The null / new-landmark hypothesis of an unknown map (thesis Sec. 3.2.1; SCENARIO_FORMAT.md)."""

    log_density: Float[Array, ""]  # log density of a detection's geometry under "new object"
    orientation_var: Float[Array, ""]  # variance of a new object's unobserved orientation


class Model(eqx.Module):
    """Everything the inference step needs besides the belief and the data.

    ``discovery`` is ``None`` for a known map; otherwise detections may create objects up to the
    object capacity ``N`` (``class_prior`` then has a row per slot, uniform for uncreated ones).
    ``clutter`` is ``None`` without a clutter hypothesis; otherwise a detection may be spurious, of
    log density ``clutter.log_density`` over ``[range, bearing]`` (set by the estimators that use it).
    """

    motion_cov: Float[Array, "3 3"]  # Σ_w (Sec. III)
    sensor: SensorModel  # Σ_v, classifier h_c / Σ_c (Eq. 2), field of view
    class_prior: Float[Array, "N M"]  # P(c_n), Eq. 3
    prune_ratio: Float[Array, ""]  # drop components below w_max / prune_ratio (Sec. V: 150)
    discovery: NewObjects | None = None
    clutter: NewObjects | None = None

    @property
    def num_classes(self) -> int:
        return self.sensor.classifier.num_classes


_M = TypeVar("_M", "Model", SensorModel)


def with_smooth_visibility(model: _M, range_temperature, bearing_temperature=None) -> _M:
    """``model`` (a :class:`Model` or a :class:`SensorModel`) with the smooth object observation model.

    ``range_temperature`` ``τ_r`` is in metres, ``bearing_temperature`` ``τ_b`` in radians; it defaults
    to ``τ_r / max_range`` (the same margin, as arc length, at full range). See
    :func:`hybridslam.geometry.log_smooth_visibility`. A temperature of 0 is the hard 0/1 footprint
    again (as a limit: the values, not the gradients); ``visibility_temperature=None`` is the default
    hard model.
    """
    sensor = model.sensor if isinstance(model, Model) else model
    tau_r = jnp.asarray(range_temperature, dtype=float)
    tau_b = tau_r / sensor.max_range if bearing_temperature is None else jnp.asarray(bearing_temperature, dtype=float)
    if tau_r.shape != () or tau_b.shape != ():
        raise ValueError(f"visibility temperatures: expected two scalars, got shapes {tau_r.shape} and {tau_b.shape}")
    sensor = eqx.tree_at(
        lambda s: s.visibility_temperature, sensor, jnp.stack([tau_r, tau_b]), is_leaf=lambda v: v is None
    )
    return eqx.tree_at(lambda m: m.sensor, model, sensor) if isinstance(model, Model) else sensor


def model_from_scenario(
    scenario: Scenario, classifier: str | ClassifierModel | None = None, prune_ratio: float = 150.0,
    visibility_temperature: float | tuple[float, float] | None = None,
) -> Model:
    """Read the model from a scenario; ``classifier`` overrides ``scenario.classifier.model``.

    A name (``"mirror"``, ``"independent"``, ``"none"``) takes ``alpha`` and ``K`` from the file;
    ``"learned"`` loads the model file named by ``classifier.path``; ``"confusion"`` takes
    ``classifier.matrix`` (thesis Eq. 2.14-2.15). ``visibility_temperature``
    ``τ_r`` or ``(τ_r, τ_b)`` (metres, radians) selects the smooth object observation model
    (:func:`with_smooth_visibility`); ``None`` keeps the paper's 0/1 footprint.
    """
    spec = scenario.classifier
    if classifier is None or isinstance(classifier, str):
        name = spec.model if classifier is None else classifier
        if name in ("mirror", "independent") and (spec.alpha is None or spec.K is None):
            raise ValueError(
                f"classifier {name!r} needs alpha and K, but the scenario's model is {spec.model!r}"
            )
        if name == "learned" and spec.path is None:
            raise ValueError(f"classifier 'learned' needs a model file, but the scenario's model is {spec.model!r}")
        if name == "confusion" and spec.matrix is None:
            raise ValueError(f"classifier 'confusion' needs a matrix, but the scenario's model is {spec.model!r}")
        classifier = make_classifier(name, scenario.num_classes, spec.alpha, spec.K, path=spec.path,
                                     matrix=spec.matrix)
    if classifier.num_classes != scenario.num_classes:
        raise ValueError(
            f"classifier has {classifier.num_classes} classes, scenario has {scenario.num_classes}"
        )
    if not prune_ratio >= 1.0:
        raise ValueError(f"prune_ratio must be >= 1, got {prune_ratio}")
    f = lambda a: jnp.asarray(a, dtype=float)  # noqa: E731
    sensor = SensorModel(f(scenario.geometric_cov), classifier, f(scenario.max_range), f(scenario.fov))
    model = Model(f(scenario.motion_cov), sensor, f(scenario.class_prior), f(prune_ratio))
    if scenario.discovery is not None:
        model = _with_discovery(model, scenario)
    if visibility_temperature is None:
        return model
    tau = jnp.atleast_1d(jnp.asarray(visibility_temperature, dtype=float))
    if tau.shape not in ((1,), (2,)):
        raise ValueError(f"visibility_temperature: expected tau_r or (tau_r, tau_b), got {visibility_temperature!r}")
    return with_smooth_visibility(model, *tau)


def _with_discovery(model: Model, scenario: Scenario) -> Model:
    """Object slots up to ``discovery.max_objects``; a new object's class prior is uniform (no information)."""
    d = scenario.discovery
    if d is None:
        raise ValueError("discovery: the scenario has no discovery section")
    m = scenario.num_classes
    extra = jnp.full((d.max_objects - scenario.num_objects, m), 1.0 / m)
    prior = jnp.concatenate([model.class_prior, extra])
    new = NewObjects(jnp.asarray(d.new_object_log_density, dtype=float), jnp.asarray(d.new_object_orientation_var, dtype=float))
    return Model(model.motion_cov, model.sensor, prior, model.prune_ratio, new)
