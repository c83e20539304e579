"""Levenberg-Marquardt over a :class:`~.graph.FactorGraph` (the package docstring, "Damping" and
"Linear convergence"): the loop's own state (:class:`_LMState`, a fixed structure), its traced
stopping rules (:class:`TerminationConfig`) and its outcome (:class:`Solution`). The public entry,
differentiable by the implicit function theorem, is :func:`~.implicit.solve`."""

from __future__ import annotations

from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ...models import se2
from .. import buckets
from ..update import GN_TOLERANCE
from .elimination import AbstractElimination, solve_normal
from .graph import FactorGraph
from .linearization import Linearization, linearize, prior_information

_LAMBDA_RANGE = (1e-15, 1e15)
_DECREMENT_LAMBDA = 1e-3  # damping below which a step's model gain stands for Gauss-Newton's


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


class TerminationConfig(eqx.Module):
    """When :func:`~.implicit.solve`'s Levenberg-Marquardt loop stops, and where its damping starts.

    All traced (changing them does not recompile; ``max_steps``, which fixes the history's shape, is
    static and passed beside): ``state_tol`` bounds ``max|δ|`` (m / rad), ``cost_rtol`` the relative
    and ``cost_atol`` the absolute cost decrease still worth an iterate (nats: the relative, the
    rate and the Newton-decrement tests of the package docstring, "Damping"), ``lambda_init`` the
    initial damping relative to ``diag(H)``. No derivative flows through them (:func:`~.implicit.solve`
    stops their gradients).
    """

    state_tol: float | Float[Array, ""] = GN_TOLERANCE
    cost_rtol: float | Float[Array, ""] = 1e-12
    cost_atol: float | Float[Array, ""] = 1e-9
    lambda_init: float | Float[Array, ""] = 1e-4


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


def _lm_step(graph: FactorGraph, info: Float[Array, "D0 D0"], method: AbstractElimination,
             config: TerminationConfig, max_steps: int, s: _LMState) -> _LMState:
    """One Levenberg-Marquardt iteration: solve the damped system at the kept linearization, linearize
    at the candidate, accept or reject it (Nielsen), and test the stopping rules of the package
    docstring ("Damping")."""
    state_tol, cost_rtol, cost_atol = config.state_tol, config.cost_rtol, config.cost_atol
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


def levenberg_marquardt(graph: FactorGraph, poses0: Float[Array, "P 3"], objects0: Float[Array, "N 3"],
                        config: TerminationConfig, *, max_steps: int, method: AbstractElimination) -> Solution:
    """The Levenberg-Marquardt loop of :func:`~.implicit.solve` from ``(poses0, objects0)``: a
    ``lax.while_loop`` over :func:`_lm_step` until every member of a batch is done."""
    dtype = poses0.dtype
    info = prior_information(graph)
    init = _LMState(
        jnp.asarray(False), poses0, objects0, _unlinearized(graph, poses0.shape[0], objects0.shape[0], dtype),
        jnp.asarray(config.lambda_init, dtype), jnp.asarray(2.0, dtype), jnp.asarray(0), jnp.asarray(False),
        cast(optx.RESULTS, optx.RESULTS.successful),  # an item; its stub says str
        jnp.full((max_steps,), jnp.nan, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype),
    )
    body = lambda s: _lm_step(graph, info, method, config, max_steps, s)  # noqa: E731
    s = jax.lax.while_loop(lambda s: ~s.done, body, init)
    return Solution(s.poses, s.objects, s.lin.cost, s.steps, s.result, s.lin.active, s.history, s.lin)
