"""The factor graph of one smoothing problem and its residual functions (the problem of
:mod:`hybridslam.inference.smoother`'s docstring): what :func:`~.linearization.linearize` reads."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PyTree

from ...models import geometry, se2
from ...models.measurement import SensorModel, detection_residual
from ...models.motion import odometry_residual

Mode = Literal["sum", "max"]

_LOG_2PI = math.log(2.0 * math.pi)



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

    @property
    def heading_curvature(self) -> bool:
        """Whether the object's heading enters the residual, through the viewpoint of a
        viewpoint-dependent classifier (its Gauss-Newton curvature then needs the second-order
        term: :func:`~.linearization.linearize`)."""
        classifier = self.sensor.classifier
        return classifier.uses_scores and classifier.viewpoint_dependent

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
    heading_curvature: ClassVar[bool] = False  # range and bearing do not see the object's heading

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
      (:class:`~hybridslam.estimators.smoothers.factors.DataLog`) instead of once per step.
    * ``independent_objects`` (static): the caller promises that the prior couples no two objects
      (``Λ`` restricted to the objects is block-diagonal in 3×3 blocks; ``x_0`` may be coupled to
      them). A measurement factor touches one object, so the object part ``C`` of ``H`` is then
      block-diagonal too and the objects-first elimination inverts it block by block
      (:func:`solve_normal`, :func:`marginal`). :func:`~hybridslam.estimators.smoothers.factors.graph`
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
