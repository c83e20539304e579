"""Marginals of the hybrid belief (Eq. 6-8).

All functions take one :class:`~hybridslam.analysis.mixture.WeightedMixture` (a hybrid belief or any
estimator's view) and return fixed-shape arrays (jit- and vmap-able); empty slots carry probability 0.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .mixture import ClassedMixture, WeightedMixture


def association_probabilities(belief: WeightedMixture) -> Float[Array, " K"]:
    """``P(β_1:k | H_k)`` (Eq. 8) of each component's association history, summed over ``C``.

    Entry ``i`` is the total weight of all components sharing component ``i``'s ``β_1:k``.
    """
    flat = belief.history.reshape(belief.history.shape[0], -1)
    same = jnp.all(flat[:, None, :] == flat[None, :, :], axis=-1)
    w = jnp.where(belief.alive, belief.weights, 0.0)
    return jnp.where(belief.alive, same.astype(w.dtype) @ w, 0.0)


def class_probabilities(belief: ClassedMixture) -> Float[Array, "N M"]:
    """``P(c_n = c | H_k)`` for every object (Eq. 7, marginalized per object).

    A component that leaves object ``n`` open (Sec. IV-D) contributes the class prior of ``n``.
    """
    m = belief.model.num_classes
    w = jnp.where(belief.alive, belief.weights, 0.0)
    onehot = belief.classes[..., None] == jnp.arange(m)[None, None, :]  # (K, N, M); all False when open
    open_ = (belief.classes < 0)[..., None]
    per_component = jnp.where(open_, belief.model.class_prior[None], onehot.astype(w.dtype))
    return jnp.einsum("k,knm->nm", w, per_component)


def pose_mixture(belief: WeightedMixture) -> tuple[Float[Array, " K"], Float[Array, "K 3"], Float[Array, "K 3 3"]]:
    """The mixture ``P(x_k | H_k)`` of Eq. 6: weights, means and covariances of the robot pose."""
    w = jnp.where(belief.alive, belief.weights, 0.0)
    return w, belief.mean[:, :3], belief.cov[:, :3, :3]
