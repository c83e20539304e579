"""Short sums and small Cholesky factors written out entry by entry, for the hottest elementwise code.

XLA on CPU lowers a reduction to its own loop that does not fuse with the elementwise work
around it, so a ``jnp.sum`` over an axis of 2-4 entries inside ``vmap`` over samples and objects
materializes its operand and loops over it again. Slicing the axis and adding the slices keeps
the whole computation one fused elementwise loop: the per-sample likelihood table of the sampled
weights (Eq. 16) takes 100 ns per (draw, object) instead of 200 ns this way. Likewise a batch of
small Cholesky factorizations is one LAPACK call per matrix plus layout copies, where the
written-out factorization fuses over the batch (:func:`gaussian_terms`). The results are the same
sums and factors; only the rounding of the last bits may differ.
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

MAX_UNROLLED = 8  # longer axes: jnp.sum (unrolling would only grow the program)


def sum_last(a: Float[Array, "*B n"]) -> Float[Array, "*B"]:
    """``jnp.sum(a, axis=-1)``, unrolled into adds when the axis has at most :data:`MAX_UNROLLED` entries."""
    n = a.shape[-1]
    if n == 0 or n > MAX_UNROLLED:
        return jnp.sum(a, axis=-1)
    return functools.reduce(operator.add, (a[..., j] for j in range(n)))


MAX_UNROLLED_CHOLESKY = 12  # larger matrices: LAPACK (the unrolled program grows as n³)


def gaussian_terms(s: Float[Array, "n n"], r: Float[Array, " n"]) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """``(rᵀ S⁻¹ r, log|S|)`` of a symmetric positive-definite ``S``, by Cholesky ``S = L Lᵀ``: the two
    terms of a Gaussian log density such as the joint innovation density (thesis Eq. 4.14-4.15).

    Up to :data:`MAX_UNROLLED_CHOLESKY` rows the factorization and the forward substitution are
    written out entry by entry: under ``vmap`` they become one fused elementwise loop over the
    batch instead of a LAPACK call per matrix plus the layout copies around it (the hybrid belief
    scores hundreds of 8×8 joint innovation covariances per step this way). Larger ``S`` go to
    ``jnp.linalg.cholesky``, which first symmetrizes ``S``; the unrolled path reads its lower
    triangle only (the same for a symmetric ``S``). Both give NaN where ``S`` is not positive
    definite.
    """
    _, white, log_det = cholesky_whiten(s, r)
    return jnp.sum(white**2), log_det


def cholesky_whiten(
    s: Float[Array, "n n"], r: Float[Array, " n"]
) -> tuple[Float[Array, "n n"], Float[Array, " n"], Float[Array, ""]]:
    """``(L, L⁻¹ r, log|S|)`` with ``S = L Lᵀ`` (``L`` lower triangular), written out entry by entry up
    to :data:`MAX_UNROLLED_CHOLESKY` rows as :func:`gaussian_terms` says, by LAPACK beyond."""
    n = s.shape[-1]
    if n > MAX_UNROLLED_CHOLESKY:
        chol = jnp.linalg.cholesky(s)
        whitened = jax.scipy.linalg.solve_triangular(chol, r, lower=True)
        return chol, whitened, 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
    zero = jnp.zeros((), s.dtype)
    low: list[list] = [[zero] * n for _ in range(n)]
    white: list = [None] * n
    log_det = zero
    for j in range(n):
        d = s[j, j] - sum((low[j][k] ** 2 for k in range(j)), start=zero)
        low[j][j] = jnp.sqrt(d)
        log_det = log_det + jnp.log(d)
        for i in range(j + 1, n):
            off = s[i, j] - sum((low[i][k] * low[j][k] for k in range(j)), start=zero)
            low[i][j] = off / low[j][j]
        white[j] = (r[j] - sum((low[j][k] * white[k] for k in range(j)), start=zero)) / low[j][j]
    return jnp.stack([jnp.stack(row) for row in low]), jnp.stack(white), log_det
