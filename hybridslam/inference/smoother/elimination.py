"""Elimination orders of the normal equations ``H δ = −g``: strategies as objects.

``H = [[A, B], [Bᵀ, C]]`` (:class:`~.linearization.Linearization`). :class:`PosesFirst` eliminates
the block-tridiagonal poses by a scan and factors the Schur complement onto the objects;
:class:`ObjectsFirst` inverts ``C`` (block by block when block-diagonal) and factors a dense ``3P``
pose system; :class:`Dense` solves the full ``H`` (the reference); :class:`Auto` picks one of the
first two by the shapes. Each gives the step (:meth:`AbstractElimination.solve`) and the marginal
covariance of ``[x_k, objects]`` (:meth:`AbstractElimination.covariance`). The names ``"auto"``,
``"poses-first"``, ``"objects-first"``, ``"dense"`` stand for them wherever a ``method`` is taken
(:func:`as_elimination`).
"""

from __future__ import annotations

import abc
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float, Int

from .. import buckets
from .blocks import _backward3, _chol3, _forward3, _tridiagonal_dense, tridiagonal_solve
from .linearization import Linearization, _diagonal_blocks

Method = Literal["auto", "poses-first", "objects-first", "dense"]

SMALL_POSE_SYSTEM = 16  # poses; up to it a dense 3P pose system beats the tridiagonal scan (resolve_method)


class _PoseElimination(eqx.Module):
    """Poses eliminated: ``X = A⁻¹ [B | extra]`` and the Cholesky factor of ``S = C − Bᵀ A⁻¹ B``."""

    a_inv_b: Float[Array, "P 3 N3"]
    a_inv_extra: Float[Array, "P 3 K"]
    schur_chol: Float[Array, "N3 N3"]


def _eliminate_poses(lin: Linearization, extra: Float[Array, "P 3 K"]) -> _PoseElimination:
    n3 = lin.grad_object.shape[0]
    p = lin.pose_diag.shape[0]
    x = tridiagonal_solve(lin.pose_diag, lin.pose_off, jnp.concatenate([lin.pose_object, extra], axis=-1))
    a_inv_b = x[..., :n3]
    s = lin.object_dense() - lin.pose_object.reshape(3 * p, n3).T @ a_inv_b.reshape(3 * p, n3)
    s = 0.5 * (s + s.T)  # symmetric to rounding; Cholesky reads one triangle
    return _PoseElimination(a_inv_b, x[..., n3:], jnp.linalg.cholesky(s))


