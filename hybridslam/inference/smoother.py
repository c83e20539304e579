"""A factor-graph smoother: the whole trajectory and the map re-solved by damped Gauss-Newton.

The filters of :mod:`hybridslam.estimators` keep one joint Gaussian over ``[x_k, objects]``; the
papers' estimators smooth: every step re-solves (relinearizes) the trajectory ``x_0..x_T`` and the
objects, like GTSAM's batch Levenberg-Marquardt or iSAM2. This module is that solver for one
component; batch components with ``jax.vmap``.

**The problem.** Variables: ``P`` poses ``X (P, 3)`` and ``N`` objects ``O (N, 3)`` (``[x, y, θ]``).
The negative log posterior (up to a constant) is ``½‖r(X, O)‖²`` with whitened residuals

* a dense Gaussian prior on ``y₀ = [x_0, o_0, .., o_{N-1}]``: ``R (y₀ ⊖ μ)`` (headings wrapped),
  ``Λ = RᵀR``. Dense because a fixed-lag window's marginalized prior couples ``x_0`` and the map;
* odometry ``W Log(u_i⁻¹ ∘ x_{i-1}⁻¹ ∘ x_i)`` (:func:`~hybridslam.motion.odometry_residual`,
  GTSAM's ``BetweenFactor<Pose2>``), ``i = 1..P-1``;
* measurement factors ``f`` between pose ``meas_pose[f]`` and candidates ``meas_objects[f, g]``
  with log-weights ``log w_fg`` and a whitened residual ``r_fg, log η_fg = residual_fn(x, o, data_f, g)``
  (``log p = log η − ½‖r‖²``; the measurement factor of Eq. 10). ``mode="sum"``: every candidate
  is a factor ``√w_fg r_fg`` (ML and hybrid: ``G = 1``, ``w = 1``; Gaussian PDA: ``w = p_fg``).
  ``mode="max"``: a max-mixture (Olson & Agarwal; Doherty thesis Sec. 4.1.1, Eq. 4.16): at every
  iterate the factor is its active component ``g* = argmin_g ½‖r_g‖² − log η_g − log w_g`` over
  the candidates and the null component (cost ``−log w_null``, no residual), with no gradient
  through the choice.

**Gauss-Newton** (the update of Tchuiev et al. Eq. 9-11, over the whole trajectory): at an iterate
``y`` with stacked Jacobian ``J``, the step solves ``(JᵀJ + λD) δ = −Jᵀr`` and ``y ← y ⊕ δ``. The
retraction ``⊕`` is plain vector addition on ``[x, y, θ]`` with the heading wrapped (what the
filters do; the minimizer does not depend on the retraction, only the path does).

**Structure.** ``H = JᵀJ`` is never formed from a dense Jacobian: each factor's Jacobian (3×3,
6×6 blocks by ``jax.jacfwd``, vmapped over factors) is scatter-added into

* a block-tridiagonal pose part (odometry chain; measurement factors add to diagonal blocks),
* a pose-object part ``B (3P, 3N)`` (one 3×3 block per measurement factor, plus the prior's
  ``x_0``-map coupling),
* an object part ``C (3N, 3N)``: the prior's ``Λ_OO`` plus 3×3 diagonal blocks.

The elimination ``method="poses-first"`` (the default unless there are more objects than poses
or few poses, :func:`resolve_method`) eliminates the poses first: one block
Cholesky of the tridiagonal pose part (a ``lax.scan`` with closed-form 3×3 Cholesky factors,
elementwise so it fuses on CPU) solves ``A X = [B | −g_p]`` for all right-hand sides at once; the
Schur complement ``S = C − Bᵀ A⁻¹ B`` onto the objects is one dense matmul and a dense ``3N``
Cholesky; back-substitution is ``δ_p = A⁻¹(−g_p) − (A⁻¹B) δ_o``. ``"objects-first"`` (``C``
inverted, then a dense ``3P`` pose system) and ``"dense"`` (the full ``H``, ``jnp.linalg.solve``:
the reference) are selectable; see ``scripts/bench_smoother.py`` for timings. When the prior couples
no two objects (``FactorGraph.independent_objects``: every run's prior is so, a fixed-lag window's
is not), ``C`` is block-diagonal and objects-first inverts it block by block, in closed form: the
hallway's step (61 poses, 70 object slots) then costs one ``3P`` Schur product and Cholesky instead
of two dense ``3N`` factorizations besides.

**Live prefix.** A run's graph is padded to the whole trajectory and the map's capacity; after ``k``
steps only ``x_0..x_k`` and the objects created so far are active, and the padded slots after them
are uncoupled identity rows. :func:`linearize` records those prefixes (``Linearization.live_poses``,
``live_objects``), and :func:`solve_normal` and :func:`marginal` eliminate only the smallest of four
compiled sizes that holds them (:mod:`.buckets`: a quarter, half, three quarters or all of each axis
of 32 slots or more), with the same result: the hallway's solves early in a run work on 16 of its 61
poses and 18 of its 70 objects. Four sizes cost 2-6 s more compilation on the hallway and MRCLAM
(``HYBRIDSLAM_BUCKETS=1``: one size, the whole graph).

**Damping.** Levenberg-Marquardt with Marquardt's scaling ``D = diag(H)`` (clipped to
``[1e-6, 1e32]`` like Ceres, so an unobserved direction is still damped) and Nielsen's update of
``λ`` from the gain ratio ``ρ = (F(y) − F(y ⊕ δ)) / (L(0) − L(δ))``: accept if the true cost
decreased, then ``λ ← λ max(1/3, 1 − (2ρ − 1)³)``; else ``λ ← λν``, ``ν ← 2ν``. The loop keeps the
linearization of the current iterate: each iteration linearizes once, at the candidate (its cost
comes with it). Stops when ``max|δ| < state_tol`` (1 µm / 1 µrad by default, the filters'
``GN_TOLERANCE``), when an accepted step lowers the cost by less than ``cost_rtol`` relative, when
the gain still to come, estimated from the observed rate, is below ``cost_atol`` (below), when the
step just taken was (nearly, ``λ ≤ 1e-3``) Gauss-Newton's and its model gain ``L(0) − L(δ)`` is
below ``cost_atol`` (the Newton decrement test: the quadratic model has less than that left to
give, so the step is kept if it lowered the cost and nothing more is tried), or after
``max_steps`` iterations. The decrement test is what ends a warm-started solve: from the previous
step's trajectory a hallway solve reached gains ``0.47, 2e-4, 4e-7, 1e-8, 1e-10`` nats and used to
take one more iterate to see the relative test pass. (The estimators' smoother steps pass a looser
``cost_atol`` before a scenario's last step, :class:`~hybridslam.estimators.smoothing.Full`'s
``step_atol``: the second of those iterates ends such a solve.)

**Linear convergence.** Gauss-Newton converges quadratically only on zero-residual problems. The
viewpoint-dependent semantic factors at ``alpha = 0.5`` (Eq. 18) are not: their second-order term,
which Gauss-Newton leaves out, is about a third of the Hessian in some direction, and the cost then
falls by a constant factor ``r ≈ 1/3`` per iterate (measured on the default study's tracks), so a
relative test of ``1e-12`` takes 15-25 iterates. Accepted steps with gains ``a_{n-1}, a_n`` give
the rate ``r_n = a_n / a_{n-1}``; when the rate is steady (``r_n`` in ``[0.05, 0.9]`` and within a
factor 2 of ``r_{n-1}``: linear convergence, not the collapsing rates of a quadratic endgame or of a
shrinking damping, which the relative test handles), the gain still to come is the geometric
series ``a_n r_n / (1 − r_n)``, and the solve stops when that is below ``cost_atol`` (``1e-9``
nats: the mode is then within ``√(2·1e-9) ≈ 5e-5`` standard deviations of the optimum) while
``λ ≤ 1`` (a step at least half Gauss-Newton's).

**Why not optimistix.** ``optx.AbstractGaussNewton`` hands its descent the Jacobian as a lineax
operator of the flattened residual function (``jax.linearize`` of the whole residual vector) and
the descent's ``query`` gets no ``args``. A structured descent would have to carry the graph
inside the solver object and re-linearize it blockwise next to optimistix's own linearization,
and the trust-region search's predicted reduction would go through the full-residual JVP again.
The hand-written ``lax.while_loop`` linearizes once per iteration, shares its blocks with
:func:`marginal` and :func:`marginalize_first`, and still reports an ``optx.RESULTS``.

**Inactive variables** (``pose_active``, ``object_active``; padded slots) carry no factors; their
rows of ``H`` become the identity and their gradient zero, so they stay exactly at their initial
value and every factorization stays finite.

**Derivatives.** :func:`solve` is differentiable (``jax.grad``, ``jax.jacfwd``, ``jax.vmap`` of
them) with respect to every floating-point input of the graph: odometry, measurements, noise
square roots, prior, candidate weights. Not through the ``lax.while_loop`` (reverse mode cannot
go through one, and the iterations are not the function): the solution ``y*`` satisfies
``g(y*, θ) = Jᵀr = 0``, so by the implicit function theorem ``(∂g/∂y) ẏ = −(∂g/∂θ) θ̇``
(a ``jax.custom_jvp`` rule, :func:`_solve_jvp`; optimistix's ``ImplicitAdjoint`` does the same for
its own solvers). ``∂g/∂y`` is the exact Hessian, applied by forward-mode products, and the system
is solved by conjugate gradients (``lineax``) preconditioned with the solution's own Gauss-Newton
factorization, the same structured elimination as a step: the two differ only by the residuals'
second-order terms, so a few iterations suffice. The solution's linearization, which
:func:`marginal` turns into the covariance, is differentiated at ``(y*, θ)`` with ``ẏ``, so the
smoothed marginals have exact derivatives too. Exact at the optimum; a solve stopped early (the
estimators' loose tolerance before a scenario's last step) gives the derivative at the point it
stopped. Discrete choices (the max-mixture's active components) are held fixed. Costs nothing
unless differentiated.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree

from ..models import geometry, se2
from ..models.measurement import SensorModel, detection_residual
from ..models.motion import odometry_residual
from . import buckets
from .update import GN_TOLERANCE, wrap_angles

Mode = Literal["sum", "max"]
Method = Literal["auto", "poses-first", "objects-first", "dense"]

_LOG_2PI = math.log(2.0 * math.pi)
SMALL_POSE_SYSTEM = 16  # poses; up to it a dense 3P pose system beats the tridiagonal scan (resolve_method)
_DAMPING_RANGE = (1e-6, 1e32)  # Marquardt's diag(H), clipped like Ceres' min/max_lm_diagonal
_LAMBDA_RANGE = (1e-15, 1e15)
_DECREMENT_LAMBDA = 1e-3  # damping below which a step's model gain stands for Gauss-Newton's
_IMPLICIT_MAXITER = 50  # conjugate-gradient iterations of a derivative (a few suffice: preconditioned)
_IMPLICIT_RTOL, _IMPLICIT_ATOL = 1e-12, 1e-14  # its tolerance, per entry of the tangent


# --------------------------------------------------------------------------------------------
# Residual functions
# --------------------------------------------------------------------------------------------


class DetectionData(eqx.Module):
    """Per-factor data of detection factors (leading axis ``F``; one factor's slice has none).

    ``geo``: measured ``[range (m), bearing (rad)]``; ``scores``: classifier scores ``(M,)``;
    ``cls``: the class hypothesis of each candidate ``(G,)`` (the candidate object's class).
    """

    geo: Float[Array, "*F 2"]
    scores: Float[Array, "*F M"]
    cls: Int[Array, "*F G"]


class SensorResidual(eqx.Module):
    """``residual_fn`` of the library's detection factor (Eq. 10): ``[r_geo, r_sem[c]]``, ``2 + M``.

    Wraps :func:`~hybridslam.measurement.detection_residual` with the candidate's class
    ``data.cls[g]``; ``data`` is one factor's :class:`DetectionData`.
    """

    sensor: SensorModel

    def __call__(
        self, x: se2.Pose, obj: se2.Pose, data: DetectionData, g: Int[Array, ""]
    ) -> tuple[Float[Array, " R"], Float[Array, ""]]:
        pick = jnp.arange(data.cls.shape[0]) == g  # one-hot select: elementwise, no gather
        c = jnp.sum(jnp.where(pick, data.cls, 0))
        return detection_residual(self.sensor, x, obj, data.geo, data.scores, c)


class RangeBearingResidual(eqx.Module):
    """Geometric-only ``residual_fn``: ``W (z − h(x, o))`` with the bearing wrapped, ``(2,)``.

    ``W`` is the square-root information of ``[range, bearing]`` (``Σ_v⁻¹ = WᵀW``); ``data`` is
    one factor's measured ``[range (m), bearing (rad)]``. The factor the filters' Gauss-Newton
    uses (semantics enter their association weights only).
    """

    sqrt_info: Float[Array, "2 2"]

    def __call__(
        self, x: se2.Pose, obj: se2.Pose, data: Float[Array, "2"], g: Int[Array, ""]
    ) -> tuple[Float[Array, "2"], Float[Array, ""]]:
        del g
        d = geometry.geometric_residual(data, geometry.range_bearing(x, obj))
        r = jnp.sum(self.sqrt_info * d[None, :], axis=-1)
        log_norm = jnp.log(jnp.abs(jnp.linalg.det(self.sqrt_info))) - _LOG_2PI
        return r, log_norm


def _as_pytree(fn: Callable) -> Callable:
    """Functions become ``jax.tree_util.Partial`` (a pytree whose function is static), so a graph
    holding a plain function can cross ``jax.jit``; modules keep their arrays traced."""
    if isinstance(fn, (eqx.Module, jax.tree_util.Partial)):
        return fn
    return jax.tree_util.Partial(fn)


# --------------------------------------------------------------------------------------------
# The factor graph
# --------------------------------------------------------------------------------------------


class FactorGraph(eqx.Module):
    """The factors of one smoothing problem over ``P`` poses and ``N`` objects (static shapes).

    Fields (``D₀ = 3 + 3N``; ``F`` measurement factors with ``G`` candidates each):

    * ``prior_mean (D₀,)``, ``prior_sqrt_info (D₀, D₀)``: Gaussian prior on ``[x_0, o_0..o_{N-1}]``,
      residual ``R (y₀ ⊖ μ)`` (every third entry, a heading, wrapped), ``Λ = RᵀR``. Uncreated
      objects should carry an uncoupled block (the solver masks them anyway). ``None`` if
      ``prior_info`` is given: the prior is then ``½ dᵀΛd`` with ``d = y₀ ⊖ μ``, the same function
      without a square root (a fixed-lag window's marginalized prior: no factor to carry).
    * ``odometry (P-1, 3)``, ``odometry_active (P-1,)``, ``motion_sqrt_info (3, 3)``: factor ``i``
      (row ``i-1``) between ``x_{i-1}`` and ``x_i``, residual ``W odometry_fn(x_{i-1}, x_i, u_i)``.
    * ``meas_pose (F,)``, ``meas_objects (F, G)``: the pose and the candidate objects of each
      measurement factor (indices of padded candidates are clipped; give them weight ``-inf``).
    * ``meas_log_weight (F, G)``: ``log w_fg`` (``-inf``: no such candidate);
      ``meas_null_log_weight (F,)``: the null component (``-inf``: none; ``"max"`` mode only).
      A factor with no finite weight contributes nothing.
    * ``meas_data``: a pytree with leading axis ``F`` (e.g. :class:`DetectionData`).
    * ``pose_active (P,)``, ``object_active (N,)``: inactive variables have no factors and keep
      their initial value.
    * ``residual_fn(x, o, data_f, g) -> (r (R,), log_norm ())``: whitened residual and log
      normalizer of candidate ``g`` (an ``eqx.Module`` such as :class:`SensorResidual`, or a
      function, which is wrapped in ``jax.tree_util.Partial``: a new function object recompiles).
    * ``odometry_fn(x_prev, x, u) -> (3,)``: unwhitened between-residual (default
      :func:`~hybridslam.motion.odometry_residual`; tests swap in a linear one).
    * ``mode``: ``"sum"`` or ``"max"`` (static), see the module docstring.
    * ``prior_info (D₀, D₀)``, optional: ``Λ = RᵀR`` of ``prior_sqrt_info``, if the caller has it
      (required without ``prior_sqrt_info``).
      A run's prior is constant, so its smoothers form this ``O(N³)`` product once
      (:class:`~hybridslam.estimators.smoothing.DataLog`) instead of once per step.
    * ``independent_objects`` (static): the caller promises that the prior couples no two objects
      (``Λ`` restricted to the objects is block-diagonal in 3×3 blocks; ``x_0`` may be coupled to
      them). A measurement factor touches one object, so the object part ``C`` of ``H`` is then
      block-diagonal too and the objects-first elimination inverts it block by block
      (:func:`solve_normal`, :func:`marginal`). :func:`~hybridslam.estimators.smoothing.graph`
      sets it: a run's prior is the scenario's, block-diagonal. A fixed-lag window's
      marginalized prior couples the map, so its graphs do not.
    """

    prior_mean: Float[Array, " D0"]
    prior_sqrt_info: Float[Array, "D0 D0"] | None
    odometry: Float[Array, "P1 3"]
    odometry_active: Bool[Array, " P1"]
    motion_sqrt_info: Float[Array, "3 3"]
    meas_pose: Int[Array, " F"]
    meas_objects: Int[Array, "F G"]
    meas_log_weight: Float[Array, "F G"]
    meas_null_log_weight: Float[Array, " F"]
    meas_data: PyTree
    pose_active: Bool[Array, " P"]
    object_active: Bool[Array, " N"]
    residual_fn: Callable = eqx.field(converter=_as_pytree)
    odometry_fn: Callable = eqx.field(default=odometry_residual, converter=_as_pytree)
    mode: Mode = eqx.field(default="sum", static=True)
    prior_info: Float[Array, "D0 D0"] | None = None
    independent_objects: bool = eqx.field(default=False, static=True)

    @property
    def num_poses(self) -> int:
        return self.pose_active.shape[-1]

    @property
    def num_objects(self) -> int:
        return self.object_active.shape[-1]


def check_shapes(graph: FactorGraph, poses: Float[Array, "P 3"], objects: Float[Array, "N 3"]) -> None:
    """Raise ``ValueError`` naming the first field whose shape disagrees (trace time, unbatched)."""
    if graph.mode not in ("sum", "max"):
        raise ValueError(f"FactorGraph.mode: expected 'sum' or 'max', got {graph.mode!r}")
    p, n = graph.pose_active.shape[0], graph.object_active.shape[0]
    f, g = graph.meas_objects.shape if graph.meas_objects.ndim == 2 else (-1, -1)
    expected = {
        "poses": ((p, 3), poses.shape),
        "objects": ((n, 3), objects.shape),
        "prior_mean": ((3 + 3 * n,), graph.prior_mean.shape),
        "odometry": ((p - 1, 3), graph.odometry.shape),
        "odometry_active": ((p - 1,), graph.odometry_active.shape),
        "motion_sqrt_info": ((3, 3), graph.motion_sqrt_info.shape),
        "meas_pose": ((f,), graph.meas_pose.shape),
        "meas_objects": ((f, g), graph.meas_objects.shape),
        "meas_log_weight": ((f, g), graph.meas_log_weight.shape),
        "meas_null_log_weight": ((f,), graph.meas_null_log_weight.shape),
    }
    if graph.prior_sqrt_info is None and graph.prior_info is None:
        raise ValueError("FactorGraph.prior_sqrt_info: None needs prior_info (the prior's information Λ)")
    if graph.prior_sqrt_info is not None:
        expected["prior_sqrt_info"] = ((3 + 3 * n, 3 + 3 * n), graph.prior_sqrt_info.shape)
    if graph.prior_info is not None:
        expected["prior_info"] = ((3 + 3 * n, 3 + 3 * n), graph.prior_info.shape)
    for name, (want, got) in expected.items():
        if tuple(want) != tuple(got):
            raise ValueError(f"FactorGraph.{name}: expected shape {tuple(want)}, got {tuple(got)}")
    if p < 2:
        raise ValueError(f"FactorGraph.pose_active: at least 2 poses are needed, got {p}")
    for path, leaf in jax.tree_util.tree_leaves_with_path(graph.meas_data):
        if jnp.ndim(leaf) < 1 or jnp.shape(leaf)[0] != f:
            name = jax.tree_util.keystr(path)
            raise ValueError(f"FactorGraph.meas_data{name}: expected leading axis {f}, got shape {jnp.shape(leaf)}")


# --------------------------------------------------------------------------------------------
# Linearization: H = JᵀJ and g = Jᵀr in blocks
# --------------------------------------------------------------------------------------------


class Linearization(eqx.Module):
    """The Gauss-Newton normal equations ``H δ = −g`` at one iterate, in blocks, and its cost.

    ``H = [[A, B], [Bᵀ, C]]`` over ``[x_0..x_{P-1}, o_0..o_{N-1}]``: ``A`` block tridiagonal with
    ``pose_diag[i] = A[i, i]`` and ``pose_off[i] = A[i, i+1]``; ``pose_object[i] = B[i]`` (rows of
    pose ``i``); ``object = C``, dense ``(3N, 3N)``, or its diagonal 3×3 blocks ``(N, 3, 3)`` when
    ``object_blocks`` (the graph's ``independent_objects``: ``C`` is then block-diagonal, and
    forming, damping and inverting it block by block is ``O(N)``; :meth:`object_dense` gives it
    dense either way). ``cost = ½‖r‖²`` (in ``"max"`` mode plus each factor's constant
    ``κ_g* − min_g κ_g``, ``κ_g = −log η_g − log w_g``: the negative log posterior up to a constant,
    so costs compare across a switch of component). ``active[f]``: the component of factor ``f``
    with the least cost (the max-mixture's active one): ``0..G-1``, ``G`` the null, ``-1`` none.
    """

    pose_diag: Float[Array, "P 3 3"]
    pose_off: Float[Array, "P1 3 3"]
    pose_object: Float[Array, "P 3 N3"]
    object: Float[Array, "N3 N3"] | Float[Array, "N 3 3"]  # dense, or diagonal blocks (object_blocks)
    grad_pose: Float[Array, "P 3"]
    grad_object: Float[Array, " N3"]
    cost: Float[Array, ""]
    active: Int[Array, " F"]
    object_blocks: bool = eqx.field(default=False, static=True)
    # The last active pose + 1 and object + 1 (padded slots after them are inactive): the solves work
    # on those prefixes at a bucketed size (buckets.py). None: every slot.
    live_poses: Int[Array, ""] | None = None
    live_objects: Int[Array, ""] | None = None

    def dense(self) -> tuple[Float[Array, "D D"], Float[Array, " D"]]:
        """The full ``H (3P+3N, 3P+3N)`` and ``g`` (reference solver and tests)."""
        p = self.pose_diag.shape[0]
        b = self.pose_object.reshape(3 * p, -1)
        h = jnp.block([[_tridiagonal_dense(self.pose_diag, self.pose_off), b], [b.T, self.object_dense()]])
        return h, jnp.concatenate([self.grad_pose.reshape(-1), self.grad_object])

    def head(self, poses: int, objects: int) -> Linearization:
        """The blocks of the first ``poses`` poses and ``objects`` objects: the same solution on them
        when the slots after them are inactive (identity rows, no coupling, zero gradient), as
        ``live_poses`` and ``live_objects`` say."""
        n3 = 3 * objects
        obj = self.object[:objects] if self.object_blocks else self.object[:n3, :n3]
        return dataclasses.replace(
            self, pose_diag=self.pose_diag[:poses], pose_off=self.pose_off[: poses - 1],
            pose_object=self.pose_object[:poses, :, :n3], object=obj, grad_pose=self.grad_pose[:poses],
            grad_object=self.grad_object[:n3])

    def buckets(self) -> tuple[tuple[tuple[int, int], ...], tuple[Int[Array, ""], Int[Array, ""]]]:
        """The (poses, objects) sizes the solves are compiled for, and the live counts that pick one."""
        p, n = self.pose_diag.shape[0], self.grad_object.shape[0] // 3
        if self.live_poses is None or self.live_objects is None:
            return ((p, n),), (jnp.asarray(p), jnp.asarray(n))
        return buckets.bucket_sizes(p, n), (self.live_poses, self.live_objects)  # type: ignore[return-value]

    def object_dense(self) -> Float[Array, "N3 N3"]:
        """``C`` as a dense ``(3N, 3N)`` matrix."""
        return _block_diag(self.object) if self.object_blocks else self.object

    def _object_diagonal(self) -> Float[Array, " N3"]:
        if self.object_blocks:
            return jnp.diagonal(self.object, axis1=-2, axis2=-1).reshape(-1)
        return jnp.diagonal(self.object)

    def damped(self, lam: Float[Array, ""]) -> Linearization:
        """``H + λD`` with Marquardt's ``D = diag(H)`` clipped to ``_DAMPING_RANGE``."""
        eye = jnp.eye(3, dtype=self.pose_diag.dtype)
        dp = jnp.clip(jnp.diagonal(self.pose_diag, axis1=-2, axis2=-1), *_DAMPING_RANGE)
        do = jnp.clip(self._object_diagonal(), *_DAMPING_RANGE)
        pose_diag = self.pose_diag + lam * dp[..., None] * eye[None]
        if self.object_blocks:
            obj = self.object + lam * do.reshape(-1, 3)[..., None] * eye[None]
        else:
            i = jnp.arange(do.shape[0])
            obj = self.object.at[i, i].add(lam * do)
        return eqx.tree_at(lambda s: (s.pose_diag, s.object), self, (pose_diag, obj))

    def damping_norm(self, dp: Float[Array, "P 3"], do: Float[Array, " N3"]) -> Float[Array, ""]:
        """``δᵀDδ`` with the same ``D`` as :meth:`damped`."""
        wp = jnp.clip(jnp.diagonal(self.pose_diag, axis1=-2, axis2=-1), *_DAMPING_RANGE)
        wo = jnp.clip(self._object_diagonal(), *_DAMPING_RANGE)
        return jnp.sum(wp * dp**2) + jnp.sum(wo * do**2)


def _outer(j: Float[Array, "*B R a"], k: Float[Array, "*B R b"]) -> Float[Array, "*B a b"]:
    """``jᵀk`` over the residual axis, as a broadcast sum (tiny dots batch poorly on CPU)."""
    return jnp.sum(j[..., :, :, None] * k[..., :, None, :], axis=-3)


def _prior_terms(graph: FactorGraph, poses, objects):
    """Prior residual ``R (y₀ ⊖ μ)``: its cost and gradient ``Rᵀr`` over ``[x_0, objects]``
    (``½ dᵀΛd`` and ``Λd`` from ``prior_info`` where the graph has no ``R``).

    Inactive entries of ``y₀ ⊖ μ`` are zeroed: an uncreated object contributes nothing, and cost,
    gradient and the masked ``Λ`` of :func:`prior_information` describe the same function.
    """
    d = wrap_angles(jnp.concatenate([poses[0], objects.reshape(-1)]) - graph.prior_mean)
    d = jnp.where(_prior_active(graph), d, 0.0)
    sqrt_info, info = graph.prior_sqrt_info, graph.prior_info
    if sqrt_info is None:
        assert info is not None  # check_shapes: one of the two is given
        grad = info @ d
        return 0.5 * jnp.dot(d, grad), grad
    r = sqrt_info @ d
    return 0.5 * jnp.sum(r**2), sqrt_info.T @ r


def _odometry_terms(graph: FactorGraph, poses):
    """Per odometry factor: cost, Jacobians ``(3, 3)`` w.r.t. ``x_{i-1}``, ``x_i`` and gradients."""

    def one(x_prev, x, u):
        def f(z):
            r = graph.motion_sqrt_info @ graph.odometry_fn(z[:3], z[3:], u)
            return r, r

        j, r = jax.jacfwd(f, has_aux=True)(jnp.concatenate([x_prev, x]))
        return r, j

    r, j = jax.vmap(one)(poses[:-1], poses[1:], graph.odometry)
    on = graph.odometry_active & graph.pose_active[:-1] & graph.pose_active[1:]
    r, j = jnp.where(on[:, None], r, 0.0), jnp.where(on[:, None, None], j, 0.0)
    hess = _outer(j, j)  # (P-1, 6, 6)
    grad = jnp.sum(j * r[..., None], axis=-2)  # (P-1, 6)
    return 0.5 * jnp.sum(r**2), hess, grad


def _component_choice(graph: FactorGraph, half_sq, log_norm, valid, live_pose):
    """Active component (``0..G-1``, ``G`` null, ``-1`` none) and the per-factor max-mode cost."""
    g = graph.meas_log_weight.shape[-1]
    kappa = jnp.where(valid, -log_norm - graph.meas_log_weight, jnp.inf)
    null_lw = graph.meas_null_log_weight
    null_valid = (null_lw > -jnp.inf) & live_pose
    kappa_null = jnp.where(null_valid, -null_lw, jnp.inf)
    costs = jnp.concatenate([jnp.where(valid, half_sq + kappa, jnp.inf), kappa_null[:, None]], axis=-1)
    live = jnp.any(valid, axis=-1) | null_valid
    best = jnp.argmin(costs, axis=-1)
    kappa_ref = jnp.minimum(jnp.min(kappa, axis=-1), kappa_null)
    cost = jnp.where(live, jnp.min(costs, axis=-1) - jnp.where(live, kappa_ref, 0.0), 0.0)
    return jnp.where(live, best, -1), jnp.where(best[:, None] == jnp.arange(g)[None, :], valid, False), cost


def _measurement_terms(graph: FactorGraph, poses, objects):
    """Per (factor, candidate): weighted 6×6 blocks ``s JᵀJ``, gradients ``s Jᵀr`` over ``[x, o]``."""
    p, n = poses.shape[0], objects.shape[0]
    g = graph.meas_objects.shape[-1]
    pose_idx = jnp.clip(graph.meas_pose, 0, p - 1)
    obj_idx = jnp.clip(graph.meas_objects, 0, n - 1)

    def one(x, o, data, cand):
        def f(z):
            r, log_norm = graph.residual_fn(z[:3], z[3:], data, cand)
            return r, (r, log_norm)

        j, (r, log_norm) = jax.jacfwd(f, has_aux=True)(jnp.concatenate([x, o]))
        return r, log_norm, j

    per_candidate = jax.vmap(one, (None, 0, None, 0))
    r, log_norm, j = jax.vmap(per_candidate, (0, 0, 0, None))(
        poses[pose_idx], objects[obj_idx], graph.meas_data, jnp.arange(g)
    )
    lw = graph.meas_log_weight
    # A candidate on an inactive object (or a factor on an inactive pose) does not exist.
    live_pose = graph.pose_active[pose_idx] & (graph.meas_pose >= 0) & (graph.meas_pose < p)
    valid = (lw > -jnp.inf) & graph.object_active[obj_idx] & live_pose[:, None]
    half_sq = 0.5 * jnp.sum(jnp.where(valid[..., None], r, 0.0) ** 2, axis=-1)
    active, chosen, max_cost = _component_choice(graph, half_sq, log_norm, valid, live_pose)
    if graph.mode == "max":
        use, scale, cost = chosen, jnp.ones_like(lw), jnp.sum(max_cost)
    else:
        use = valid
        scale = jnp.exp(jnp.where(valid, lw, 0.0))
        cost = jnp.sum(jnp.where(valid, scale * half_sq, 0.0))
    # `where`, not a product with a zero weight: a padded slot's residual may be NaN.
    r = jnp.where(use[..., None], r, 0.0)
    j = jnp.where(use[..., None, None], j, 0.0) * jnp.sqrt(scale)[..., None, None]
    hess = _outer(j, j)  # (F, G, 6, 6)
    grad = jnp.sum(j * (jnp.sqrt(scale)[..., None] * r)[..., None], axis=-2)  # (F, G, 6)
    return cost, hess, grad, pose_idx, obj_idx, active


def _scatter_measurements(hess, grad, pose_idx, obj_idx, p: int, n: int):
    """Scatter-add per-factor blocks into pose diagonal ``(P,3,3)``, object diagonal ``(N,3,3)``,
    pose-object ``(P,3,N,3)`` blocks and the pose / object gradients."""
    dtype = hess.dtype
    pp = jnp.zeros((p, 3, 3), dtype).at[pose_idx].add(jnp.sum(hess[..., :3, :3], axis=1))
    oo = jnp.zeros((n, 3, 3), dtype).at[obj_idx].add(hess[..., 3:, 3:])
    rows = jnp.broadcast_to(pose_idx[:, None], obj_idx.shape)
    po = jnp.zeros((p, 3, n, 3), dtype).at[rows, :, obj_idx, :].add(hess[..., :3, 3:])
    gp = jnp.zeros((p, 3), dtype).at[pose_idx].add(jnp.sum(grad[..., :3], axis=1))
    go = jnp.zeros((n, 3), dtype).at[obj_idx].add(grad[..., 3:])
    return pp, oo, po, gp, go


def _diagonal_blocks(m: Float[Array, "N3 N3"]) -> Float[Array, "N 3 3"]:
    """The diagonal 3×3 blocks of ``m``."""
    n = m.shape[0] // 3
    i = jnp.arange(n)
    return m.reshape(n, 3, n, 3)[i, :, i, :]


def _block_diag(blocks: Float[Array, "N 3 3"]) -> Float[Array, "N3 N3"]:
    n = blocks.shape[0]
    eye = jnp.eye(n, dtype=blocks.dtype)
    return (blocks[:, :, None, :] * eye[:, None, :, None]).reshape(3 * n, 3 * n)


def _prior_active(graph: FactorGraph) -> Bool[Array, " D0"]:
    """Which entries of ``[x_0, objects]`` are active."""
    return jnp.concatenate([jnp.repeat(graph.pose_active[:1], 3), jnp.repeat(graph.object_active, 3)])


def prior_information(graph: FactorGraph) -> Float[Array, "D0 D0"]:
    """``Λ = RᵀR`` of the prior with the rows and columns of inactive variables zeroed.

    Constant, so :func:`solve` forms it once, outside the loop (it is the one ``O(N³)`` product),
    and not at all if the graph carries it (``FactorGraph.prior_info``).
    """
    on = _prior_active(graph)
    info, sqrt_info = graph.prior_info, graph.prior_sqrt_info
    if info is None:
        assert sqrt_info is not None  # check_shapes: one of the two is given
        info = sqrt_info.T @ sqrt_info
    return jnp.where(on[:, None] & on[None, :], info, 0.0)


def _identity_for_inactive(lin: Linearization, pose_active, object_active) -> Linearization:
    """Identity diagonal blocks and zero gradient for inactive variables, so they stay put and every
    factorization stays finite. Their factors were already dropped (and Λ masked), so their rows
    hold nothing else: this costs ``O(P + N)``, not a pass over ``H``."""
    eye = jnp.eye(3, dtype=lin.pose_diag.dtype)
    oa = jnp.repeat(object_active, 3)
    n3 = oa.shape[0]
    if lin.object_blocks:
        obj = lin.object + jnp.where(object_active[:, None, None], 0.0, eye[None])
    else:
        obj = lin.object.at[jnp.arange(n3), jnp.arange(n3)].add(jnp.where(oa, 0.0, 1.0))
    return eqx.tree_at(
        lambda s: (s.pose_diag, s.object, s.grad_pose, s.grad_object),
        lin,
        (lin.pose_diag + jnp.where(pose_active[:, None, None], 0.0, eye[None]), obj,
         jnp.where(pose_active[:, None], lin.grad_pose, 0.0), jnp.where(oa, lin.grad_object, 0.0)),
    )


def linearize(
    graph: FactorGraph,
    poses: Float[Array, "P 3"],
    objects: Float[Array, "N 3"],
    prior_info: Float[Array, "D0 D0"] | None = None,
) -> Linearization:
    """The blocks of ``H = JᵀJ``, ``g = Jᵀr`` and the cost ``½‖r‖²`` at ``(poses, objects)``.

    Each factor's Jacobian comes from ``jax.jacfwd`` on its own variables (3 or 6 columns), vmapped
    over factors; the prior's is ``R``, so its block is the constant ``Λ = RᵀR`` (``prior_info``,
    computed here if not given). ``log η`` is treated as a constant (no Gauss-Newton term): with the
    library's classifiers it does not depend on the state.
    """
    check_shapes(graph, poses, objects)
    p, n = poses.shape[0], objects.shape[0]
    info = prior_information(graph) if prior_info is None else prior_info
    prior_cost, prior_grad = _prior_terms(graph, poses, objects)
    odo_cost, odo_h, odo_g = _odometry_terms(graph, poses)
    meas_cost, h, g, pose_idx, obj_idx, active = _measurement_terms(graph, poses, objects)
    pp, oo, po, gp, go = _scatter_measurements(h, g, pose_idx, obj_idx, p, n)

    zero = jnp.zeros((1, 3, 3), pp.dtype)
    pose_diag = pp + jnp.concatenate([odo_h[:, :3, :3], zero]) + jnp.concatenate([zero, odo_h[:, 3:, 3:]])
    pose_diag = pose_diag.at[0].add(info[:3, :3])
    pose_object = po.reshape(p, 3, 3 * n).at[0].add(info[:3, 3:])
    zero_g = jnp.zeros((1, 3), gp.dtype)
    grad_pose = gp + jnp.concatenate([odo_g[:, :3], zero_g]) + jnp.concatenate([zero_g, odo_g[:, 3:]])
    lin = Linearization(
        pose_diag=pose_diag,
        pose_off=odo_h[:, :3, 3:],
        pose_object=pose_object,
        object=_diagonal_blocks(info[3:, 3:]) + oo if graph.independent_objects else info[3:, 3:] + _block_diag(oo),
        grad_pose=grad_pose.at[0].add(prior_grad[:3]),
        grad_object=go.reshape(-1) + prior_grad[3:],
        cost=prior_cost + odo_cost + meas_cost,
        active=active,
        object_blocks=graph.independent_objects,
        live_poses=jnp.max(jnp.where(graph.pose_active, jnp.arange(1, p + 1), 0)),
        live_objects=jnp.max(jnp.where(graph.object_active, jnp.arange(1, n + 1), 0), initial=0),
    )
    return _identity_for_inactive(lin, graph.pose_active, graph.object_active)


# --------------------------------------------------------------------------------------------
# Structured linear algebra
# --------------------------------------------------------------------------------------------


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


def resolve_method(method: Method, num_poses: int, num_objects: int, object_blocks: bool = False) -> Method:
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
    if method != "auto":
        return method
    small = object_blocks and num_poses <= SMALL_POSE_SYSTEM
    return "objects-first" if num_objects > num_poses or small else "poses-first"


def solve_normal(
    lin: Linearization, method: Method = "auto"
) -> tuple[Float[Array, "P 3"], Float[Array, "N 3"]]:
    """The Gauss-Newton step ``δ = −H⁻¹ g`` of ``lin`` (damp it first with :meth:`~Linearization.damped`)."""
    p, n = lin.pose_diag.shape[0], lin.grad_object.shape[0] // 3
    method = resolve_method(method, p, n, lin.object_blocks)
    solvers = {"poses-first": _solve_poses_first, "objects-first": _solve_objects_first, "dense": _solve_dense}
    if method not in solvers:
        raise ValueError(f"method: expected one of {sorted(solvers)} or 'auto', got {method!r}")
    if method == "dense":
        d_p, d_o = solvers[method](lin)
        return d_p, d_o.reshape(n, 3)

    def on_head(size: tuple[int, int], lin: Linearization):
        d_p, d_o = solvers[method](lin.head(*size))
        # The inactive slots left out: δ = 0.
        return (jnp.concatenate([d_p, jnp.zeros((p - size[0], 3), d_p.dtype)]),
                jnp.concatenate([d_o, jnp.zeros(3 * (n - size[1]), d_o.dtype)]))

    sizes, live = lin.buckets()
    d_p, d_o = buckets.by_bucket(sizes, live, on_head, lin)
    return d_p, d_o.reshape(n, 3)


# --------------------------------------------------------------------------------------------
# Levenberg-Marquardt
# --------------------------------------------------------------------------------------------


class Solution(eqx.Module):
    """The smoothed trajectory and map of one graph.

    ``poses (P, 3)``, ``objects (N, 3)`` (headings wrapped); ``cost``: ``½‖r‖²`` at the solution
    (see :class:`Linearization` for the max-mode constant); ``steps``: iterations taken (linear
    solves); ``result``: ``optx.RESULTS.successful`` or ``nonlinear_max_steps_reached`` /
    ``nonfinite`` (kept, not thrown, so a vmapped batch shows which component failed); ``active
    (F,)``: each factor's active component at the solution (``G`` the null, ``-1`` none; in
    ``"sum"`` mode the likeliest, for information); ``history (max_steps,)``: the cost of the
    current iterate after each iteration (``nan`` after the last), non-increasing;
    ``linearization``: the blocks of ``H`` and ``g`` at the solution (what :func:`marginal` needs).
    """

    poses: Float[Array, "P 3"]
    objects: Float[Array, "N 3"]
    cost: Float[Array, ""]
    steps: Int[Array, ""]
    result: optx.RESULTS
    active: Int[Array, " F"]
    history: Float[Array, " S"]
    linearization: Linearization

    @property
    def converged(self) -> Bool[Array, ""]:
        return jnp.asarray(self.result == optx.RESULTS.successful)


class _LMState(eqx.Module):
    started: Bool[Array, ""]  # False until the first iteration has linearized at the start
    poses: Float[Array, "P 3"]
    objects: Float[Array, "N 3"]
    lin: Linearization
    lam: Float[Array, ""]
    nu: Float[Array, ""]
    steps: Int[Array, ""]
    done: Bool[Array, ""]
    result: optx.RESULTS
    history: Float[Array, " S"]
    gain: Float[Array, ""]  # the cost decrease of the last accepted step (0 before the first)
    rate: Float[Array, ""]  # its ratio to the one before (0 before the second)


def retract(y: Float[Array, "K 3"], delta: Float[Array, "K 3"], active: Bool[Array, " K"]) -> Float[Array, "K 3"]:
    """``y ⊕ δ``: vector addition, heading wrapped; inactive rows are returned untouched."""
    z = y + delta
    z = z.at[:, 2].set(se2.wrap(z[:, 2]))
    return jnp.where(active[:, None], z, y)


def _nielsen(lam, nu, accept, rho):
    """Nielsen's λ update (Madsen, Nielsen & Tingleff 2004, Eq. 2.21)."""
    shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
    lam = jnp.where(accept, lam * shrink, lam * nu)
    return jnp.clip(lam, *_LAMBDA_RANGE), jnp.where(accept, 2.0, 2.0 * nu)


def _unlinearized(graph: FactorGraph, p: int, n: int, dtype) -> Linearization:
    """An identity system with cost ``+inf`` in place of the start's linearization: :func:`solve`'s
    first iteration takes no step (``δ = 0``, the solve skipped) and linearizes at the start. One
    :func:`linearize` in the loop instead of one before it and one in it: the program holds it once
    (0.7 s less XLA compilation of `hybridslam run` on a paper-setup file, 2026-11-26)."""
    eye = jnp.eye(3, dtype=dtype)
    obj = jnp.broadcast_to(eye, (n, 3, 3)) if graph.independent_objects else jnp.eye(3 * n, dtype=dtype)
    index = jnp.result_type(int)  # what linearize's int fields are (int64 under x64)
    return Linearization(
        pose_diag=jnp.broadcast_to(eye, (p, 3, 3)), pose_off=jnp.zeros((p - 1, 3, 3), dtype),
        pose_object=jnp.zeros((p, 3, 3 * n), dtype), object=obj, grad_pose=jnp.zeros((p, 3), dtype),
        grad_object=jnp.zeros((3 * n,), dtype), cost=jnp.asarray(jnp.inf, dtype),
        active=jnp.full(graph.meas_pose.shape, -1, index), object_blocks=graph.independent_objects,
        live_poses=jnp.asarray(p, index), live_objects=jnp.asarray(n, index),
    )


def _lm_step(graph, info, method, state_tol, cost_rtol, cost_atol, max_steps, s: _LMState) -> _LMState:
    lin = s.lin.damped(s.lam)
    # The first iteration has no step to solve for; a solve costs what a linearization does (the
    # MRCLAM graph's 201-pose chain). Every member of a vmapped batch starts together, so "any member
    # unstarted" (batch_max: unbatched) is a real branch, not a select that runs both sides.
    first = buckets.batch_max(jnp.asarray(~s.started, jnp.int32)) > 0
    d_p, d_o = jax.lax.cond(first, lambda: (jnp.zeros_like(s.poses), jnp.zeros_like(s.objects)),
                            lambda: solve_normal(lin, method))
    small = jnp.maximum(jnp.max(jnp.abs(d_p)), jnp.max(jnp.abs(d_o), initial=0.0)) < state_tol
    poses = retract(s.poses, d_p, graph.pose_active)
    objects = retract(s.objects, d_o, graph.object_active)
    new = linearize(graph, poses, objects, info)
    # L(0) − L(δ) = −gᵀδ − ½δᵀHδ = ½(λδᵀDδ − gᵀδ), since (H + λD)δ = −g.
    g_dot = jnp.sum(s.lin.grad_pose * d_p) + jnp.sum(s.lin.grad_object * d_o.reshape(-1))
    predicted = 0.5 * (s.lam * s.lin.damping_norm(d_p, d_o.reshape(-1)) - g_dot)
    actual = s.lin.cost - new.cost
    finite = jnp.isfinite(new.cost)
    # The first iteration linearizes at the start and takes no step (scalars kept below); a
    # non-finite start ends the solve.
    begin = ~s.started
    accept = (finite & (actual > 0)) | begin
    lam, nu = _nielsen(s.lam, s.nu, accept, actual / jnp.where(predicted > 0, predicted, 1.0))
    pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(accept, u, v), a, b)  # noqa: E731
    steps = s.steps + 1
    rate = actual / jnp.where(s.gain > 0, s.gain, jnp.inf)
    to_come = actual * rate / (1.0 - jnp.minimum(rate, 0.9))
    linear = (rate >= 0.05) & (rate <= 0.9) & (rate <= 2.0 * s.rate) & (s.rate <= 2.0 * rate)
    steady = accept & linear & (s.lam <= 1.0) & (to_come <= cost_atol)
    # The Newton decrement: a (nearly) Gauss-Newton step whose model gain is below cost_atol.
    decrement = finite & (s.lam <= _DECREMENT_LAMBDA) & (predicted <= cost_atol)
    converged = small | (accept & (actual <= cost_rtol * jnp.abs(s.lin.cost))) | steady | decrement
    out_of_steps = steps >= max_steps
    result = optx.RESULTS.where(
        converged, optx.RESULTS.successful,
        optx.RESULTS.where(out_of_steps, optx.RESULTS.nonlinear_max_steps_reached, optx.RESULTS.successful),
    )
    result = optx.RESULTS.where(begin, optx.RESULTS.where(finite, optx.RESULTS.successful, optx.RESULTS.nonfinite),
                                result)
    kept = pick((poses, objects, new), (s.poses, s.objects, s.lin))
    before = lambda now, then: jnp.where(begin, then, now)  # noqa: E731
    gained = accept & ~begin
    return _LMState(jnp.asarray(True), *kept, before(lam, s.lam), before(nu, s.nu),  # type: ignore[call-arg]
                    before(steps, s.steps), before(converged | out_of_steps, ~finite), result,
                    before(s.history.at[s.steps].set(kept[2].cost), s.history),
                    jnp.where(gained, actual, s.gain), jnp.where(gained, rate, s.rate))


def solve(
    graph: FactorGraph,
    poses0: Float[Array, "P 3"],
    objects0: Float[Array, "N 3"],
    *,
    max_steps: int = 50,
    method: Method = "auto",
    state_tol: float | Float[Array, ""] = GN_TOLERANCE,
    cost_rtol: float | Float[Array, ""] = 1e-12,
    cost_atol: float | Float[Array, ""] = 1e-9,
    lambda_init: float | Float[Array, ""] = 1e-4,
) -> Solution:
    """Minimize ``½‖r(X, O)‖²`` of ``graph`` from ``(poses0, objects0)`` by Levenberg-Marquardt.

    ``max_steps`` and ``method`` are static (one compile per shape); the tolerances and the initial
    damping ``lambda_init`` (relative to ``diag(H)``: ``1e-4`` is nearly Gauss-Newton when the
    start is good; a bad start costs a few rejected steps) are traced. Works under ``jax.jit`` and
    ``jax.vmap`` (the ``lax.while_loop`` runs until every member of a batch is done; finished
    members stay put). See the module docstring for the algorithm.

    Differentiable in forward and reverse mode with respect to every floating-point input of
    ``graph`` (and ``poses0``, ``objects0`` for the inactive slots, which keep them): by the implicit
    function theorem at the solution, not through the iterations (module docstring, "Derivatives").
    """
    check_shapes(graph, poses0, objects0)
    if max_steps < 0:
        raise ValueError(f"max_steps: expected a non-negative int, got {max_steps}")
    dtype = jnp.result_type(float)
    poses0, objects0 = jnp.asarray(poses0, dtype), jnp.asarray(objects0, dtype)
    if max_steps == 0:
        lin = linearize(graph, poses0, objects0, prior_information(graph))
        result = optx.RESULTS.where(jnp.isfinite(lin.cost), optx.RESULTS.successful, optx.RESULTS.nonfinite)
        return Solution(poses0, objects0, lin.cost, jnp.asarray(0), result, lin.active, jnp.zeros((0,), dtype), lin)
    # The tolerances shape the iterations only: no derivative flows through them.
    settings = jax.tree.map(jax.lax.stop_gradient, (state_tol, cost_rtol, cost_atol, lambda_init))
    return _solve(graph, poses0, objects0, settings, max_steps=max_steps, method=method)


@eqx.filter_custom_jvp
def _solve(graph: FactorGraph, poses0, objects0, settings, *, max_steps: int, method: Method) -> Solution:
    """:func:`solve`'s Levenberg-Marquardt loop (its derivative: :func:`_solve_jvp`)."""
    state_tol, cost_rtol, cost_atol, lambda_init = settings
    dtype = poses0.dtype
    info = prior_information(graph)
    init = _LMState(
        jnp.asarray(False), poses0, objects0, _unlinearized(graph, poses0.shape[0], objects0.shape[0], dtype),
        jnp.asarray(lambda_init, dtype), jnp.asarray(2.0, dtype), jnp.asarray(0), jnp.asarray(False),
        cast(optx.RESULTS, optx.RESULTS.successful),  # an item; its stub says str
        jnp.full((max_steps,), jnp.nan, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype),
    )
    body = lambda s: _lm_step(graph, info, method, state_tol, cost_rtol, cost_atol, max_steps, s)  # noqa: E731
    s = jax.lax.while_loop(lambda s: ~s.done, body, init)
    return Solution(s.poses, s.objects, s.lin.cost, s.steps, s.result, s.lin.active, s.history, s.lin)


def _stationarity(graph: FactorGraph, poses, objects,
                  info=None) -> tuple[Float[Array, "P 3"], Float[Array, "N 3"]]:
    """``g = Jᵀr`` at ``(poses, objects)``: zero at the solution (inactive rows: zero everywhere).
    ``info``: the graph's :func:`prior_information`, if formed already."""
    lin = linearize(graph, poses, objects, prior_information(graph) if info is None else info)
    return lin.grad_pose, lin.grad_object.reshape(objects.shape)


def _zeros_for_none(tangent, like):
    """A symbolic zero tangent (``None``) as an array of zeros."""
    return jnp.zeros_like(like) if tangent is None else tangent


@_solve.def_jvp
def _solve_jvp(primals, tangents, *, max_steps: int, method: Method):
    """The implicit function theorem at the solution ``y*`` of ``g(y, θ) = 0``: the tangent ``ẏ``
    solves ``(∂g/∂y) ẏ = −(∂g/∂θ) θ̇`` on the active rows (``∂g/∂y`` the exact Hessian, by
    forward-mode products; lineax's conjugate gradients, at most ``_IMPLICIT_MAXITER`` iterations,
    preconditioned by the solution's own Gauss-Newton factorization, which differs from the Hessian
    by the residuals' second-order terms only), and the inactive rows keep the start's tangent. The
    solution's linearization (what :func:`marginal` reads) moves with ``(θ̇, ẏ)``. Linear in the
    tangents, so reverse mode transposes it (lineax transposes its solve: the operator is symmetric)."""
    graph, poses0, objects0, settings = primals
    t_graph, t_poses0, t_objects0, _ = tangents
    sol = _solve(graph, poses0, objects0, settings, max_steps=max_steps, method=method)
    y = (sol.poses, sol.objects)
    on = (graph.pose_active[:, None], graph.object_active[:, None])
    mask = lambda v, other: tuple(jnp.where(m, a, b) for m, a, b in zip(on, v, other))  # noqa: E731
    zero = tuple(jnp.zeros_like(a) for a in y)

    _, g_dot = eqx.filter_jvp(lambda g: _stationarity(g, *y), (graph,), (t_graph,))
    start_dot = (_zeros_for_none(t_poses0, sol.poses), _zeros_for_none(t_objects0, sol.objects))
    rhs = mask(tuple(-_zeros_for_none(t, a) for t, a in zip(g_dot, y)), start_dot)

    info = prior_information(graph)  # constant in y: formed once, not in every product

    def hessian(v):
        _, hv = jax.jvp(lambda p, o: _stationarity(graph, p, o, info), y, mask(v, zero))
        return mask(hv, v)

    def gauss_newton(v):
        lin = eqx.tree_at(lambda s: (s.grad_pose, s.grad_object), sol.linearization,
                          (-v[0], -v[1].reshape(-1)))
        return mask(solve_normal(lin, method), v)  # solve_normal returns −H⁻¹g = H⁻¹v

    structure = jax.eval_shape(lambda: rhs)
    spd = (lx.symmetric_tag, lx.positive_semidefinite_tag)
    y_dot = lx.linear_solve(
        lx.FunctionLinearOperator(hessian, structure, spd), rhs,
        lx.CG(rtol=_IMPLICIT_RTOL, atol=_IMPLICIT_ATOL, max_steps=_IMPLICIT_MAXITER),
        options={"preconditioner": lx.FunctionLinearOperator(gauss_newton, structure, spd)}, throw=False,
    ).value
    _, lin_dot = eqx.filter_jvp(lambda g, p, o: linearize(g, p, o, prior_information(g)), (graph, *y),
                                (t_graph, *y_dot))
    # A Solution of tangents, None (zero) where there is none: unflattened, as its fields' types do not hold.
    t_out = eqx.tree_at(lambda s: (s.poses, s.objects, s.cost, s.linearization),
                        jax.tree.map(lambda _: None, sol), (*y_dot, lin_dot.cost, lin_dot),
                        is_leaf=lambda x: x is None)
    return sol, t_out


# --------------------------------------------------------------------------------------------
# Marginals for the filter side and fixed-lag windows
# --------------------------------------------------------------------------------------------


def marginal(
    solution: Solution, k: Int[Array, ""] | int, method: Method = "auto"
) -> tuple[Float[Array, " D0"], Float[Array, "D0 D0"]]:
    """Laplace marginal of ``[x_k, o_0..o_{N-1}]`` (``D₀ = 3 + 3N``): the mean at the solution and
    the matching block of ``H⁻¹`` (Gauss-Newton Hessian), every other pose marginalized.

    ``method="auto"`` eliminates the objects first where :func:`resolve_method` would and ``C`` is
    block-diagonal, else the poses (``"dense"`` takes the poses-first path too). Poses first:
    ``Σ_OO = S⁻¹`` with ``S = C − BᵀA⁻¹B``, ``Σ_kO = −(A⁻¹B)_k S⁻¹``,
    ``Σ_kk = (A⁻¹)_kk + (A⁻¹B)_k S⁻¹ (A⁻¹B)_kᵀ``, with ``(A⁻¹)_kk`` from the same tridiagonal solve
    (three extra right-hand sides ``e_k``). Objects
    first, with ``S_p = A − B C⁻¹ Bᵀ = L Lᵀ``, ``Z = L⁻¹ B C⁻¹`` and ``u = L⁻¹ e_k``:
    ``Σ_OO = C⁻¹ + ZᵀZ``, ``Σ_kO = −uᵀZ``, ``Σ_kk = uᵀu`` (the block inverse of ``H``; only
    ``C⁻¹`` is inverted, blockwise when ``C`` is block-diagonal). ``k`` may be traced. Inactive
    objects get identity covariance, uncorrelated (the filters' uncreated slots). The blocks are
    the solver's own linearization at the solution (``solution.linearization``), not formed again.
    """
    lin = solution.linearization
    p, n3 = lin.pose_diag.shape[0], lin.grad_object.shape[0]
    mean = jnp.concatenate([solution.poses[k], solution.objects.reshape(-1)])
    order = resolve_method(method, p, n3 // 3, lin.object_blocks)  # for the whole graph, whatever the bucket

    def on_head(size: tuple[int, int], lin: Linearization, k: Int[Array, ""] | int) -> Float[Array, "D0 D0"]:
        cov = _marginal_cov(lin.head(*size), k, method, order)
        # The inactive objects left out: identity covariance, uncorrelated (what the whole H gives).
        return jax.scipy.linalg.block_diag(cov, jnp.eye(n3 - 3 * size[1], dtype=cov.dtype))

    sizes, (live_p, live_o) = lin.buckets()
    live = (jnp.maximum(live_p, jnp.asarray(k) + 1), live_o)  # x_k itself must be in the head
    return mean, buckets.by_bucket(sizes, live, on_head, lin, k)


def _marginal_cov(lin: Linearization, k: Int[Array, ""] | int, method: Method, order: Method) -> Float[Array, "D0 D0"]:
    """The covariance of :func:`marginal`, ``x_k`` one of ``lin``'s poses, eliminating in ``order``."""
    p, n3 = lin.pose_diag.shape[0], lin.grad_object.shape[0]
    eye = jnp.eye(3, dtype=lin.pose_diag.dtype)
    # With a dense C, "auto" keeps the poses-first path: inverting C densely buys nothing there.
    if order == "objects-first" and (lin.object_blocks or method == "objects-first"):
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
    else:
        e_k = jnp.where((jnp.arange(p) == k)[:, None, None], eye[None], 0.0)
        pelim = _eliminate_poses(lin, e_k)
        chol_inv = jsl.solve_triangular(pelim.schur_chol, jnp.eye(n3, dtype=eye.dtype), lower=True)
        s_oo = chol_inv.T @ chol_inv  # S⁻¹ = L⁻ᵀL⁻¹, symmetric by construction
        x_k = pelim.a_inv_b[k]  # (A⁻¹B)_k, (3, 3N)
        s_ko = -x_k @ s_oo
        s_kk = pelim.a_inv_extra[k] - s_ko @ x_k.T
    return jnp.block([[0.5 * (s_kk + s_kk.T), s_ko], [s_ko.T, s_oo]])


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
