"""The paper's evaluation metrics (Sec. V), exactly as SCENARIO_FORMAT.md defines them."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..inference.ties import best_slot
from .marginals import association_probabilities
from .mixture import WeightedMixture


class Metrics(eqx.Module):
    entropy: Float[Array, ""]  # H(w) over association hypotheses P(β_1:k | H_k) (Eq. 8)
    det_cov: Float[Array, ""]  # det of the 2x2 position covariance of x_k, highest-weight component
    err_wmax: Float[Array, ""]  # position error of the highest-weight component (NaN without truth)
    err_wavg: Float[Array, ""]  # weight-averaged position error over components (NaN without truth)
    num_components: Int[Array, ""]


def association_entropy(belief: WeightedMixture) -> Float[Array, ""]:
    """``H = −Σ_β P(β) log P(β)``, written per component as ``−Σ_i w_i log P(β(i))``."""
    p = association_probabilities(belief)
    w = jnp.where(belief.alive, belief.weights, 0.0)
    h = -jnp.sum(jnp.where(belief.alive, w * jnp.log(jnp.where(belief.alive, p, 1.0)), 0.0))
    return jnp.maximum(h, 0.0)  # never -1e-17 from rounding (-0.0 is made 0.0 when written: io.result)


def metrics(belief: WeightedMixture, true_pose: Float[Array, "3"] | None = None) -> Metrics:
    best = best_slot(belief.log_weights)
    det_cov = jnp.linalg.det(belief.cov[best, :2, :2])
    if true_pose is None:
        err_max = err_avg = jnp.full((), jnp.nan)
    else:
        err = jnp.linalg.norm(belief.mean[:, :2] - true_pose[None, :2], axis=-1)
        w = jnp.where(belief.alive, belief.weights, 0.0)
        err_max, err_avg = err[best], jnp.sum(jnp.where(belief.alive, w * err, 0.0))
    return Metrics(association_entropy(belief), det_cov, err_max, err_avg, jnp.sum(belief.alive))
