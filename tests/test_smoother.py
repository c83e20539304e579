"""The factor-graph smoother (hybridslam.inference.smoother) against closed forms.

For a linear-Gaussian graph (linear odometry and measurement residuals) the minimizer is the
least-squares solution of the stacked residuals, its covariance the inverse of ``JᵀJ``: both are
computed here from an independently stacked residual vector (``jax.jacfwd`` of the whole thing and
``numpy.linalg.lstsq``), not from the solver's own blocks.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import hybridslam  # noqa: F401  (float64)
from hybridslam.inference import smoother as sm
from hybridslam.inference.update import GN_TOLERANCE
from hybridslam.models import geometry, se2
from hybridslam.models.motion import odometry_residual

P, N, F, G = 5, 3, 7, 2
W_ODO = np.diag([10.0, 10.0, 20.0])
W_MEAS = np.array([[5.0, 1.0], [0.0, 4.0]])
# Every solve's cap on iterations (static: one compiled solve per graph structure and shape; the
# linear graphs converge in a few iterations, the nonlinear ones in under 20).
MAX_STEPS = 60
# The solver's default tolerances: traced, so that solves to other tolerances share a program.
DEFAULTS = {"state_tol": GN_TOLERANCE, "cost_rtol": 1e-12, "cost_atol": 1e-9, "lambda_init": 1e-4}


@eqx.filter_jit
def _solve(graph, poses0, objects0, tolerances, method):
    return sm.solve(graph, poses0, objects0, max_steps=MAX_STEPS, method=method, **tolerances)


def solve(graph, poses0, objects0, method="auto", **tolerances):
    """:func:`sm.solve`, compiled once per graph structure, shape and ``method`` (every call of the
    file shares the programs; op by op, the surrounding array code costs hundreds of tiny compiles)."""
    tolerances = {k: jnp.asarray(v, float) for k, v in {**DEFAULTS, **tolerances}.items()}
    return _solve(graph, jnp.asarray(poses0, float), jnp.asarray(objects0, float), tolerances, method)


def exact_solve(graph, poses0, objects0, method="auto"):
    """Undamped (lambda_init = 0): Gauss-Newton, exact in one step on a linear graph. A damped start
    converges linearly, and once the cost changes by less than its rounding the acceptance test
    stalls it a few 1e-9 from the optimum (seen with the suite's XLA settings on one CPU), while
    these tests compare with exact solutions to 1e-9."""
    return solve(graph, poses0, objects0, method, lambda_init=0.0)


linearize = jax.jit(sm.linearize)
marginal = jax.jit(sm.marginal, static_argnums=2)


def linear_odometry(x_prev, x, u):
    return x - x_prev - u


class Offset(eqx.Module):
    """``W (z − (o_xy − x_xy))``: a linear measurement of the object relative to the pose."""

    sqrt_info: jnp.ndarray

    def __call__(self, x, o, data, g):
        del g
        return self.sqrt_info @ (data - (o[:2] - x[:2])), jnp.asarray(0.0)


def _graph(rng, mode="sum", poses=P, linear=True, independent=False):
    """A random graph: prior on x_0 and the map, odometry chain, F factors with G candidates.

    ``independent``: a block-diagonal prior (no two objects coupled; ``independent_objects``)."""
    n0 = 3 + 3 * N
    a = rng.normal(size=(n0, n0)) * 0.1
    info = np.eye(n0) * 4.0 + a @ a.T
    if independent:
        info = info * np.kron(np.eye(N + 1), np.ones((3, 3)))
    sqrt_info = np.linalg.cholesky(info).T
    meas_objects = rng.integers(0, N, size=(F, G))
    log_w = np.log(rng.uniform(0.2, 1.0, size=(F, G)))
    log_w[0, 1] = -np.inf  # a padded candidate
    return sm.FactorGraph(
        prior_mean=jnp.asarray(rng.normal(size=n0) * 0.1),
        prior_sqrt_info=jnp.asarray(sqrt_info),
        odometry=jnp.asarray(rng.normal(size=(poses - 1, 3)) * 0.1),
        odometry_active=jnp.ones(poses - 1, bool),
        motion_sqrt_info=jnp.asarray(W_ODO),
        meas_pose=jnp.asarray(rng.integers(0, poses, size=F)),
        meas_objects=jnp.asarray(meas_objects),
        meas_log_weight=jnp.asarray(log_w),
        meas_null_log_weight=(jnp.full(F, -np.inf, float) if mode == "sum"
                              else jnp.asarray(np.log(rng.uniform(0.01, 0.1, F)))),
        meas_data=jnp.asarray(rng.normal(size=(F, 2)) * 0.2),
        pose_active=jnp.ones(poses, bool),
        object_active=jnp.ones(N, bool),
        residual_fn=Offset(jnp.asarray(W_MEAS)) if linear else sm.RangeBearingResidual(jnp.asarray(W_MEAS)),
        odometry_fn=linear_odometry if linear else odometry_residual,
        mode=mode,
        independent_objects=independent,
    )


def _stacked_residual(graph):
    """Every whitened residual of a sum-mode graph, stacked: ``r(y)``, ``y = [poses, objects]``
    (a padded candidate's rows are zero: its weight is ``exp(-inf) = 0``)."""
    p, n = graph.num_poses, graph.num_objects

    def r(y):
        poses, objects = y[: 3 * p].reshape(p, 3), y[3 * p :].reshape(n, 3)
        parts = [graph.prior_sqrt_info @ (jnp.concatenate([poses[0], objects.reshape(-1)]) - graph.prior_mean)]
        for i in range(1, p):
            parts.append(graph.motion_sqrt_info @ graph.odometry_fn(poses[i - 1], poses[i], graph.odometry[i - 1]))
        for f in range(graph.meas_pose.shape[0]):
            for g in range(graph.meas_objects.shape[1]):
                res, _ = graph.residual_fn(poses[graph.meas_pose[f]], objects[graph.meas_objects[f, g]],
                                           graph.meas_data[f], g)
                parts.append(jnp.exp(0.5 * graph.meas_log_weight[f, g]) * res)
        return jnp.concatenate(parts)

    return r


@jax.jit
def _stacked_jacobian(graph):
    """``r(0)`` and ``J = ∂r/∂y`` at ``y = 0`` (:func:`_stacked_residual`), one compiled program."""
    r = _stacked_residual(graph)
    y0 = jnp.zeros(3 * graph.num_poses + 3 * graph.num_objects)
    return r(y0), jax.jacfwd(r)(y0)


def _least_squares(graph):
    """The exact minimizer and ``(JᵀJ)⁻¹`` of a linear sum-mode graph, by numpy."""
    r0, j = (np.asarray(a) for a in _stacked_jacobian(graph))
    y = -np.linalg.lstsq(j, r0, rcond=None)[0]
    return y, np.linalg.inv(j.T @ j)


def test_linear_graph_solution_is_the_least_squares_solution():
    graph = _graph(np.random.default_rng(0))
    sol = exact_solve(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    y, _ = _least_squares(graph)
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(sol.poses).reshape(-1), y[: 3 * P], atol=1e-9)
    np.testing.assert_allclose(np.asarray(sol.objects).reshape(-1), y[3 * P :], atol=1e-9)
    hist = np.asarray(sol.history)
    hist = hist[np.isfinite(hist)]
    assert np.all(np.diff(hist) <= 1e-12), hist  # the LM cost never increases


@jax.jit
def _eliminations(graph, poses, objects):
    """The dense ``H``, ``g`` of the linearization and its solution by every elimination order."""
    lin = sm.linearize(graph, poses, objects)
    return lin.dense(), {m: sm.solve_normal(lin, m) for m in ("poses-first", "objects-first", "dense")}


@pytest.mark.parametrize("independent", [False, True])
def test_structured_eliminations_match_the_dense_solve(independent):
    graph = _graph(np.random.default_rng(1), independent=independent)
    (h, g), solutions = _eliminations(graph, jnp.asarray(np.random.default_rng(2).normal(size=(P, 3)) * 0.1),
                                      jnp.zeros((N, 3)))
    ref = -np.linalg.solve(np.asarray(h), np.asarray(g))
    for method, (d_p, d_o) in solutions.items():
        got = np.concatenate([np.asarray(d_p).reshape(-1), np.asarray(d_o).reshape(-1)])
        np.testing.assert_allclose(got, ref, atol=1e-10, err_msg=method)


@pytest.mark.parametrize("k", [0, 2, P - 1])
def test_marginal_is_the_block_of_the_inverse_hessian(k):
    graph = _graph(np.random.default_rng(3))
    sol = exact_solve(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    _, full = _least_squares(graph)
    idx = np.concatenate([np.arange(3 * k, 3 * k + 3), 3 * P + np.arange(3 * N)])
    for method in ("auto", "objects-first"):  # poses first, and objects first with a dense C
        mean, cov = marginal(sol, jnp.asarray(k), method)
        np.testing.assert_allclose(np.asarray(cov), full[np.ix_(idx, idx)], rtol=1e-8, atol=1e-12, err_msg=method)
        np.testing.assert_allclose(np.asarray(mean[:3]), np.asarray(sol.poses[k]))


@pytest.mark.parametrize("independent", [False, True])
def test_covariances_are_the_blocks_of_the_inverse_hessian(independent):
    """Every pose's marginal, its cross-covariance with the map and the map's joint covariance: the
    blocks of the dense ``H⁻¹``, with a dense or a block-diagonal object part."""
    graph = _graph(np.random.default_rng(5), independent=independent)
    sol = exact_solve(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    assert sol.linearization.object_blocks == independent
    h, _ = sol.linearization.dense()
    full = np.linalg.inv(np.asarray(h))
    got = sm.covariances(sol)
    poses = np.stack([full[3 * t: 3 * t + 3, 3 * t: 3 * t + 3] for t in range(P)])
    np.testing.assert_allclose(np.asarray(got.poses), poses, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(np.asarray(got.pose_object).reshape(3 * P, 3 * N), full[: 3 * P, 3 * P:], rtol=1e-8,
                               atol=1e-12)
    np.testing.assert_allclose(np.asarray(got.objects), full[3 * P:, 3 * P:], rtol=1e-8, atol=1e-12)


def test_auto_order_eliminates_the_larger_set_or_a_small_pose_chain_last():
    """``"auto"``: objects first when they outnumber the poses, or when the pose system is small and
    the objects are independent (the paper setup); poses first on long chains; explicit orders kept."""
    assert sm.resolve_method("auto", 61, 70) == "objects-first"
    assert sm.resolve_method("auto", 201, 15, True) == "poses-first"
    assert sm.resolve_method("auto", 11, 6) == "poses-first"
    assert sm.resolve_method("auto", 11, 6, True) == "objects-first"
    assert sm.resolve_method("auto", sm.SMALL_POSE_SYSTEM + 1, 6, True) == "poses-first"
    assert sm.resolve_method("dense", 11, 6, True) == "dense"


@pytest.mark.parametrize("k", [0, 1])
def test_marginal_of_independent_objects_inverts_their_blocks(k):
    """Fewer poses than objects and a block-diagonal object prior: ``"auto"`` eliminates the objects
    first, block by block, and still gives the block of ``H⁻¹``, inactive objects at identity."""
    graph = _graph(np.random.default_rng(8), poses=2, independent=True)
    graph = eqx.tree_at(lambda g: g.object_active, graph, jnp.array([True, True, False]))
    assert sm.resolve_method("auto", graph.num_poses, graph.num_objects) == "objects-first"
    sol = exact_solve(graph, jnp.zeros((2, 3)), jnp.zeros((N, 3)))
    assert sol.linearization.object_blocks
    mean, cov = marginal(sol, jnp.asarray(k), "auto")
    reference = exact_solve(dataclasses.replace(graph, independent_objects=False), jnp.zeros((2, 3)),
                            jnp.zeros((N, 3)), "dense")
    h, _ = reference.linearization.dense()
    idx = np.concatenate([np.arange(3 * k, 3 * k + 3), 6 + np.arange(3 * N)])
    np.testing.assert_allclose(np.asarray(cov), np.linalg.inv(np.asarray(h))[np.ix_(idx, idx)], rtol=1e-8,
                               atol=1e-12)
    np.testing.assert_allclose(np.asarray(cov)[-3:, -3:], np.eye(3), atol=1e-12)  # the inactive object
    np.testing.assert_allclose(np.asarray(cov)[:-3, -3:], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(mean), np.concatenate([np.asarray(reference.poses[k]),
                                                                 np.asarray(reference.objects).reshape(-1)]),
                               atol=1e-9)


@jax.jit
def _marginalize_first(graph, poses, objects):
    """:func:`sm.marginalize_first` and :func:`sm.marginalize_first_information`: one program."""
    return sm.marginalize_first(graph, poses, objects), sm.marginalize_first_information(graph, poses, objects)


def test_marginalizing_the_first_pose_is_exact_for_linear_factors():
    """Solving [x_1.., O] under the marginalized prior gives the full solution without x_0."""
    graph = _graph(np.random.default_rng(4))
    sol = exact_solve(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    (mean, sqrt_info), _ = _marginalize_first(graph, sol.poses, sol.objects)
    keep = graph.meas_pose > 0
    reduced = sm.FactorGraph(
        prior_mean=mean, prior_sqrt_info=sqrt_info, odometry=graph.odometry[1:],
        odometry_active=graph.odometry_active[1:], motion_sqrt_info=graph.motion_sqrt_info,
        meas_pose=jnp.maximum(graph.meas_pose - 1, 0), meas_objects=graph.meas_objects,
        meas_log_weight=jnp.where(keep[:, None], graph.meas_log_weight, -jnp.inf),
        meas_null_log_weight=graph.meas_null_log_weight, meas_data=graph.meas_data,
        pose_active=graph.pose_active[1:], object_active=graph.object_active,
        residual_fn=graph.residual_fn, odometry_fn=graph.odometry_fn,
    )
    out = solve(reduced, jnp.zeros((P - 1, 3)), jnp.zeros((N, 3)))
    np.testing.assert_allclose(np.asarray(out.poses), np.asarray(sol.poses[1:]), atol=1e-9)
    np.testing.assert_allclose(np.asarray(out.objects), np.asarray(sol.objects), atol=1e-9)


def test_marginalizing_keeps_an_uninformed_object_uninformed():
    """A discovered object has no prior on its position, and the first pose did not see it: its
    rows of the marginalized prior carry no information (zero rows of ``R``, not a failed
    Cholesky), and the marginalization stays exact for linear factors."""
    graph = _graph(np.random.default_rng(5))
    xy = np.array([3 + 3 * 2, 3 + 3 * 2 + 1])  # object 2's position
    sqrt_info = np.array(graph.prior_sqrt_info)
    sqrt_info[:, xy] = 0.0
    objects, poses, log_w = (np.array(a) for a in (graph.meas_objects, graph.meas_pose, graph.meas_log_weight))
    poses[np.any(objects == 2, axis=1) & (poses == 0)] = 1  # x_0 does not see it
    objects[1, 0], poses[1], log_w[1, 0] = 2, 2, 0.0  # a later pose does
    graph = eqx.tree_at(lambda g: (g.prior_sqrt_info, g.meas_objects, g.meas_pose, g.meas_log_weight), graph,
                        (jnp.asarray(sqrt_info), jnp.asarray(objects), jnp.asarray(poses), jnp.asarray(log_w)))
    sol = exact_solve(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    _, (mean, r, info) = _marginalize_first(graph, sol.poses, sol.objects)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(r))
    np.testing.assert_array_equal(np.asarray(r)[xy + 0], 0.0)  # prior over [x_1, O]: same object offsets
    # The information handed on is RᵀR, the uninformed rows included (zero rows and columns).
    np.testing.assert_allclose(np.asarray(info), np.asarray(r).T @ np.asarray(r), rtol=1e-10,
                               atol=1e-10 * np.abs(np.asarray(info)).max())
    np.testing.assert_array_equal(np.asarray(info)[xy], 0.0)
    keep = graph.meas_pose > 0
    reduced = eqx.tree_at(
        lambda g: (g.prior_mean, g.prior_sqrt_info, g.odometry, g.odometry_active, g.meas_pose, g.meas_log_weight,
                   g.pose_active),
        graph,
        (mean, r, graph.odometry[1:], graph.odometry_active[1:], jnp.maximum(graph.meas_pose - 1, 0),
         jnp.where(keep[:, None], graph.meas_log_weight, -jnp.inf), graph.pose_active[1:]))
    out = solve(reduced, jnp.zeros((P - 1, 3)), jnp.zeros((N, 3)))
    np.testing.assert_allclose(np.asarray(out.poses), np.asarray(sol.poses[1:]), atol=1e-9)
    np.testing.assert_allclose(np.asarray(out.objects), np.asarray(sol.objects), atol=1e-9)
    # The same solve given the information instead of forming RᵀR, and given only the information
    # (no R: the prior ½dᵀΛd, what a fixed-lag window carries): the same solution and cost.
    with_info = eqx.tree_at(lambda g: g.prior_info, reduced, info, is_leaf=lambda x: x is None)
    only_info = eqx.tree_at(lambda g: g.prior_sqrt_info, with_info, None)
    for g in (with_info, only_info):
        got = solve(g, jnp.zeros((P - 1, 3)), jnp.zeros((N, 3)))
        np.testing.assert_allclose(np.asarray(got.poses), np.asarray(sol.poses[1:]), atol=1e-9)
        np.testing.assert_allclose(float(got.cost), float(out.cost), rtol=1e-9, atol=1e-12)
    lin_r, lin_info = (linearize(g, sol.poses[1:], sol.objects + 0.1, info) for g in (reduced, only_info))
    np.testing.assert_allclose(float(lin_info.cost), float(lin_r.cost), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(lin_info.grad_object), np.asarray(lin_r.grad_object), rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="prior_sqrt_info: None needs prior_info"):
        solve(eqx.tree_at(lambda g: g.prior_sqrt_info, reduced, None), jnp.zeros((P - 1, 3)), jnp.zeros((N, 3)))


def test_max_mixture_picks_the_component_that_explains_the_data():
    """A factor with a consistent candidate and an absurd one: "max" mode ignores the absurd one
    (the result equals the graph with only the good candidate); a hopeless outlier takes the null."""
    rng = np.random.default_rng(5)
    base = _graph(rng, mode="max")
    truth_objects = np.asarray(base.prior_mean[3:]).reshape(N, 3)
    poses0 = np.zeros((P, 3))
    # Factor f sees object good[f] exactly (relative offset), candidate 1 is another object.
    good = np.arange(F) % N
    data = truth_objects[good, :2] - poses0[np.asarray(base.meas_pose), :2]
    data[-1] = [40.0, -40.0]  # an outlier: no candidate explains it
    objs = np.stack([good, (good + 1) % N], axis=1)
    lw = np.log(np.full((F, G), 0.5))
    graph = sm.FactorGraph(**{**{f: getattr(base, f) for f in base.__dataclass_fields__},
                              "meas_objects": jnp.asarray(objs), "meas_log_weight": jnp.asarray(lw),
                              "meas_data": jnp.asarray(data)})
    out = solve(graph, jnp.asarray(poses0), jnp.asarray(truth_objects))
    active = np.asarray(out.active)
    assert np.all(active[:-1] == 0), active
    assert active[-1] == G, active  # the null component
    only_good = sm.FactorGraph(**{**{f: getattr(graph, f) for f in graph.__dataclass_fields__},
                                  "meas_log_weight": jnp.asarray(np.where(np.arange(G) == 0, 0.0, -np.inf)[None]
                                                                 * np.ones((F, 1))).at[-1].set(-jnp.inf),
                                  "mode": "sum"})
    ref = exact_solve(only_good, jnp.asarray(poses0), jnp.asarray(truth_objects))  # linear: the exact minimizer
    np.testing.assert_allclose(np.asarray(out.poses), np.asarray(ref.poses), atol=1e-7)
    np.testing.assert_allclose(np.asarray(out.objects), np.asarray(ref.objects), atol=1e-7)


def _nonlinear_graph(rng):
    """Range-bearing factors and SE(2) odometry around a true trajectory: (graph, truth, objects)."""
    true_poses = np.cumsum(np.tile([[1.0, 0.0, 0.1]], (P, 1)), axis=0)
    objects = np.array([[3.0, 4.0, 0.0], [6.0, -3.0, 0.0], [1.0, -5.0, 0.0]])
    base = _graph(rng, linear=False)
    pose_of = np.asarray(base.meas_pose)
    obj_of = np.asarray(base.meas_objects[:, 0])
    z = np.stack([np.asarray(geometry.range_bearing(jnp.asarray(true_poses[i]), jnp.asarray(objects[j])))
                  for i, j in zip(pose_of, obj_of)]) + rng.normal(size=(F, 2)) * 0.05
    odo = np.stack([np.asarray(se2.between(jnp.asarray(true_poses[i]), jnp.asarray(true_poses[i + 1])))
                    for i in range(P - 1)])
    graph = sm.FactorGraph(**{**{f: getattr(base, f) for f in base.__dataclass_fields__},
                              "meas_data": jnp.asarray(z), "odometry": jnp.asarray(odo),
                              "meas_log_weight": jnp.where(jnp.arange(G) == 0, 0.0, -jnp.inf)[None].repeat(F, 0),
                              "prior_mean": jnp.concatenate([jnp.asarray(true_poses[0]), jnp.asarray(objects).reshape(-1)])})
    return graph, true_poses, objects


def test_nonlinear_graph_converges_to_a_stationary_point():
    """Range-bearing factors and SE(2) odometry: LM converges and the gradient vanishes there."""
    rng = np.random.default_rng(6)
    graph, true_poses, objects = _nonlinear_graph(rng)
    start = true_poses + rng.normal(size=(P, 3)) * 0.2
    out = solve(graph, jnp.asarray(start), jnp.asarray(objects))
    assert out.result == optx.RESULTS.successful
    lin = linearize(graph, out.poses, out.objects)
    assert float(jnp.max(jnp.abs(lin.grad_pose))) < 1e-6
    assert float(jnp.max(jnp.abs(lin.grad_object))) < 1e-6
    assert float(jnp.max(jnp.abs(out.poses[:, :2] - true_poses[:, :2]))) < 0.3


def test_a_warm_start_ends_by_the_newton_decrement_at_the_strict_solution():
    """A smoother step's solve (warm start: last step's solution, a new pose 30 cm off) stops once
    a Gauss-Newton step's model gain is below ``cost_atol``: fewer iterates than without the test
    (``cost_atol=0``), the same solution to 1e-7, and the linearization it returns is the one at its
    solution (what ``marginal`` uses)."""
    graph, true_poses, objects = _nonlinear_graph(np.random.default_rng(6))
    out = solve(graph, jnp.asarray(true_poses), jnp.asarray(objects))
    warm = out.poses.at[-1].add(jnp.array([0.3, -0.3, 0.06]))
    fast = solve(graph, warm, out.objects)
    strict = solve(graph, warm, out.objects, cost_atol=0.0)
    assert fast.result == optx.RESULTS.successful and strict.result == optx.RESULTS.successful
    assert int(fast.steps) < int(strict.steps)
    np.testing.assert_allclose(np.asarray(fast.poses), np.asarray(strict.poses), atol=1e-7)
    np.testing.assert_allclose(np.asarray(fast.objects), np.asarray(strict.objects), atol=1e-7)
    assert 0.0 <= float(fast.cost - strict.cost) <= 1e-9
    again = linearize(graph, fast.poses, fast.objects)
    for a, b in zip(jax.tree.leaves(fast.linearization), jax.tree.leaves(again)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)  # 2.5e-12 on jax 0.4.38


def test_bad_shapes_name_the_field(unchecked_types):
    graph = _graph(np.random.default_rng(7))
    with pytest.raises(ValueError, match="poses"):
        solve(graph, jnp.zeros((P + 1, 3)), jnp.zeros((N, 3)))
    with pytest.raises(ValueError, match="odometry"):
        bad = sm.FactorGraph(**{**{f: getattr(graph, f) for f in graph.__dataclass_fields__},
                                "odometry": graph.odometry[:-1]})
        solve(bad, jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    with pytest.raises(ValueError, match="method"):
        sm.solve_normal(linearize(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3))), "cholmod")


class Curved(eqx.Module):
    """``W (u + κ u²)``, ``u = z − (o_xy − x_xy)``: residuals that stay non-zero at the optimum and
    curve, so Gauss-Newton converges only linearly (as the semantic factors of Eq. 18 make it)."""

    sqrt_info: jnp.ndarray
    kappa: float

    def __call__(self, x, o, data, g):
        del g
        u = data - (o[:2] - x[:2])
        return self.sqrt_info @ (u + self.kappa * u**2), jnp.asarray(0.0)


def test_a_steady_linear_rate_stops_once_the_gain_to_come_is_below_cost_atol():
    base = _graph(np.random.default_rng(3))
    graph = dataclasses.replace(base, residual_fn=Curved(jnp.asarray(W_MEAS), 0.5), meas_data=base.meas_data * 5)
    p0, o0 = jnp.zeros((P, 3)), jnp.zeros((N, 3))
    strict = solve(graph, p0, o0, cost_atol=0.0)
    steady = solve(graph, p0, o0)  # cost_atol = 1e-9 nats
    gains = -np.diff(np.asarray(strict.history)[: int(strict.steps)])
    rates = gains[1:] / gains[:-1]
    assert np.all((rates[:6] > 0.05) & (rates[:6] < 0.9)), rates  # linear convergence: the rule applies
    assert strict.result == optx.RESULTS.successful and steady.result == optx.RESULTS.successful
    assert int(steady.steps) < int(strict.steps)
    assert 0.0 <= float(steady.cost - strict.cost) <= 1e-9



def test_a_nonfinite_solve_keeps_the_given_estimate():
    """``smooth`` keeps the ``mean`` and ``cov`` it was given (and says ``nonfinite``) where the graph
    yields no finite solution or marginal, and returns the graph's own where it does."""
    from hybridslam.estimators.smoothers.kinds import Full, smooth

    rng = np.random.default_rng(5)
    good = _graph(rng)
    # A NaN in the prior's information: no finite Hessian (NaN data alone would leave the start and
    # the marginal finite: the solver says nonfinite and stops there, and that marginal is kept).
    bad = eqx.tree_at(lambda g: g.prior_sqrt_info, good, good.prior_sqrt_info.at[4, 4].set(jnp.nan))
    poses = jnp.zeros((P, 3))
    mean = jnp.asarray(rng.normal(size=3 + 3 * N) * 0.1)
    cov = jnp.eye(3 + 3 * N) * 7.0
    k = jnp.asarray(P - 1)
    smooth_full = jax.jit(lambda *args: smooth(Full(), *args))
    ok, failed = (smooth_full(g, poses, mean, cov, k) for g in (good, bad))
    assert ok.result == optx.RESULTS.successful and failed.result == optx.RESULTS.nonfinite
    np.testing.assert_array_equal(failed.mean, mean)
    np.testing.assert_array_equal(failed.cov, cov)
    np.testing.assert_array_equal(failed.poses, poses.at[P - 1].set(mean[:3]))
    assert bool(jnp.all(jnp.isfinite(ok.cov))) and not bool(jnp.allclose(ok.cov, cov))


# --------------------------------------------------------------------------------------------
# Derivatives of the solution (implicit function theorem, not through the iterations)
# --------------------------------------------------------------------------------------------


@pytest.fixture
def fast_compile():
    """XLA's optimizations off: derivative programs compile about twice as fast, and these are tiny."""
    old = jax.config.values["jax_disable_most_optimizations"]
    jax.config.update("jax_disable_most_optimizations", True)
    yield
    jax.config.update("jax_disable_most_optimizations", old)


def _with(graph, **fields):
    return eqx.tree_at(lambda g: tuple(getattr(g, f) for f in fields), graph, tuple(fields.values()))


def test_derivative_of_a_linear_solution_is_the_least_squares_one(fast_compile):
    """On a linear graph ``y*(θ) = argmin ‖r(y, θ)‖²``, so ``dy*/dθ = −(JᵀJ)⁻¹ Jᵀ ∂r/∂θ``: computed
    here by numpy from the independently stacked residuals, against reverse mode through :func:`solve`."""
    graph = _graph(np.random.default_rng(0))
    theta = (graph.meas_data, graph.odometry)
    start = (jnp.zeros((P, 3)), jnp.zeros((N, 3)))

    def solution(theta):
        graph_theta = _with(graph, meas_data=theta[0], odometry=theta[1])
        sol = sm.solve(graph_theta, *start, max_steps=20, lambda_init=0.0)
        return jnp.concatenate([sol.poses.reshape(-1), sol.objects.reshape(-1)])

    got = jax.jit(jax.jacrev(solution))(theta)
    y = jnp.zeros(3 * (P + N))
    stacked = lambda th: _stacked_residual(_with(graph, meas_data=th[0], odometry=th[1]))(y)  # noqa: E731
    j = np.asarray(_stacked_jacobian(graph)[1])
    for j_theta, g in zip(jax.jit(jax.jacfwd(stacked))(theta), got):
        j_theta = np.asarray(j_theta).reshape(j.shape[0], -1)
        expected = -np.linalg.solve(j.T @ j, j.T @ j_theta)
        np.testing.assert_allclose(np.asarray(g).reshape(expected.shape), expected, atol=1e-9)


def test_derivatives_of_a_nonlinear_solution_and_its_marginal_match_finite_differences(fast_compile):
    """Range-bearing factors and SE(2) odometry (second-order terms: the Hessian is not Gauss-Newton's),
    one inactive pose and object (padding): reverse mode equals forward mode (along a random direction of
    each input), both equal central finite differences of the converged solution, its cost and its
    marginal covariance; the inactive slots follow the start and nothing else."""
    rng = np.random.default_rng(6)
    graph, true_poses, objects = _nonlinear_graph(rng)
    graph = _with(graph, pose_active=graph.pose_active.at[-1].set(False),
                  object_active=graph.object_active.at[-1].set(False))
    theta = {"data": graph.meas_data, "odometry": graph.odometry, "prior": graph.prior_mean,
             "start": jnp.asarray(true_poses + rng.normal(size=(P, 3)) * 0.05)}

    def outputs(theta):
        g = _with(graph, meas_data=theta["data"], odometry=theta["odometry"], prior_mean=theta["prior"])
        sol = sm.solve(g, theta["start"], jnp.asarray(objects), max_steps=60, state_tol=1e-12, cost_rtol=0.0,
                       cost_atol=0.0)
        _, cov = sm.marginal(sol, 2)
        return jnp.concatenate([sol.poses.reshape(-1), sol.objects.reshape(-1), cov[:9].reshape(-1),
                                sol.cost[None]])

    reverse = jax.jit(jax.jacrev(outputs))(theta)
    # Forward mode along each direction (one jvp program, which also gives the values the finite
    # differences take): a random direction sees any column where the two modes differ.
    jvp = jax.jit(lambda theta, tangent: jax.jvp(outputs, (theta,), (tangent,)))
    zero = jax.tree.map(jnp.zeros_like, theta)
    for name in theta:
        direction = np.asarray(rng.normal(size=theta[name].shape))
        jac = np.asarray(reverse[name])
        ad = np.tensordot(jac, direction, direction.ndim)
        forward = np.asarray(jvp(theta, {**zero, name: jnp.asarray(direction)})[1])
        # Entry by entry |reverse - forward| <= 1e-7 |reverse| + 1e-10, carried through the contraction.
        bound = (1e-7 * np.tensordot(np.abs(jac), np.abs(direction), direction.ndim)
                 + 1e-10 * np.sum(np.abs(direction)))
        assert np.all(np.abs(ad - forward) <= bound), (name, np.max(np.abs(ad - forward) - bound))
        h = 1e-4  # the solves stop ~1e-9 from the optimum: a smaller step's difference is that noise
        plus, minus = (jvp({**theta, name: theta[name] + s * h * direction}, zero)[0] for s in (1, -1))
        fd = np.asarray(plus - minus) / (2 * h)
        np.testing.assert_allclose(ad, fd, atol=1e-5 * np.max(np.abs(fd)), err_msg=name)
    inactive_pose, inactive_object = slice(3 * (P - 1), 3 * P), slice(3 * P + 3 * (N - 1), 3 * (P + N))
    for name in ("data", "odometry", "prior"):
        jac = np.asarray(reverse[name])
        assert not np.any(jac[inactive_pose]) and not np.any(jac[inactive_object]), name
    start = np.asarray(reverse["start"])
    np.testing.assert_array_equal(start[inactive_pose].reshape(3, -1)[:, -3:], np.eye(3))
    assert np.max(np.abs(start[: 3 * (P - 1)])) < 1e-9  # the solution forgets its start
