"""Merging equivalent mixture components: one Gaussian held by several association histories.

A component of the hybrid belief is a hypothesis ``(C, β_1:k)`` with a Gaussian over
``[x_k, objects]`` (Tchuiev et al. Eq. 4-8). Two histories can differ only in which of two
readings of one cluster went to which of its landmarks (MRCLAM's barcoded tubes stand 0.18 m
apart, and the sensor reads each several times a step): their Gaussians then agree to a fraction
of a standard deviation, and every later step treats them alike. A capacity of ``K`` can fill with
``K`` such copies of one hypothesis, and the next ambiguous detection's alternative finds no slot.

:func:`merge_equivalent` merges each component into the likeliest *equivalent* one: same class
realization and objects (``same``), and mean within squared Mahalanobis distance ``threshold`` of
the other's under the other's covariance,

    d²(i → j) = (μ_i − μ_j)ᵀ Σ_j⁻¹ (μ_i − μ_j) ≤ threshold,

for ``j`` ranked above ``i`` (:func:`~.ties.rank_key`, ties by slot: no last bit decides). The
survivor's weight becomes the sum of its group's (Eq. 6's marginal mixture keeps its mass), its own
Gaussian and history stay, and the merged slots are freed. Between equal Gaussians this changes
no marginal over ``[x_k, objects]`` (Eq. 6-8); what is lost is the merged histories themselves
(the posterior over which reading was which landmark), which later steps would not have told
apart. (This is the hypothesis merging of multiple-hypothesis trackers; the papers' Algorithm 1
prunes, it does not merge.)

Cost: one Cholesky factor per component and ``K²`` triangular solves, ``O(K D³ + K² D²)`` for
``D = 3 + 3N``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp
from jaxtyping import Array, Bool, Float, Int

from .ties import rank_key
from .update import wrap_angles


def mahalanobis_to(chol: Float[Array, "D D"], centre: Float[Array, " D"], means: Float[Array, "C D"]) -> Float[Array, " C"]:
    """``(μ_c − centre)ᵀ Σ⁻¹ (μ_c − centre)`` for each row of ``means``, ``Σ = chol cholᵀ`` (angles of
    the differences wrapped to (-π, π]: a heading is on the circle)."""
    diff = jax.vmap(wrap_angles)(means - centre[None, :])
    z = jax.scipy.linalg.solve_triangular(chol, diff.T, lower=True)
    return jnp.sum(z**2, axis=0)


def squared_distances(mean: Float[Array, "K D"], cov: Float[Array, "K D D"]) -> Float[Array, "K K"]:
    """``d2[i, j] = (μ_i − μ_j)ᵀ Σ_j⁻¹ (μ_i − μ_j)``: component ``i``'s mean under ``j``'s Gaussian
    (dimensionless; ``inf`` where ``Σ_j`` has no Cholesky factor)."""
    d2 = jax.vmap(mahalanobis_to, (0, 0, None))(jnp.linalg.cholesky(cov), mean, mean).T  # row j -> column j
    return jnp.where(jnp.isfinite(d2), d2, jnp.inf)


def merge_equivalent(
    log_weights: Float[Array, " K"], mean: Float[Array, "K D"], cov: Float[Array, "K D D"],
    same: Bool[Array, "K K"], threshold: Float[Array, ""] | float,
) -> tuple[Float[Array, " K"], Int[Array, " K"], Int[Array, ""]]:
    """Merge every component into the likeliest equivalent one (module docstring).

    ``log_weights`` (K,), ``-inf`` for empty slots; ``mean`` (K, D) and ``cov`` (K, D, D) over
    ``[x_k, objects]``; ``same[i, j]``: ``i`` and ``j`` hold the same class realization and objects
    (the caller's notion; the diagonal is ignored); ``threshold``: the largest squared Mahalanobis
    distance that counts as equivalent (0 merges only identical means).

    Returns the merged log weights (the survivors' the log-sum of their group's, the merged ``-inf``;
    the total is unchanged), each slot's survivor ``(K,)`` (its own index if it survives, also for
    empty slots) and the number of components merged.
    """
    k = log_weights.shape[0]
    alive = log_weights > -jnp.inf
    key = rank_key(log_weights)
    slots = jnp.arange(k)
    # j is above i: a higher rank, or the same rank and a lower slot (a strict total order).
    above = (key[None, :] > key[:, None]) | ((key[None, :] == key[:, None]) & (slots[None, :] < slots[:, None]))
    close = squared_distances(mean, cov) <= threshold
    joins = same & close & above & alive[:, None] & alive[None, :]  # joins[i, j]: i may merge into j
    # The likeliest equivalent above each component (the first such slot in rank order), else itself.
    order_key = jnp.where(joins, key[None, :], -jnp.inf)
    target = jnp.where(jnp.any(joins, axis=1), jnp.argmax(order_key, axis=1), slots)
    # Follow the chain up to a survivor: each hop climbs the total order, so log2(K) doublings end it.
    for _ in range(max(1, math.ceil(math.log2(max(k, 2))))):
        target = target[target]
    merged_log_w = jax.vmap(lambda j: logsumexp(jnp.where(target == j, log_weights, -jnp.inf)))(slots)
    survives = target == slots
    out = jnp.where(survives & alive, merged_log_w, -jnp.inf)
    return out, target, jnp.sum(alive & ~survives, dtype=jnp.int32)
