"""Marginals of a smoothed graph: the Laplace marginal of ``[x_k, objects]`` for the filter side
(:func:`marginal`), and the fixed-lag marginalization of ``x_0`` into the next window's prior
(:func:`marginalize_first`, a Schur complement of the factors that touch it)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float, Int

from .. import buckets
from ..update import wrap_angles
from .blocks import tridiagonal_inverse_diagonal, tridiagonal_solve
from .elimination import AbstractElimination, Method, as_elimination
from .graph import FactorGraph
from .linearization import Linearization, linearize
from .lm import Solution


def marginal(
    solution: Solution, k: Int[Array, ""] | int, method: Method | AbstractElimination = "auto"
) -> tuple[Float[Array, " D0"], Float[Array, "D0 D0"]]:
    """Laplace marginal of ``[x_k, o_0..o_{N-1}]`` (``D₀ = 3 + 3N``): the mean at the solution and
    the matching block of ``H⁻¹`` (Gauss-Newton Hessian), every other pose marginalized.

    ``method`` (a name or an :class:`~.elimination.AbstractElimination`) says the elimination order,
    :meth:`~.elimination.AbstractElimination.for_marginal`: ``"auto"`` eliminates the objects first
    where :func:`~.elimination.resolve_method` would and ``C`` is block-diagonal, else the poses
    (``"dense"`` takes the poses-first path too); the formulas are those of
    :meth:`~.elimination.AbstractElimination.covariance`. ``k`` may be traced. Inactive
    objects get identity covariance, uncorrelated (the filters' uncreated slots). The blocks are
    the solver's own linearization at the solution (``solution.linearization``), not formed again.
    """
    lin = solution.linearization
    p, n3 = lin.pose_diag.shape[0], lin.grad_object.shape[0]
    mean = jnp.concatenate([solution.poses[k], solution.objects.reshape(-1)])
    order = as_elimination(method).for_marginal(p, n3 // 3, lin.object_blocks)  # for the whole graph, whatever the bucket

    def on_head(size: tuple[int, int], lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
        cov = order.covariance(lin.head(*size), k)
        # The inactive objects left out: identity covariance, uncorrelated (what the whole H gives).
        return jax.scipy.linalg.block_diag(cov, jnp.eye(n3 - 3 * size[1], dtype=cov.dtype))

    sizes, (live_p, live_o) = lin.buckets()
    live = (jnp.maximum(live_p, jnp.asarray(k) + 1), live_o)  # x_k itself must be in the head
    return mean, buckets.by_bucket(sizes, live, on_head, lin, k)


class Covariances(eqx.Module):
    """Blocks of the whole ``H⁻¹`` (Laplace covariance of every pose and object) at a solution:
    ``poses (P, 3, 3)`` each pose's marginal, ``pose_object (P, 3, 3N)`` each pose's cross-covariance
    with the map, ``objects (3N, 3N)`` the map's joint covariance."""

    poses: Float[Array, "P 3 3"]
    pose_object: Float[Array, "P 3 N3"]
    objects: Float[Array, "N3 N3"]


def covariances(solution: Solution) -> Covariances:
    """:class:`Covariances` of ``solution`` by the poses-first block inverse: ``Σ_OO = S⁻¹`` with
    ``S = C − BᵀA⁻¹B``, ``Σ_PO = −(A⁻¹B) S⁻¹``, ``Σ_tt = (A⁻¹)_tt + (A⁻¹B)_t S⁻¹ (A⁻¹B)_tᵀ``, the
    diagonal blocks of ``A⁻¹`` by :func:`~.blocks.tridiagonal_inverse_diagonal`: ``O(P N²)`` work,
    never the ``(3P)²`` pose covariance. Inactive slots keep their identity blocks (uncorrelated)."""
    lin = solution.linearization
    p, n3 = lin.pose_diag.shape[0], lin.grad_object.shape[0]
    x = tridiagonal_solve(lin.pose_diag, lin.pose_off, lin.pose_object)  # A⁻¹B, (P, 3, 3N)
    s = lin.object_dense() - lin.pose_object.reshape(3 * p, n3).T @ x.reshape(3 * p, n3)
    chol = jnp.linalg.cholesky(0.5 * (s + s.T))
    chol_inv = jsl.solve_triangular(chol, jnp.eye(n3, dtype=s.dtype), lower=True)
    s_oo = chol_inv.T @ chol_inv
    s_po = -jnp.einsum("pij,jk->pik", x, s_oo)
    s_pp = tridiagonal_inverse_diagonal(lin.pose_diag, lin.pose_off) - jnp.einsum("pik,pjk->pij", s_po, x)
    return Covariances(0.5 * (s_pp + jnp.swapaxes(s_pp, -1, -2)), s_po, s_oo)


def first_pose_factors(graph: FactorGraph) -> FactorGraph:
    """The graph restricted to the factors that touch ``x_0``: the prior, odometry factor 1 and the
    measurement factors of pose 0 (the others get weight ``-inf`` / inactive)."""
    first_odo = graph.odometry_active & (jnp.arange(graph.odometry_active.shape[0]) == 0)
    at_first = graph.meas_pose == 0
    return eqx.tree_at(
        lambda g: (g.odometry_active, g.meas_log_weight, g.meas_null_log_weight),
        graph,
        (first_odo, jnp.where(at_first[:, None], graph.meas_log_weight, -jnp.inf),
         jnp.where(at_first, graph.meas_null_log_weight, -jnp.inf)),
    )


def marginalize_first(
    graph: FactorGraph, poses: Float[Array, "P 3"], objects: Float[Array, "N 3"]
) -> tuple[Float[Array, " D0"], Float[Array, "D0 D0"]]:
    """Fixed-lag marginalization of ``x_0``: the prior ``(mean, R)`` of
    :func:`marginalize_first_information`, without its information matrix."""
    mean, sqrt_info, _ = marginalize_first_information(graph, poses, objects)
    return mean, sqrt_info


def marginalize_first_information(
    graph: FactorGraph, poses: Float[Array, "P 3"], objects: Float[Array, "N 3"]
) -> tuple[Float[Array, " D0"], Float[Array, "D0 D0"], Float[Array, "D0 D0"]]:
    """Fixed-lag marginalization of ``x_0``: the Gaussian prior ``(mean, R)`` over ``[x_1, objects]``.

    The factors touching ``x_0`` (:func:`first_pose_factors`) are linearized at ``(poses, objects)``
    (a solution of ``graph``, or the current estimate),
    ``½δᵀHδ + gᵀδ`` over ``[x_0 | x_1, O]``; eliminating ``x_0`` gives the Schur complement
    ``H' = H_rr − H_r0 H_00⁻¹ H_0r``, ``g' = g_r − H_r0 H_00⁻¹ g_0``, i.e. the prior
    ``½‖R (y ⊖ μ)‖²`` with ``RᵀR = H'`` (``R`` upper triangular) and ``μ = ŷ ⊕ (−H'⁻¹g')``. Exact
    for linear-Gaussian factors; the standard fixed-lag approximation otherwise (the factors stay
    linearized at this solution). The next window's graph takes it as ``prior_mean`` /
    ``prior_sqrt_info`` / ``prior_info``. Inactive objects keep their value and an identity block;
    coordinates that nothing informs keep their value and get a zero row of ``R`` (no information).

    Returns ``(mean, R, H')``. ``RᵀR = H'`` exactly: an uninformed coordinate ``u`` has a zero row
    and column in ``H'``, so the Cholesky factor of ``H' + e_u e_uᵀ`` has column ``e_u``, the row of
    ``R`` that is zeroed. Handing ``H'`` on saves the next solve its ``O(D₀³)`` product ``RᵀR``.
    """
    lin = linearize(first_pose_factors(graph), poses, objects)
    d0 = 3 + lin.grad_object.shape[0]

    def on_head(size: tuple[int, int], lin: Linearization):
        # The objects after the live ones are inactive: identity blocks of H', uncoupled, zero
        # gradient, so they keep their value and an identity block of R and H' (what the whole
        # computation gives them), and the O(D₀³) factorization is done on the live head only.
        lin = lin.head(lin.pose_diag.shape[0], size[1])
        h_0r = jnp.concatenate([lin.pose_off[0], lin.pose_object[0]], axis=-1)  # (3, 3 + 3n)
        h_rr = jnp.block([[lin.pose_diag[1], lin.pose_object[1]], [lin.pose_object[1].T, lin.object_dense()]])
        g_r = jnp.concatenate([lin.grad_pose[1], lin.grad_object])
        t = jsl.cho_solve((jnp.linalg.cholesky(lin.pose_diag[0]), True),
                          jnp.concatenate([h_0r, lin.grad_pose[0][:, None]], axis=-1))
        h = h_rr - h_0r.T @ t[:, :-1]
        h = 0.5 * (h + h.T)
        g = g_r - h_0r.T @ t[:, -1]
        # A coordinate no factor informs (a discovered object's position, before the pose that saw
        # it first is marginalized) has an exactly zero row and column: it stays uninformed (a
        # zero row of R), factorized through a unit diagonal so that the Cholesky factor exists.
        uninformed = jnp.diagonal(h) <= 0.0
        chol = jnp.linalg.cholesky(h + jnp.diag(uninformed.astype(h.dtype)))
        step = jsl.cho_solve((chol, True), jnp.where(uninformed, 0.0, g))
        eye = jnp.eye(d0 - h.shape[0], dtype=h.dtype)
        return (jnp.concatenate([step, jnp.zeros(eye.shape[0], step.dtype)]),
                jsl.block_diag(jnp.where(uninformed[:, None], 0.0, chol.T), eye), jsl.block_diag(h, eye))

    sizes, (_, live_objects) = lin.buckets()
    sizes = tuple(dict.fromkeys((0, n) for _, n in sizes))  # by the live objects only (x_0, x_1 are whole)
    step, r, h = buckets.by_bucket(sizes, (0, live_objects), on_head, lin)
    y = jnp.concatenate([poses[1], objects.reshape(-1)])
    return wrap_angles(y - step), r, h
