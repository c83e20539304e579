"""Maximum-likelihood data association (Doherty's thesis Sec. 3.3, Eq. 3.2-3.3).

Per step: the jointly most likely assignment of all the step's detections (Eq. 3.2, over the
gated joint assignments of :func:`.gaussian.associate`: joint compatibility), fixed forever; its
null entries create new objects; then Gauss-Newton with the fixed assignment (Eq. 3.3).
Settings: :class:`.gaussian.SingleGaussian` (``candidates`` G, default 3; ``gate_probability``, default 0.999).
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..models.measurement import Detections
from . import gaussian
from .base import StepInfo
from .gaussian import GaussianState, SingleGaussian


class ML(SingleGaussian):
    """Maximum-likelihood data association (see the module docstring)."""

    name: ClassVar[str] = "ml"
    title: ClassVar[str] = "maximum-likelihood association"
    reference: ClassVar[str] = "Doherty thesis Sec. 3.3"

    def step(self, state: GaussianState, odometry: Float[Array, "3"], detections: Detections,
             key: jax.Array) -> tuple[GaussianState, StepInfo]:
        """One filter step; ``key`` is unused (the estimator is deterministic)."""
        return _step(self, state, odometry, detections)


def _step(est: ML, state: GaussianState, odometry, detections: Detections) -> tuple[GaussianState, StepInfo]:
    mean, cov = gaussian.predict(state, odometry)
    assoc = gaussian.associate(state, mean, cov, detections, est.max_hypotheses)
    best = jnp.argmax(assoc.log_prob)
    opts, new, skip, unmapped = assoc.options[best], assoc.new[best], assoc.skip[best], assoc.unmapped[best]
    slots = jnp.arange(opts.shape[0])
    used = detections.mask & (opts < assoc.num_candidates)
    obj = jnp.where(used, assoc.candidates[slots, jnp.minimum(opts, assoc.num_candidates - 1)], -1)
    created = gaussian.new_slots(state, new)
    mean, cov = gaussian.create_objects(state, mean, cov, created, detections)
    mean, cov, result = gaussian.weighted_update(state, mean, cov, obj, detections.geo, used.astype(mean.dtype),
                                                 est.gn_max_steps)
    prob = (obj[:, None] == jnp.arange(state.max_objects)[None, :]) & used[:, None]
    classes = gaussian.update_classes(state, assoc, prob.astype(mean.dtype), created)
    assigned = jnp.where(used, obj, jnp.where(new, created, assoc.candidates[:, 0]))
    # The smoother's factors: the chosen object of each associated (or creating) detection.
    g = assoc.num_candidates
    factor_obj = jnp.zeros((slots.shape[0], g), jnp.int32).at[:, 0].set(jnp.maximum(assigned, 0).astype(jnp.int32))
    factor_w = jnp.full((slots.shape[0], g), -jnp.inf).at[:, 0].set(jnp.where(used | new, 0.0, -jnp.inf))
    return gaussian.commit(est, state, mean, cov, classes, assigned, used | new, detections, jnp.sum(new),
                           {"skipped": jnp.sum(skip), "unmapped": jnp.sum(unmapped), "solver_result": result,
                            "rejected": jnp.sum(assoc.clutter[best] & detections.mask),
                            "dropped": assoc.dropped}, odometry,
                           (factor_obj, factor_w, jnp.full(slots.shape, -jnp.inf)))
