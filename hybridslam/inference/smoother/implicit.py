"""The smoother's solve, differentiable by the implicit function theorem (the package docstring,
"Derivatives"): :func:`solve` runs :func:`~.lm.levenberg_marquardt` under a ``jax.custom_jvp`` rule
(:func:`_solve_jvp`) that differentiates the solution's stationarity, not the iterations."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Float

from ..update import GN_TOLERANCE
from .elimination import AbstractElimination, Method, as_elimination, solve_normal
from .graph import FactorGraph, check_shapes
from .linearization import linearize, prior_information
from .lm import Solution, TerminationConfig, levenberg_marquardt

_IMPLICIT_MAXITER = 50  # conjugate-gradient iterations of a derivative (a few suffice: preconditioned)
_IMPLICIT_RTOL, _IMPLICIT_ATOL = 1e-12, 1e-14  # its tolerance, per entry of the tangent


def solve(
    graph: FactorGraph,
    poses0: Float[Array, "P 3"],
    objects0: Float[Array, "N 3"],
    *,
    max_steps: int = 50,
    method: Method | AbstractElimination = "auto",
    state_tol: float | Float[Array, ""] = GN_TOLERANCE,
    cost_rtol: float | Float[Array, ""] = 1e-12,
    cost_atol: float | Float[Array, ""] = 1e-9,
    lambda_init: float | Float[Array, ""] = 1e-4,
) -> Solution:
    """Minimize ``½‖r(X, O)‖²`` of ``graph`` from ``(poses0, objects0)`` by Levenberg-Marquardt.

    ``max_steps`` and ``method`` (a name or an :class:`~.elimination.AbstractElimination`) are static (one compile per shape); the tolerances and the initial
    damping ``lambda_init`` (relative to ``diag(H)``: ``1e-4`` is nearly Gauss-Newton when the
    start is good; a bad start costs a few rejected steps) are traced. Works under ``jax.jit`` and
    ``jax.vmap`` (the ``lax.while_loop`` runs until every member of a batch is done; finished
    members stay put). See the package docstring for the algorithm.

    Differentiable in forward and reverse mode with respect to every floating-point input of
    ``graph`` (and ``poses0``, ``objects0`` for the inactive slots, which keep them): by the implicit
    function theorem at the solution, not through the iterations (package docstring, "Derivatives").
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
    config = jax.tree.map(jax.lax.stop_gradient, TerminationConfig(state_tol, cost_rtol, cost_atol, lambda_init))
    return _solve(graph, poses0, objects0, config, max_steps=max_steps, method=as_elimination(method))


@eqx.filter_custom_jvp
def _solve(graph: FactorGraph, poses0, objects0, config: TerminationConfig, *, max_steps: int,
           method: AbstractElimination) -> Solution:
    """:func:`solve`'s Levenberg-Marquardt loop (its derivative: :func:`_solve_jvp`)."""
    return levenberg_marquardt(graph, poses0, objects0, config, max_steps=max_steps, method=method)


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
def _solve_jvp(primals, tangents, *, max_steps: int, method: AbstractElimination):
    """The implicit function theorem at the solution ``y*`` of ``g(y, θ) = 0``: the tangent ``ẏ``
    solves ``(∂g/∂y) ẏ = −(∂g/∂θ) θ̇`` on the active rows (``∂g/∂y`` the exact Hessian, by
    forward-mode products; lineax's conjugate gradients, at most ``_IMPLICIT_MAXITER`` iterations,
    preconditioned by the solution's own Gauss-Newton factorization, which differs from the Hessian
    by the residuals' second-order terms only), and the inactive rows keep the start's tangent. The
    solution's linearization (what :func:`marginal` reads) moves with ``(θ̇, ẏ)``. Linear in the
    tangents, so reverse mode transposes it (lineax transposes its solve: the operator is symmetric)."""
    graph, poses0, objects0, config = primals
    t_graph, t_poses0, t_objects0, _ = tangents
    sol = _solve(graph, poses0, objects0, config, max_steps=max_steps, method=method)
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
