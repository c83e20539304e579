"""Linearization of a :class:`~.graph.FactorGraph`: the Gauss-Newton normal equations ``H = JᵀJ``,
``g = Jᵀr`` in blocks (block-tridiagonal poses, pose-object coupling, objects) and the cost, with
each factor's Jacobian by ``jax.jacfwd`` on its own variables (see the package docstring,
"Structure" and "Live prefix")."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .. import buckets
from ..update import wrap_angles
from .blocks import _tridiagonal_dense
from .graph import FactorGraph, check_shapes

_DAMPING_RANGE = (1e-6, 1e32)  # Marquardt's diag(H), clipped like Ceres' min/max_lm_diagonal




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


_OBJECT_HEADING = 5  # the object's heading among a factor's variables [x (3), o (3)]


def _heading_second_order(residual_fn, z, data, cand, r) -> Float[Array, ""]:
    """``Σ_i r_i ∂²r_i/∂θ_o²``: the term of the exact Hessian of ``½‖r‖²`` in the object's heading
    that Gauss-Newton leaves out (Nocedal & Wright, Numerical Optimization, Eq. 10.5: ``∇²f = JᵀJ +
    Σ r_i ∇²r_i``), by forward over forward differentiation along that one coordinate."""
    e = jnp.zeros_like(z).at[_OBJECT_HEADING].set(1.0)
    along = lambda w: residual_fn(w[:3], w[3:], data, cand)[0]  # noqa: E731
    d2 = jax.jvp(lambda w: jax.jvp(along, (w,), (e,))[1], (z,), (e,))[1]
    return jnp.sum(r * d2)


def _measurement_terms(graph: FactorGraph, poses, objects):
    """Per (factor, candidate): weighted 6×6 blocks ``s JᵀJ``, gradients ``s Jᵀr`` over ``[x, o]``.

    Where the object's heading enters the residual (a viewpoint-dependent classifier's semantic
    factor, ``residual_fn.heading_curvature``), its diagonal entry also carries the second-order
    term :func:`_heading_second_order`, where positive. Range and bearing do not observe that
    heading; only the classifier's viewpoint does, through a residual far from linear in it. With
    ``JᵀJ`` alone the curvature can be far too small: on KITTI 0006 with a learned model, 0.75
    against the cost's 50.6 nats/rad², so Gauss-Newton asked for a 1.77 rad turn, Levenberg-Marquardt
    rejected it, and 1520 of the run's smoothings ran out of iterations (none with the term;
    docs/studies/kitti.md). The gradient is unchanged, so the solution is too (where it converges);
    the term only makes the quadratic model, and the Laplace marginal's heading variance at the
    solution, that of the cost itself."""
    p, n = poses.shape[0], objects.shape[0]
    g = graph.meas_objects.shape[-1]
    pose_idx = jnp.clip(graph.meas_pose, 0, p - 1)
    obj_idx = jnp.clip(graph.meas_objects, 0, n - 1)
    curvature = bool(getattr(graph.residual_fn, "heading_curvature", False))

    def one(x, o, data, cand):
        def f(z):
            r, log_norm = graph.residual_fn(z[:3], z[3:], data, cand)
            return r, (r, log_norm)

        z = jnp.concatenate([x, o])
        j, (r, log_norm) = jax.jacfwd(f, has_aux=True)(z)
        second = _heading_second_order(graph.residual_fn, z, data, cand, r) if curvature else jnp.zeros((), r.dtype)
        return r, log_norm, j, second

    per_candidate = jax.vmap(one, (None, 0, None, 0))
    r, log_norm, j, second = jax.vmap(per_candidate, (0, 0, 0, None))(
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
    if curvature:  # where positive: H stays positive semi-definite
        extra = jnp.where(use, scale * jnp.maximum(second, 0.0), 0.0)
        hess = hess.at[..., _OBJECT_HEADING, _OBJECT_HEADING].add(extra)
    grad = jnp.sum(j * (jnp.sqrt(scale)[..., None] * r)[..., None], axis=-2)  # (F, G, 6)
    return cost, hess, grad, pose_idx, obj_idx, active


def _live_factors(graph: FactorGraph) -> Int[Array, ""]:
    """One past the last measurement factor with a component (a candidate or a null one): the
    factors after it carry no term."""
    f = graph.meas_pose.shape[0]
    live = jnp.any(graph.meas_log_weight > -jnp.inf, axis=-1) | (graph.meas_null_log_weight > -jnp.inf)
    return jnp.max(jnp.where(live, jnp.arange(1, f + 1), 0), initial=0)


def _measurement_blocks(graph: FactorGraph, poses, objects):
    """The measurement factors' cost, active components ``(F,)`` and blocks scattered
    (:func:`_scatter_measurements`), linearized over the live prefix of the factor slots only, at
    one of a few compiled sizes (:mod:`..buckets`): a fixed-lag window's slots are sized for the
    busiest window of the log (MRCLAM: 329 slots where half as many are typical). The factors left
    out have no component: they add nothing, and their active component is ``-1`` (none)."""
    p, n = poses.shape[0], objects.shape[0]
    f = graph.meas_pose.shape[0]

    def on_head(size: tuple[int]):
        head = jax.tree.map(lambda a: a[: size[0]], (graph.meas_pose, graph.meas_objects, graph.meas_log_weight,
                                                       graph.meas_null_log_weight, graph.meas_data))
        g = dataclasses.replace(graph, meas_pose=head[0], meas_objects=head[1], meas_log_weight=head[2],
                                meas_null_log_weight=head[3], meas_data=head[4])
        cost, h, grad, pose_idx, obj_idx, active = _measurement_terms(g, poses, objects)
        active = jnp.concatenate([active, jnp.full((f - size[0],), -1, active.dtype)])
        return cost, active, _scatter_measurements(h, grad, pose_idx, obj_idx, p, n)

    return buckets.by_bucket(buckets.bucket_sizes(f), (_live_factors(graph),), on_head)


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
    """The blocks of ``H = JᵀJ``, ``g = Jᵀr`` and the cost ``½‖r‖²`` at ``(poses, objects)``; an
    object's heading seen through a viewpoint-dependent classifier also gets its second-order
    curvature (:func:`_measurement_terms`).

    Each factor's Jacobian comes from ``jax.jacfwd`` on its own variables (3 or 6 columns), vmapped
    over factors; the prior's is ``R``, so its block is the constant ``Λ = RᵀR`` (``prior_info``,
    computed here if not given). ``log η`` is treated as a constant (no Gauss-Newton term): a
    residual function returns a state-independent one. The closed-form classifiers' score
    covariances do not depend on the viewpoint; a learned model's do, and it carries the varying
    part ``log|R_c(θ)|`` as one more residual entry (:meth:`~hybridslam.models.learned.Learned.residuals`),
    so ``½‖r‖² − log η`` is the whole negative log-likelihood here too.
    """
    check_shapes(graph, poses, objects)
    p, n = poses.shape[0], objects.shape[0]
    info = prior_information(graph) if prior_info is None else prior_info
    prior_cost, prior_grad = _prior_terms(graph, poses, objects)
    odo_cost, odo_h, odo_g = _odometry_terms(graph, poses)
    meas_cost, active, (pp, oo, po, gp, go) = _measurement_blocks(graph, poses, objects)

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