def _solve_poses_first(lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
    """Schur complement onto the objects: ``S δ_o = −g_o + Bᵀ A⁻¹ g_p``, ``δ_p = A⁻¹(−g_p − B δ_o)``."""
    p, n3 = lin.pose_diag.shape[0], lin.grad_object.shape[0]
    elim = _eliminate_poses(lin, -lin.grad_pose[..., None])
    x_g = elim.a_inv_extra[..., 0]
    rhs = -lin.grad_object - lin.pose_object.reshape(3 * p, n3).T @ x_g.reshape(-1)
    d_o = jsl.cho_solve((elim.schur_chol, True), rhs)
    d_p = x_g - jnp.sum(elim.a_inv_b * d_o[None, None, :], axis=-1)
    return d_p, d_o



def _object_blocks(lin: Linearization) -> Float[Array, "N 3 3"]:
    """The diagonal 3×3 blocks of ``C``."""
    return lin.object if lin.object_blocks else _diagonal_blocks(lin.object)


def _object_solve(lin: Linearization, rhs: Float[Array, "N3 K"]) -> Float[Array, "N3 K"]:
    """``C⁻¹ rhs``: block by block (closed-form 3×3 Cholesky factors, ``O(N K)``) if ``C`` is
    block-diagonal (``lin.object_blocks``), else by a dense ``3N`` Cholesky (``O(N³ + N² K)``)."""
    if lin.object_blocks:
        n = rhs.shape[0] // 3
        chol = _chol3(_object_blocks(lin))
        return _backward3(chol, _forward3(chol, rhs.reshape(n, 3, -1))).reshape(rhs.shape)
    return jsl.cho_solve((jnp.linalg.cholesky(lin.object), True), rhs)


class _ObjectElimination(eqx.Module):
    """Objects eliminated: ``Y = C⁻¹ [Bᵀ | extra]`` and the Cholesky factor of ``S = A − B C⁻¹ Bᵀ``."""

    c_inv_bt: Float[Array, "N3 P3"]
    c_inv_extra: Float[Array, "N3 K"]
    schur_chol: Float[Array, "P3 P3"]


def _eliminate_objects(lin: Linearization, extra: Float[Array, "N3 K"]) -> _ObjectElimination:
    p = lin.pose_diag.shape[0]
    b = lin.pose_object.reshape(3 * p, -1)
    y = _object_solve(lin, jnp.concatenate([b.T, extra], axis=-1))
    s = _tridiagonal_dense(lin.pose_diag, lin.pose_off) - b @ y[:, : 3 * p]
    s = 0.5 * (s + s.T)
    return _ObjectElimination(y[:, : 3 * p], y[:, 3 * p:], jnp.linalg.cholesky(s))


def _solve_objects_first(lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
    """Schur complement onto the poses: ``C`` inverted (blockwise if block-diagonal, else by a dense
    ``3N`` Cholesky), then a dense ``3P`` system: ``S δ_p = −g_p + B C⁻¹ g_o``, ``δ_o = C⁻¹(−g_o − Bᵀδ_p)``."""
    p = lin.pose_diag.shape[0]
    b = lin.pose_object.reshape(3 * p, -1)
    elim = _eliminate_objects(lin, -lin.grad_object[:, None])
    y_g = elim.c_inv_extra[:, 0]
    d_p = jsl.cho_solve((elim.schur_chol, True), -lin.grad_pose.reshape(-1) - b @ y_g)
    return d_p.reshape(p, 3), y_g - elim.c_inv_bt @ d_p


def _solve_dense(lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
    """Reference: the full ``H``, ``jnp.linalg.solve``."""
    p = lin.pose_diag.shape[0]
    h, g = lin.dense()
    d = jnp.linalg.solve(h, -g)
    return d[: 3 * p].reshape(p, 3), d[3 * p:]


class AbstractElimination(eqx.Module):
    """An elimination order of ``H δ = −g`` (no fields: static, one compile per order)."""

    name: ClassVar[str]
    bucketed: ClassVar[bool] = True  # solved on the live prefix at a bucketed size (buckets.py)

    @abc.abstractmethod
    def solve(self, lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
        """The Gauss-Newton step ``δ = −H⁻¹ g`` of ``lin``: ``(δ_p, δ_o)``, ``δ_o`` flat."""

    @abc.abstractmethod
    def covariance(self, lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
        """The block of ``H⁻¹`` over ``[x_k, o_0..o_{N-1}]`` (:func:`~.marginals.marginal`)."""

    def resolve(self, num_poses: int, num_objects: int, object_blocks: bool = False) -> AbstractElimination:
        """The order that solves a graph of these sizes: itself, but for :class:`Auto`."""
        del num_poses, num_objects, object_blocks
        return self

    def for_marginal(self, num_poses: int, num_objects: int, object_blocks: bool = False) -> AbstractElimination:
        """The order :func:`~.marginals.marginal` eliminates in: :meth:`resolve`, but for :class:`Auto`."""
        return self.resolve(num_poses, num_objects, object_blocks)


def _covariance_poses_first(lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
    """Poses first: ``Σ_OO = S⁻¹`` with ``S = C − BᵀA⁻¹B``, ``Σ_kO = −(A⁻¹B)_k S⁻¹``,
    ``Σ_kk = (A⁻¹)_kk + (A⁻¹B)_k S⁻¹ (A⁻¹B)_kᵀ``, with ``(A⁻¹)_kk`` from the same tridiagonal solve
    (three extra right-hand sides ``e_k``)."""
    p, n3 = lin.pose_diag.shape[0], lin.grad_object.shape[0]
    eye = jnp.eye(3, dtype=lin.pose_diag.dtype)
    e_k = jnp.where((jnp.arange(p) == k)[:, None, None], eye[None], 0.0)
    pelim = _eliminate_poses(lin, e_k)
    chol_inv = jsl.solve_triangular(pelim.schur_chol, jnp.eye(n3, dtype=eye.dtype), lower=True)
    s_oo = chol_inv.T @ chol_inv  # S⁻¹ = L⁻ᵀL⁻¹, symmetric by construction
    x_k = pelim.a_inv_b[k]  # (A⁻¹B)_k, (3, 3N)
    s_ko = -x_k @ s_oo
    s_kk = pelim.a_inv_extra[k] - s_ko @ x_k.T
    return jnp.block([[0.5 * (s_kk + s_kk.T), s_ko], [s_ko.T, s_oo]])


def _covariance_objects_first(lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
    """Objects first, with ``S_p = A − B C⁻¹ Bᵀ = L Lᵀ``, ``Z = L⁻¹ B C⁻¹`` and ``u = L⁻¹ e_k``:
    ``Σ_OO = C⁻¹ + ZᵀZ``, ``Σ_kO = −uᵀZ``, ``Σ_kk = uᵀu`` (the block inverse of ``H``; only
    ``C⁻¹`` is inverted, blockwise when ``C`` is block-diagonal)."""
    p, n3 = lin.pose_diag.shape[0], lin.grad_object.shape[0]
    eye = jnp.eye(3, dtype=lin.pose_diag.dtype)
    c_inv = _object_solve(lin, jnp.eye(n3, dtype=eye.dtype))
    elim = _eliminate_objects(lin, jnp.zeros((n3, 0), eye.dtype))
    # Zᵀ = (C⁻¹Bᵀ) L⁻ᵀ, solved from the right so that Zᵀ comes out row-major and ZᵀZ contracts
    # both operands' last axis: half the time of L⁻¹(C⁻¹Bᵀ)ᵀ and a transposed product
    # (hallway, 3P = 183, 3N = 210: 0.78 against 1.41 ms).
    z_t = jax.lax.linalg.triangular_solve(elim.schur_chol, elim.c_inv_bt, left_side=False, lower=True,
                                          transpose_a=True)  # (3N, 3P)
    e_k = jnp.where((jnp.arange(3 * p) // 3 == k)[:, None], jnp.tile(eye, (p, 1)), 0.0)
    u = jsl.solve_triangular(elim.schur_chol, e_k, lower=True)  # (3P, 3)
    s_oo = c_inv + z_t @ z_t.T
    s_oo, s_ko, s_kk = 0.5 * (s_oo + s_oo.T), -(z_t @ u).T, u.T @ u
    return jnp.block([[0.5 * (s_kk + s_kk.T), s_ko], [s_ko.T, s_oo]])


class PosesFirst(AbstractElimination):
    """Schur complement onto the objects, the poses by the tridiagonal scan (:func:`_solve_poses_first`)."""

    name: ClassVar[str] = "poses-first"

    def solve(self, lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
        return _solve_poses_first(lin)

    def covariance(self, lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
        return _covariance_poses_first(lin, k)


class ObjectsFirst(AbstractElimination):
    """Schur complement onto the poses, ``C`` inverted first (:func:`_solve_objects_first`)."""

    name: ClassVar[str] = "objects-first"

    def solve(self, lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
        return _solve_objects_first(lin)

    def covariance(self, lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
        return _covariance_objects_first(lin, k)


class Dense(AbstractElimination):
    """The reference: the full ``H``, ``jnp.linalg.solve``, on the whole graph (no buckets); its
    marginal takes the poses-first path."""

    name: ClassVar[str] = "dense"
    bucketed: ClassVar[bool] = False

    def solve(self, lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
        return _solve_dense(lin)

    def covariance(self, lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
        return _covariance_poses_first(lin, k)


class Auto(AbstractElimination):
    """The elimination order of ``"auto"`` for ``num_poses`` poses and ``num_objects`` objects.

    Both structured orders end in one dense Cholesky, of ``C − BᵀA⁻¹B`` (``3N``) or of
    ``A − BC⁻¹Bᵀ`` (``3P``); poses-first gets its ``A⁻¹B`` from the ``O(P)`` tridiagonal scan, while
    objects-first must form and factor the dense ``3P`` pose system. The dense factorization
    dominates, so ``"auto"`` eliminates the larger set first: poses-first unless there are more
    objects than poses (``scripts/bench_smoother.py`` on a 2-core CPU, per solve: P = 201, N = 15
    0.77 ms poses-first against 4.8 ms objects-first; P = 61, N = 70, the hallway, 2.45 against
    1.52 ms, and 0.7-0.9 ms objects-first with a block-diagonal ``C``). With a block-diagonal ``C``
    (``object_blocks``) and at most :data:`SMALL_POSE_SYSTEM` poses the ``3P`` factorization is
    cheaper than the scan's ``P`` sequential steps, so objects-first is chosen there too (the paper
    setup, P = 11, N = 6: 0.16 against 0.22 ms per solve, 5.7 against 8.1 ms for 256 vmapped; at
    P = 16 8.1 against 11.5 ms, at P = 21 26 against 19 ms, for 256).
    """

    name: ClassVar[str] = "auto"

    def resolve(self, num_poses: int, num_objects: int, object_blocks: bool = False) -> AbstractElimination:
        small = object_blocks and num_poses <= SMALL_POSE_SYSTEM
        return ObjectsFirst() if num_objects > num_poses or small else PosesFirst()

    def for_marginal(self, num_poses: int, num_objects: int, object_blocks: bool = False) -> AbstractElimination:
        # With a dense C the marginal keeps the poses-first path: inverting C densely buys nothing there.
        order = self.resolve(num_poses, num_objects, object_blocks)
        return order if object_blocks else PosesFirst()

    def _resolved(self, lin: Linearization) -> AbstractElimination:
        return self.resolve(lin.pose_diag.shape[0], lin.grad_object.shape[0] // 3, lin.object_blocks)

    def solve(self, lin: Linearization) -> tuple[Float[Array, "P 3"], Float[Array, " N3"]]:
        return self._resolved(lin).solve(lin)

    def covariance(self, lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
        return self._resolved(lin).covariance(lin, k)


_BY_NAME: dict[str, AbstractElimination] = {e.name: e for e in (Auto(), PosesFirst(), ObjectsFirst(), Dense())}


def as_elimination(method: Method | AbstractElimination) -> AbstractElimination:
    """The strategy object of ``method`` (a name or a strategy); ``ValueError`` naming it otherwise."""
    if isinstance(method, AbstractElimination):
        return method
    if method not in _BY_NAME:
        solvers = [name for name in _BY_NAME if name != "auto"]
        raise ValueError(f"method: expected one of {sorted(solvers)} or 'auto', got {method!r}")
    return _BY_NAME[method]


def resolve_method(method: Method | AbstractElimination, num_poses: int, num_objects: int,
                   object_blocks: bool = False) -> Method:
    """The name of the elimination order of ``method`` (``"auto"``: :class:`Auto`'s choice) for
    ``num_poses`` poses and ``num_objects`` objects."""
    return as_elimination(method).resolve(num_poses, num_objects, object_blocks).name  # type: ignore[return-value]


def solve_normal(
    lin: Linearization, method: Method | AbstractElimination = "auto"
) -> tuple[Float[Array, "P 3"], Float[Array, "N 3"]]:
    """The Gauss-Newton step ``δ = −H⁻¹ g`` of ``lin`` (damp it first with :meth:`~Linearization.damped`)."""
    p, n = lin.pose_diag.shape[0], lin.grad_object.shape[0] // 3
    order = as_elimination(method).resolve(p, n, lin.object_blocks)
    if not order.bucketed:
        d_p, d_o = order.solve(lin)
        return d_p, d_o.reshape(n, 3)

    def on_head(size: tuple[int, int], lin: Linearization):
        d_p, d_o = order.solve(lin.head(*size))
        # The inactive slots left out: δ = 0.
        return (jnp.concatenate([d_p, jnp.zeros((p - size[0], 3), d_p.dtype)]),
                jnp.concatenate([d_o, jnp.zeros(3 * (n - size[1]), d_o.dtype)]))

    sizes, live = lin.buckets()
    d_p, d_o = buckets.by_bucket(sizes, live, on_head, lin)
    return d_p, d_o.reshape(n, 3)
