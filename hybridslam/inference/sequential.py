"""The joint innovation density of an association hypothesis, one detection at a time.

Every estimator ranks joint assignments of a step's detections by their linearized likelihood,
the joint innovation density ``N(r; 0, S)``, ``S = H Σ Hᵀ + I⊗Σ_v`` over the detections associated
with mapped objects (thesis Eq. 4.14-4.15 stacked over the detections; the multimodal estimator's
screening of Eq. 5.10). The detections share the robot pose and correlated objects, so ``S`` is
not block diagonal; computed at once it costs a ``2D × 2D`` Cholesky per assignment.

A beam search (:func:`hybridslam.inference.beam.beam_search`) extends partial assignments one
detection at a time, and the chain rule gives the same density in that order:
``N(r; 0, S) = Π_j N(r_j; H_j δ_<j, H_j Σ_<j H_jᵀ + Σ_v)``, where ``δ_<j`` and ``Σ_<j`` are the
state's mean shift and covariance given the earlier residuals (Kalman updates at the same, fixed
linearization point). :class:`Conditioned` keeps them per partial assignment as a low-rank
downdate ``Σ_<j = Σ − U Uᵀ`` (two columns of ``U`` per detection), so extending an assignment by
one detection costs a 2×2 density (:func:`innovation_log_density`) and keeping it one rank-2
update (:func:`condition`). The two forms agree to rounding (tested against the joint form).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .gating import Innovations

_LOG_2PI = math.log(2 * math.pi)


class Conditioned(eqx.Module):
    """Partial assignments' linearized states (leading axis ``W``, one per assignment, inside a
    beam; none inside its vmapped score): ``Σ_b = Σ − U Uᵀ`` and the conditional mean shift ``δ``
    of the state ``[x_k, o_0, ...]`` given the residuals of the detections associated so far."""

    low_rank: Float[Array, "*W D R"]  # R = 2 Dmax: columns 2j, 2j+1 belong to detection j
    shift: Float[Array, "*W D"]


def start(width: int, dim: int, slots: int, dtype=float) -> Conditioned:
    """``width`` empty assignments over a ``dim``-dimensional state and ``slots`` detections."""
    return Conditioned(jnp.zeros((width, dim, 2 * slots), dtype), jnp.zeros((width, dim), dtype))


def _inverse_chol2(s: Float[Array, "2 2"]) -> tuple[Float[Array, "2 2"], Float[Array, ""]]:
    """``L⁻¹`` with ``S = L Lᵀ``, and ``log|S|``, in closed form (no batched LAPACK call per extension)."""
    a = jnp.sqrt(s[0, 0])
    b = s[1, 0] / a
    c = jnp.sqrt(s[1, 1] - b**2)
    zero = jnp.zeros_like(a)
    inv = jnp.stack([jnp.stack([1.0 / a, zero]), jnp.stack([-b / (a * c), 1.0 / c])])
    return inv, 2.0 * (jnp.log(a) + jnp.log(c))


def _innovation(pred: Innovations, row: Conditioned, j: Int[Array, ""], obj: Int[Array, ""]):
    o = jnp.maximum(obj, 0)
    jac = jnp.concatenate([pred.jac_pose[o], pred.jac_object[o]], axis=-1)  # (2, 6): ∂h/∂(x_k, o)
    sub = jnp.concatenate([jnp.arange(3), 3 + 3 * o + jnp.arange(3)])
    hu = jac @ row.low_rank[sub]
    inv_l, log_det = _inverse_chol2(pred.cov[o] - hu @ hu.T)  # pred.cov = H Σ Hᵀ + Σ_v
    return jac, sub, hu, inv_l, log_det, pred.residual[j, o] - jac @ row.shift[sub]


def innovation_log_density(pred: Innovations, row: Conditioned, j: Int[Array, ""],
                           obj: Int[Array, ""]) -> Float[Array, ""]:
    """``log N(r_j; H δ, H Σ_b Hᵀ + Σ_v)``: detection ``j`` of object ``obj`` given the detections
    ``row`` has associated (``-inf`` where the density is not finite)."""
    _, _, _, inv_l, log_det, e = _innovation(pred, row, j, obj)
    u = inv_l @ e
    out = -0.5 * u @ u - 0.5 * log_det - _LOG_2PI
    return jnp.where(jnp.isfinite(out), out, -jnp.inf)


def condition(pred: Innovations, cov: Float[Array, "D D"], row: Conditioned, j: Int[Array, ""],
              obj: Int[Array, ""], associated: Bool[Array, ""]) -> Conditioned:
    """``row`` extended by detection ``j``: when it is ``associated`` with the mapped object ``obj``,
    ``Σ_b ← Σ_b − u uᵀ`` with ``u = Σ_b Hᵀ L⁻ᵀ`` and ``δ ← δ + u L⁻¹ e`` (a Kalman update).
    ``cov``: the component's ``Σ``."""
    jac, sub, hu, inv_l, _, e = _innovation(pred, row, j, obj)
    u = (cov[:, sub] @ jac.T - row.low_rank @ hu.T) @ inv_l.T
    low_rank = jax.lax.dynamic_update_slice(row.low_rank, u, (0, 2 * j))
    shift = row.shift + u @ (inv_l @ e)
    ok = associated & jnp.all(jnp.isfinite(u))
    return Conditioned(jnp.where(ok, low_rank, row.low_rank), jnp.where(ok, shift, row.shift))
