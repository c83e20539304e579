"""PruneAndNormalize (Algorithm 1): drop children below ``w_max / ratio``, keep the top ``K``.

The threshold rule is the paper's (Sec. V, ratio 150). Capacity is a second, separate cut: every
child above the threshold that does not fit in ``K`` slots is counted in ``dropped_capacity`` —
never dropped silently. Children are ranked by :func:`~hybridslam.inference.ties.rank_key`: of two
children whose weights tie (to ~1e-9 relative), the one of lower index is kept first, whatever the
last bits of the two weights (which differ between CPUs).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp
from jaxtyping import Array, Float, Int

from ...inference.ties import rank_key


class PruneStats(eqx.Module):
    num_candidates: Int[Array, ""]  # children with a non-zero weight
    num_above_threshold: Int[Array, ""]
    dropped_threshold: Int[Array, ""]  # below w_max / ratio (the paper's rule)
    dropped_capacity: Int[Array, ""]  # above the threshold but beyond K: information lost


def prune(
    log_weights: Float[Array, " C"], capacity: int, ratio: Float[Array, ""]
) -> tuple[Int[Array, " K"], Float[Array, " K"], PruneStats]:
    """Return the kept indices (sorted by weight, highest first; tied weights by index) and their
    normalized log-weights.

    Slots beyond the survivors get ``-inf``.
    """
    if log_weights.shape[0] < capacity:  # fewer candidates than slots: pad with impossible ones
        log_weights = jnp.pad(log_weights, (0, capacity - log_weights.shape[0]), constant_values=-jnp.inf)
    finite = log_weights > -jnp.inf
    threshold = jnp.max(log_weights) - jnp.log(ratio)
    above = finite & (log_weights >= threshold)
    _, index = jax.lax.top_k(rank_key(jnp.where(above, log_weights, -jnp.inf)), capacity)
    values = jnp.where(above, log_weights, -jnp.inf)[index]
    kept = values > -jnp.inf
    values = jnp.where(kept, values - logsumexp(jnp.where(kept, values, -jnp.inf)), -jnp.inf)
    n_cand, n_above = jnp.sum(finite), jnp.sum(above)
    stats = PruneStats(n_cand, n_above, n_cand - n_above, jnp.maximum(n_above - capacity, 0))
    return index, values, stats
