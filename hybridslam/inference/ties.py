"""A total order on mixture components that the last bits of their weights cannot change.

Two hypotheses can have exactly equal weights: two class realizations that no measurement has told
apart yet (the hallway's objects whose classifier scores are symmetric), and their children after
them. Computed, such weights differ in the last bits, and which bits depends on XLA's machine code
(AVX2 against AVX-512, one XLA option against another). Ranking by the raw weights would let the CPU
decide which of two tied hypotheses a capacity keeps, and so every later step.

The rank key rounds a log-weight, relative to the largest one, to a multiple of
:data:`TIE_RESOLUTION` (so the largest sits in the middle of its bin, not on an edge where a weight a
few ulps below it would fall into the next one): weights that agree to about ``1e-9`` relative get
the same key, and equal keys are ordered by index (the
children's index is parent-major, and the parents are in this order already, so by induction the
order is the same on every CPU). Two weights that differ by a few units in the last place fall into
different keys only when a bin edge (an odd multiple of half the resolution from the largest) lies
between them: for weights ``1e-16`` apart, a chance of about ``1e-7``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

TIE_RESOLUTION = 1e-9
"""Log-weights closer than this (relative weights within ~1e-9) count as tied: far above the
rounding of a step's weights (~1e-14, the golden files' reruns on other CPUs), far below any
difference a measurement makes."""


def rank_key(log_weights: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
    """``⌊(log w − max log w) / TIE_RESOLUTION + ½⌋``: equal for tied weights, ``-inf`` for ``-inf``.

    Rank components by this key, ties by index (``jax.lax.top_k`` and ``jnp.argmax`` put the lower
    index first)."""
    top = jnp.max(log_weights)
    top = jnp.where(jnp.isfinite(top), top, 0.0)
    return jnp.floor((log_weights - top) / TIE_RESOLUTION + 0.5)


def best_slot(log_weights: Float[Array, " K"]) -> Int[Array, ""]:
    """The first slot of the highest rank (:func:`rank_key`): of tied best components, the lowest slot."""
    return jnp.argmax(rank_key(log_weights))


def rank_key_np(log_weights: np.ndarray) -> np.ndarray:
    """:func:`rank_key` on the host (the result file's component order)."""
    log_weights = np.asarray(log_weights, dtype=float)
    finite = np.isfinite(log_weights)
    top = float(np.max(log_weights[finite])) if finite.any() else 0.0
    with np.errstate(invalid="ignore"):
        return np.floor((log_weights - top) / TIE_RESOLUTION + 0.5)
