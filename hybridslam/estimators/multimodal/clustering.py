"""The multimodal mixture's reduction: greedy moment-matching merging (no mode is dropped)."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ...inference.laplace import logsumexp_or_minus_inf
from ...inference.merging import mahalanobis_to
from ...inference.ties import best_slot
from ...inference.update import wrap_angles


# --------------------------------------------------------------------------- #
# Reduction: greedy moment-matching merging (no mode is dropped)
# --------------------------------------------------------------------------- #


def cluster(
    log_w: Float[Array, " C"],
    mean: Float[Array, "C D"],
    cov: Float[Array, "C D D"],
    num_created: Int[Array, " C"],
    threshold: Float[Array, ""],
    capacity: int,
    centre_ok: Bool[Array, " C"] | None = None,
) -> tuple[Int[Array, " K"], Float[Array, " K"], Float[Array, "K C"]]:
    """:func:`clustered` with every child's covariance given."""
    centres, log_weights, wn, _ = clustered(log_w, mean, lambda c: cov[c], cov[:, :3, :3], num_created, threshold,
                                            capacity, centre_ok)
    return centres, log_weights, wn


def clustered(
    log_w: Float[Array, " C"],
    mean: Float[Array, "C D"],
    cov_of: Callable[[Int[Array, ""]], Float[Array, "D D"]],
    pose_cov: Float[Array, "C 3 3"],
    num_created: Int[Array, " C"],
    threshold: Float[Array, ""],
    capacity: int,
    centre_ok: Bool[Array, " C"] | None = None,
) -> tuple[Int[Array, " K"], Float[Array, " K"], Float[Array, "K C"], Float[Array, "K D D"]]:
    """Group ``C`` weighted Gaussians into ``K`` clusters without dropping mass (the merge's first half).

    ``K`` rounds: the heaviest unclaimed child among ``centre_ok`` (default: every live child)
    becomes a centre and claims every unclaimed child with the same number of created objects within
    squared Mahalanobis distance ``threshold`` (centre's metric). Leftovers join the nearest centre:
    moment-matched when their object slots are comparable (same number created), by weight only
    otherwise. Returns the centres (the used ones first), merged log weights (``-inf`` for unused
    slots), the normalized moment weights ``(K, C)`` (zero for a member joined by weight only) and
    the centres' covariances. ``cov_of(c)``: child ``c``'s covariance (only the ``K`` centres' are
    asked for: the children's need not exist as a ``C × D × D`` array); ``pose_cov``: every child's
    pose block.
    """
    live = log_w > -jnp.inf
    centre_ok = live if centre_ok is None else centre_ok & live
    pose_chol = jax.vmap(jnp.linalg.cholesky)(pose_cov)

    def round_(owner, r):
        free = (owner < 0) & live
        c = best_slot(jnp.where(free & centre_ok, log_w, -jnp.inf))  # of tied ones, the first
        # Only the centres' factors are needed: K of them, not C.
        cov_c = cov_of(c)
        d2 = mahalanobis_to(jnp.linalg.cholesky(cov_c), mean[c], mean)
        close = free & (num_created == num_created[c]) & (d2 <= threshold)
        close = close | (jnp.arange(owner.shape[0]) == c)
        return jnp.where(close & jnp.any(free & centre_ok), r, owner), (c, jnp.any(free & centre_ok), d2, cov_c)

    owner, (centres, used, full_d2, centre_cov) = jax.lax.scan(round_, jnp.full(log_w.shape, -1),
                                                               jnp.arange(capacity))
    pose_d2 = jax.vmap(mahalanobis_to, (0, 0, None))(pose_chol[centres], mean[centres, :3], mean[:, :3])
    comparable = used[:, None] & (num_created[centres][:, None] == num_created[None, :])
    has_full = jnp.any(comparable, axis=0)
    nearest = jnp.where(has_full, jnp.argmin(jnp.where(comparable, full_d2, jnp.inf), axis=0),
                        jnp.argmin(jnp.where(used[:, None], pose_d2, jnp.inf), axis=0))
    left = (owner < 0) & live
    owner = jnp.where(left, nearest, owner)
    member = (owner[None, :] == jnp.arange(capacity)[:, None]) & live[None, :]  # (K, C)
    log_weights = logsumexp_or_minus_inf(jnp.where(member, log_w[None, :], -jnp.inf), axis=1)  # empty: -inf
    moment = member & ~(left & ~has_full)[None, :]
    centre_hot = jnp.arange(log_w.shape[0])[None, :] == centres[:, None]
    # A row with no member takes its centre alone; its softmax over nothing (NaN) is never formed, as
    # a NaN masked by the where would make every reverse-mode gradient NaN (the double where).
    has_member = jnp.any(moment, axis=1, keepdims=True)
    wn = jax.nn.softmax(jnp.where(moment, log_w[None, :], jnp.where(has_member, -jnp.inf, 0.0)), axis=1)
    wn = jnp.where(has_member, wn, centre_hot.astype(wn.dtype))
    return centres, log_weights, wn, centre_cov


def spread(
    wn: Float[Array, "K C"], anchor: Float[Array, "K D"], mean: Float[Array, "C D"],
) -> tuple[Float[Array, "K D"], Float[Array, "K D D"]]:
    """The members' weighted mean offset from each cluster's ``anchor`` and their scatter about it.

    The moment-matched cluster is ``anchor + shift`` with covariance ``Σ_c wn_c P_c + scatter``
    (angles wrapped: the offsets are taken on the circle).
    """
    delta = jax.vmap(jax.vmap(wrap_angles))(mean[None, :, :] - anchor[:, None, :])  # (K, C, D)
    shift = jnp.einsum("kc,kcd->kd", wn, delta)
    dev = delta - shift[:, None, :]
    return shift, jnp.einsum("kc,kcd,kce->kde", wn, dev, dev)
