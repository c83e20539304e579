"""Structured linear algebra of the smoother's normal equations: closed-form 3×3 Cholesky factors
and the block-tridiagonal solve of the pose chain (fused elementwise 3×3 arithmetic in a
``lax.scan``), and the dense form of a block-tridiagonal matrix."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def _mm(a: Float[Array, "*B i j"], b: Float[Array, "*B j k"]) -> Float[Array, "*B i k"]:
    """3×3 products as broadcast sums: they fuse into elementwise kernels inside the scan."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _chol3(a: Float[Array, "*B 3 3"]) -> tuple[Float[Array, "*B"], ...]:
    """Closed-form Cholesky ``a = L Lᵀ`` of SPD 3×3 blocks: ``(l00, l10, l20, l11, l21, l22)``."""
    l00 = jnp.sqrt(a[..., 0, 0])
    l10, l20 = a[..., 1, 0] / l00, a[..., 2, 0] / l00
    l11 = jnp.sqrt(a[..., 1, 1] - l10**2)
    l21 = (a[..., 2, 1] - l20 * l10) / l11
    l22 = jnp.sqrt(a[..., 2, 2] - l20**2 - l21**2)
    return l00, l10, l20, l11, l21, l22


def _forward3(chol, b: Float[Array, "*B 3 K"]) -> Float[Array, "*B 3 K"]:
    """``L⁻¹ b`` for a :func:`_chol3` factor."""
    l00, l10, l20, l11, l21, l22 = (c[..., None] for c in chol)
    y0 = b[..., 0, :] / l00
    y1 = (b[..., 1, :] - l10 * y0) / l11
    y2 = (b[..., 2, :] - l20 * y0 - l21 * y1) / l22
    return jnp.stack([y0, y1, y2], axis=-2)


def _backward3(chol, y: Float[Array, "*B 3 K"]) -> Float[Array, "*B 3 K"]:
    """``L⁻ᵀ y`` for a :func:`_chol3` factor."""
    l00, l10, l20, l11, l21, l22 = (c[..., None] for c in chol)
    x2 = y[..., 2, :] / l22
    x1 = (y[..., 1, :] - l21 * x2) / l11
    x0 = (y[..., 0, :] - l10 * x1 - l20 * x2) / l00
    return jnp.stack([x0, x1, x2], axis=-2)


def tridiagonal_solve(
    diag: Float[Array, "P 3 3"], off: Float[Array, "P1 3 3"], rhs: Float[Array, "P 3 K"]
) -> Float[Array, "P 3 K"]:
    """``A⁻¹ rhs`` for SPD block-tridiagonal ``A`` (``A[i,i] = diag[i]``, ``A[i,i+1] = off[i]``).

    Block Cholesky ``A = L Lᵀ`` with ``L[k,k] = chol(A[k,k] − M_k M_kᵀ)`` and
    ``M_kᵀ = L[k-1,k-1]⁻¹ A[k-1,k]``, forward substitution in the same ``lax.scan``, then a reverse
    scan for ``Lᵀ x = y``: ``O(P K)`` work, ``2P`` sequential steps of fused 3×3 arithmetic. (Cyclic
    reduction, ``log₂ P`` batched levels, was no faster on a 2-core CPU at ``P`` = 11-201.)
    """

    def forward(carry, inputs):
        chol_prev, y_prev = carry
        d, o, b = inputs
        m_t = _forward3(chol_prev, o)  # M_kᵀ
        chol = _chol3(d - _mm(jnp.swapaxes(m_t, -1, -2), m_t))
        y = _forward3(chol, b - _mm(jnp.swapaxes(m_t, -1, -2), y_prev))
        return (chol, y), (chol, m_t, y)

    chol0 = _chol3(diag[0])
    y0 = _forward3(chol0, rhs[0])
    _, (chols, m_ts, ys) = jax.lax.scan(forward, (chol0, y0), (diag[1:], off, rhs[1:]))
    chols = tuple(jnp.concatenate([c0[None], c]) for c0, c in zip(chol0, chols))
    ys = jnp.concatenate([y0[None], ys])

    def backward(x_next, inputs):
        chol, m_t, y = inputs  # m_t = M_{k+1}ᵀ, the block L[k+1,k]ᵀ of Lᵀ's row k
        x = _backward3(chol, y - _mm(m_t, x_next))
        return x, x

    x_last = _backward3(tuple(c[-1] for c in chols), ys[-1])
    _, xs = jax.lax.scan(backward, x_last, (tuple(c[:-1] for c in chols), m_ts, ys[:-1]), reverse=True)
    return jnp.concatenate([xs, x_last[None]])



def tridiagonal_inverse_diagonal(diag: Float[Array, "P 3 3"], off: Float[Array, "P1 3 3"]) -> Float[Array, "P 3 3"]:
    """The diagonal blocks ``(A⁻¹)_ii`` of SPD block-tridiagonal ``A`` (:func:`tridiagonal_solve`'s
    layout), in ``O(P)``: a forward scan of the Schur complements ``D_0 = A_00``,
    ``D_i = A_ii − A_{i-1,i}ᵀ D_{i-1}⁻¹ A_{i-1,i}``, then the backward (Rauch-Tung-Striebel)
    recursion ``Σ_{P-1} = D_{P-1}⁻¹``, ``Σ_i = D_i⁻¹ + G_i Σ_{i+1} G_iᵀ`` with ``G_i = D_i⁻¹ A_{i,i+1}``."""

    def forward(d_inv_prev, inputs):
        a, o_prev = inputs
        d_inv = jnp.linalg.inv(a - _mm(jnp.swapaxes(o_prev, -1, -2), _mm(d_inv_prev, o_prev)))
        return d_inv, d_inv

    d_inv0 = jnp.linalg.inv(diag[0])
    _, d_invs = jax.lax.scan(forward, d_inv0, (diag[1:], off))
    d_invs = jnp.concatenate([d_inv0[None], d_invs])

    def backward(sigma_next, inputs):
        d_inv, o = inputs
        g = _mm(d_inv, o)
        sigma = d_inv + _mm(g, _mm(sigma_next, jnp.swapaxes(g, -1, -2)))
        sigma = 0.5 * (sigma + jnp.swapaxes(sigma, -1, -2))
        return sigma, sigma

    _, sigmas = jax.lax.scan(backward, d_invs[-1], (d_invs[:-1], off), reverse=True)
    return jnp.concatenate([sigmas, d_invs[-1][None]])


def _tridiagonal_dense(diag: Float[Array, "P 3 3"], off: Float[Array, "P1 3 3"]) -> Float[Array, "P3 P3"]:
    """The dense ``3P × 3P`` block-tridiagonal matrix with diagonal blocks ``diag`` and ``off[i]`` at
    block ``(i, i+1)`` (its transpose at ``(i+1, i)``). Built by selects, not scatters: XLA's CPU
    backend expands every scatter into a loop compiled as a kernel of its own."""
    p = diag.shape[0]
    i = jnp.arange(p)
    zero = jnp.zeros((1, 3, 3), diag.dtype)
    above = jnp.concatenate([off, zero])  # row i: the block at (i, i+1)
    below = jnp.concatenate([zero, jnp.swapaxes(off, -1, -2)])  # row i: the block at (i, i-1)

    def band(shift: int, rows: Float[Array, "P 3 3"]) -> Float[Array, "P 3 P 3"]:
        on = (i[:, None] + shift == i[None, :])[:, None, :, None]
        return jnp.where(on, rows[:, :, None, :], 0.0)

    return (band(0, diag) + band(1, above) + band(-1, below)).reshape(3 * p, 3 * p)
