"""The generative model: motion noise, sensor (geometry + classifier), class prior, pruning rule.

A :class:`Model` holds only traced arrays, so a sweep over ``alpha``, ``K`` or a covariance reuses
one compiled step; ``jax.vmap`` over a batch of models runs such a sweep in one call.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .classifier import ClassifierModel, make_classifier
from .measurement import SensorModel
from .scenario import Scenario


class Model(eqx.Module):
    """Everything the inference step needs besides the belief and the data."""

    motion_cov: Float[Array, "3 3"]  # Σ_w (Sec. III)
    sensor: SensorModel  # Σ_v, classifier h_c / Σ_c (Eq. 2), field of view
    class_prior: Float[Array, "N M"]  # P(c_n), Eq. 3
    prune_ratio: Float[Array, ""]  # drop components below w_max / prune_ratio (Sec. V: 150)

    @property
    def num_classes(self) -> int:
        return self.sensor.classifier.num_classes


def model_from_scenario(
    scenario: Scenario, classifier: str | ClassifierModel | None = None, prune_ratio: float = 150.0
) -> Model:
    """Read the model from a scenario; ``classifier`` overrides ``scenario.classifier.model``.

    A name (``"mirror"``, ``"independent"``, ``"none"``) takes ``alpha`` and ``K`` from the file;
    ``"learned"`` loads the model file named by ``classifier.path``.
    """
    spec = scenario.classifier
    if scenario.discovery is not None:
        raise ValueError(
            "discovery: unknown maps (new objects) are not supported by the hybrid estimator yet; "
            "only scenarios whose objects are all mapped can be run"
        )
    if classifier is None or isinstance(classifier, str):
        name = spec.model if classifier is None else classifier
        if name in ("mirror", "independent") and (spec.alpha is None or spec.K is None):
            raise ValueError(
                f"classifier {name!r} needs alpha and K, but the scenario's model is {spec.model!r}"
            )
        if name == "learned" and spec.path is None:
            raise ValueError(f"classifier 'learned' needs a model file, but the scenario's model is {spec.model!r}")
        classifier = make_classifier(name, scenario.num_classes, spec.alpha, spec.K, path=spec.path)
    if classifier.num_classes != scenario.num_classes:
        raise ValueError(
            f"classifier has {classifier.num_classes} classes, scenario has {scenario.num_classes}"
        )
    if not prune_ratio >= 1.0:
        raise ValueError(f"prune_ratio must be >= 1, got {prune_ratio}")
    f = lambda a: jnp.asarray(a, dtype=float)  # noqa: E731
    sensor = SensorModel(f(scenario.geometric_cov), classifier, f(scenario.max_range), f(scenario.fov))
    return Model(f(scenario.motion_cov), sensor, f(scenario.class_prior), f(prune_ratio))
