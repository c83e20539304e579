"""Maximum-likelihood data association (Doherty's thesis Sec. 3.3, Eq. 3.2-3.3).

Per step: the jointly most likely assignment of all the step's detections (Eq. 3.2, over the
gated joint assignments of :func:`.gaussian.associate`: joint compatibility), fixed forever; its
null entries create new objects; then Gauss-Newton with the fixed assignment (Eq. 3.3).
Options (``Settings.extra``): ``candidates`` (G, default 3), ``gate_probability`` (default 0.999).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..belief import Detections
from . import gaussian
from .gaussian import GaussianState, StepInfo
from .base import Settings

NAME = "ml"


def init(scenario, settings: Settings) -> GaussianState:
    return gaussian.init_state(scenario, settings)


@jax.jit
def step(state: GaussianState, odometry: Float[Array, "3"], detections: Detections,
         key: jax.Array) -> tuple[GaussianState, StepInfo]:
    """One filter step; ``key`` is unused (the estimator is deterministic)."""
    del key
    mean, cov = gaussian.predict(state, odometry)
    assoc = gaussian.associate(state, mean, cov, detections)
    best = jnp.argmax(assoc.log_prob)
    opts, new, skip = assoc.options[best], assoc.new[best], assoc.skip[best]
    slots = jnp.arange(opts.shape[0])
    used = detections.mask & (opts < assoc.num_candidates)
    obj = jnp.where(used, assoc.candidates[slots, jnp.minimum(opts, assoc.num_candidates - 1)], -1)
    created = gaussian.new_slots(state, new)
    mean, cov = gaussian.create_objects(state, mean, cov, created, detections)
    mean, cov, result = gaussian.weighted_update(state, mean, cov, obj, detections.geo, used.astype(mean.dtype))
    prob = (obj[:, None] == jnp.arange(state.max_objects)[None, :]) & used[:, None]
    classes = gaussian.update_classes(state, assoc, prob.astype(mean.dtype), created)
    assigned = jnp.where(used, obj, jnp.where(new, created, assoc.candidates[:, 0]))
    return gaussian.commit(state, mean, cov, classes, assigned, used | new, detections, jnp.sum(new),
                           {"skipped": jnp.sum(skip), "solver_result": result})


view = gaussian.view
warnings = gaussian.warnings


def describe(settings: Settings) -> str:
    return gaussian.describe("maximum-likelihood association", "Doherty thesis Sec. 3.3", settings)
