"""Gradients through the belief update (docs/gradients.md) against central finite differences.

Every continuous input — odometry, classifier ``alpha``/``K``, ``Σ_w``, ``Σ_v``, the prior means and
the visibility temperatures — is checked, for every functional of :mod:`hybridslam.gradients`,
after a two-step :func:`~hybridslam.planning.gradients.rollout`, for two weight methods with the
smooth visibility model: forward mode (``jax.jvp``, what ``jax.jacfwd`` batches) for ``linearized``,
reverse mode (``jax.grad``) for ``sampled`` (``laplace-is``, the third, is left out for time; see
``PROGRAMS``). The same two compiled programs
(the scene has the paper setup's shapes: 6 objects, 2 detection slots) then check that gradients
are finite on the paper setup, with the smooth and the hard 0/1 visibility (temperature 0).

Compiles dominate: each program is compiled once (module fixture), ahead of time, with XLA's
optimizations off (``_fast_compile``; about twice as fast to compile, and these runs are tiny).
"""

from __future__ import annotations

import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam.estimators.hybrid.belief import init_belief
from hybridslam.models.classifier import Mirror
from hybridslam.models.geometry import log_smooth_visibility, visible
from hybridslam.planning.gradients import (
    best_pose_log_det,
    expected_association_entropy,
    expected_position_error,
    hypothesis_neg_log_weight,
    rollout,
)

N, T = 6, 2  # the paper setup's objects; steps per rollout
WEIGHERS = {"sampled": hs.Sampled(samples=64), "laplace-is": hs.LaplaceIS(samples=32, candidates=4),
            "linearized": hs.Linearized()}
FUNCTIONALS = ("entropy", "neg_log_weight", "log_det", "position_error")
RTOL = 1e-3  # the bound on the finite-difference agreement
f64 = lambda a: jnp.asarray(a, dtype=float)  # noqa: E731


@contextlib.contextmanager
def _fast_compile():
    old = jax.config.values["jax_disable_most_optimizations"]
    jax.config.update("jax_disable_most_optimizations", True)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", old)


def _objectives(p, q, weights):
    """The four functionals after ``T`` steps from the prior; ``p``: differentiable inputs, ``q``: the rest."""
    priors = hs.Priors(p["robot_mean"], q["robot_cov"], p["object_means"], q["object_covs"])
    sensor = hs.SensorModel(p["geometric_cov"], Mirror(p["alpha"], p["K"]), q["max_range"], q["fov"], p["temperature"])
    model = hs.Model(p["motion_cov"], sensor, q["class_prior"], q["prune_ratio"])
    estimator = hs.Hybrid(weights=WEIGHERS[weights], capacity=4, max_detections=2, max_steps=T,
                          smoother=hs.Filter())
    belief = init_belief(priors, model, estimator.capacity, T, 2)
    belief, trace = rollout(estimator, belief, p["odometry"], q["detections"], q["key"])
    info = trace.info
    values = jnp.stack([
        expected_association_entropy(belief), hypothesis_neg_log_weight(belief, q["history"]),
        best_pose_log_det(belief), expected_position_error(belief, q["true_position"]),
    ])
    # The discrete choices (held fixed by the derivative): which hypotheses survive, from which parents.
    return values, (belief.history, info.details.parent, info.visibility_ignored)


def _ambiguous_scene():
    """A well-known robot, two nearby objects a detection cannot tell apart, four far away (out of view).
    Step 1 sees one of the two, step 2 both. Nothing is symmetric, so no two weights tie."""
    p = dict(
        odometry=f64([[0.5, 0.05, 0.02], [0.5, -0.03, 0.05]]),
        alpha=f64(0.3), K=f64(4.0),
        motion_cov=jnp.diag(f64([0.01, 0.01, 0.003])),
        geometric_cov=f64([[0.1, 0.01], [0.01, 0.05]]),
        robot_mean=f64([0.0, 0.0, 0.1]),
        object_means=f64([[4.0, 0.8, 0.5], [4.3, -0.6, -1.0], [-8, 5, 0.3], [-9, -4, 1.2], [15, 9, -0.7], [14, -10, 2.0]]),
        temperature=f64([0.3, 0.05]),  # metres, radians
    )
    q = dict(
        robot_cov=jnp.diag(f64([0.05, 0.05, 0.01])),
        object_covs=jnp.broadcast_to(jnp.diag(f64([0.1, 0.1, 0.01])), (N, 3, 3)),
        class_prior=f64([[0.3, 0.7], [0.6, 0.4]] + [[0.5, 0.5]] * 4),
        prune_ratio=f64(1e30), max_range=f64(5.0), fov=f64(1.6),
        detections=hs.Detections(
            f64([[[4.0, 0.12], [0.0, 0.0]], [[3.6, 0.2], [3.9, -0.35]]]),
            f64([[[0.8, 0.3], [0.0, 0.0]], [[0.7, 0.35], [0.4, 0.6]]]),
            jnp.array([[True, False], [True, True]]),
        ),
        key=jax.random.PRNGKey(3),
        history=jnp.array([[0, -1], [0, 1]], dtype=jnp.int32),
        true_position=f64([1.0, 0.05]),
    )
    return p, q


def _paper_scene(temperature):
    """The first two steps of the paper setup (Sec. V; step 1 has two detections), as (p, q)."""
    scenario = hs.simulate(0, steps=3)
    model = hs.model_from_scenario(scenario)
    priors = hs.priors_from_scenario(scenario)
    stacked = hs.stack_steps(scenario, 2)
    det = hs.stacked_detections(stacked)
    p = dict(
        odometry=f64(stacked.odometry[:T]), alpha=model.sensor.classifier.alpha, K=model.sensor.classifier.K,
        motion_cov=model.motion_cov, geometric_cov=model.sensor.geometric_cov,
        robot_mean=priors.robot_mean, object_means=priors.object_means, temperature=f64(temperature),
    )
    truth = [[d.true_object for d in s.detections] + [-1] * (2 - len(s.detections)) for s in scenario.steps[:T]]
    q = dict(
        robot_cov=priors.robot_cov, object_covs=priors.object_covs, class_prior=model.class_prior,
        prune_ratio=model.prune_ratio, max_range=model.sensor.max_range, fov=model.sensor.fov,
        detections=jax.tree.map(lambda x: x[:T], det), key=jax.random.PRNGKey(0),
        history=jnp.array(truth, dtype=jnp.int32), true_position=f64(scenario.true_robot_poses[T][:2]),
    )
    return p, q


class Program:
    """``_objectives`` and its derivative, compiled once: ``values(p, q)`` and ``jacobian(p, q, directions)``,
    the derivative ``∂F/∂p · v`` of the four functionals along each direction ``v``."""

    def __init__(self, weights: str, mode: str, p, q):
        self.mode = mode
        if mode == "forward":
            fn = lambda p, t, q: jax.jvp(lambda p: _objectives(p, q, weights), (p,), (t,), has_aux=True)  # noqa: E731
            args = (p, jax.tree.map(jnp.zeros_like, p), q)
        else:

            def combination(p, c, q):  # c @ functionals: one compiled gradient serves every functional
                values, aux = _objectives(p, q, weights)
                return c @ values, (values, aux)

            fn = jax.value_and_grad(combination, has_aux=True)
            args = (p, jnp.zeros(len(FUNCTIONALS)), q)
        with _fast_compile():
            self.compiled = jax.jit(fn).lower(*args).compile()

    def values(self, p, q):
        """Functionals and the discrete choices."""
        if self.mode == "forward":
            values, _, aux = self.compiled(p, jax.tree.map(np.zeros_like, p), q)
        else:
            (_, (values, aux)), _ = self.compiled(p, np.zeros(len(FUNCTIONALS)), q)
        return np.asarray(values), aux

    def jacobian(self, p, q, directions):
        """``(len(directions), 4)``: the derivative of every functional along every direction."""
        if self.mode == "forward":
            return np.stack([np.asarray(self.compiled(p, v, q)[1]) for v in directions])
        grads = [self.compiled(p, c, q)[1] for c in np.eye(len(FUNCTIONALS))]
        dot = lambda g, v: sum(float(np.vdot(a, b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v)))  # noqa: E731
        return np.array([[dot(g, v) for g in grads] for v in directions])


# laplace-is is left out for the suite's time: its draws are reparameterized like sampled's, and its
# mode search is the same implicit-adjoint Gauss-Newton as the update, which linearized exercises.
PROGRAMS = {"linearized": "forward", "sampled": "reverse"}


@pytest.fixture(scope="module")
def programs():
    p, q = _ambiguous_scene()
    return {w: Program(w, mode, p, q) for w, mode in PROGRAMS.items()}


def _directions(p):
    """Unit directions: every entry of every input (symmetric pairs for covariances), object means of
    the two nearby objects and one far one. Yields ``(label, step, tangent)`` (numpy: no dispatch cost)."""
    zero = {k: np.zeros_like(v) for k, v in p.items()}
    for name, x in p.items():
        x = np.asarray(x)
        if name == "object_means":
            index = [(i, j) for i in (0, 1, 2) for j in range(3)]
        elif name.endswith("cov"):
            index = [(i, j) for i in range(x.shape[0]) for j in range(i, x.shape[1])]
        else:
            index = list(np.ndindex(x.shape))
        for ix in index:
            v = np.zeros_like(x)
            v[ix] = 1.0
            if name.endswith("cov"):
                v = np.maximum(v, v.T)
            # Central differences: truncation ~h², rounding and solver noise ~1e-13/h: h ≈ 1e-5 relative.
            yield f"{name}{list(ix)}", 1e-5 * max(abs(float(x[ix])), 0.1), {**zero, name: v}


def _finite_differences(program, p, q):
    p = jax.tree.map(np.asarray, p)
    labels, fd, tangents = [], [], []
    _, choice = program.values(p, q)
    for label, h, v in _directions(p):
        (plus, c_plus), (minus, c_minus) = (program.values(jax.tree.map(lambda a, b: a + s * h * b, p, v), q) for s in (1, -1))
        for a, b, c in zip(choice, c_plus, c_minus):  # the discrete choices did not change within ±h
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=label)
            np.testing.assert_array_equal(np.asarray(a), np.asarray(c), err_msg=label)
        labels.append(label)
        fd.append((plus - minus) / (2 * h))
        tangents.append(v)
    return labels, np.stack(fd), program.jacobian(p, q, tangents)


@pytest.mark.slow  # the two programs compile for a minute (the fixture); the suite's time
@pytest.mark.parametrize("weights", list(PROGRAMS))
def test_gradients_match_finite_differences(programs, weights):
    """Relative error ≤ 1e-3 on every (input entry, functional) pair; a derivative much smaller than the
    functional's largest (e.g. exactly 0 for the far object) is compared at 1e-3 of that scale."""
    p, q = _ambiguous_scene()
    values, (history, _, ignored) = programs[weights].values(p, q)
    assert np.all(np.isfinite(values)) and not np.any(ignored)
    assert len({tuple(h.ravel()) for h in np.asarray(history)}) >= 3  # distinct association hypotheses
    labels, fd, ad = _finite_differences(programs[weights], p, q)
    scale = np.maximum(np.abs(fd), 1e-3 * np.max(np.abs(fd), axis=0))
    rel = np.abs(ad - fd) / scale
    worst = np.unravel_index(np.argmax(rel), rel.shape)
    print(f"{weights}: max relative error {rel.max():.1e} ({labels[worst[0]]}, {FUNCTIONALS[worst[1]]})")
    assert rel.max() <= RTOL, (labels[worst[0]], FUNCTIONALS[worst[1]], fd[worst[0]], ad[worst[0]])
    # Every input moves every functional somewhere (no path silently cut), but the far object's.
    for name in p:
        rows = [i for i, label in enumerate(labels) if label.startswith(name) and not label.startswith("object_means[2")]
        assert np.any(np.abs(fd[rows]) > 1e-4), name


@pytest.mark.slow
@pytest.mark.parametrize("temperature", [(0.3, 0.05), (0.0, 0.0)], ids=["smooth", "hard"])
def test_gradients_are_finite_on_the_paper_setup(programs, temperature):
    p, q = _paper_scene(temperature)
    for weights, program in programs.items():
        values, _ = program.values(p, q)
        jac = program.jacobian(p, q, [t for _, _, t in _directions(p)])
        assert np.all(np.isfinite(values[[0, 2, 3]])), weights  # the truth's history may be pruned: +inf
        assert np.all(np.isfinite(jac)), (weights, jac)
        assert np.any(jac != 0.0), weights


@pytest.mark.slow
def test_smooth_visibility_explains_what_the_hard_model_cannot(programs):
    """Two detections but one object in view: no hypothesis is possible under the 0/1 model (the step
    falls back to ignoring visibility); the smooth model weighs every hypothesis, with finite gradients.
    (``linearized`` averages the 0/1 model over a Gaussian predictive: never exactly impossible.)"""
    p, q = _ambiguous_scene()
    p["object_means"] = p["object_means"].at[1].set(f64([-3.0, 2.0, 0.3]))  # behind the robot
    for weights, program in programs.items():
        for temperature, ignored in (((0.0, 0.0), weights != "linearized"), ((0.3, 0.05), False)):
            pt = {**p, "temperature": f64(temperature)}
            values, (_, _, flags) = program.values(pt, q)
            assert bool(flags[1]) == ignored and not bool(flags[0]), (weights, temperature)
            jac = program.jacobian(pt, q, [t for _, _, t in _directions(pt)][::4])
            assert np.all(np.isfinite(jac)), (weights, temperature)


def test_smooth_visibility_model():
    @jax.jit
    def check(rb, tau):
        """log P(visible) at the temperatures, the hard footprint, and d/d(range, bearing)."""
        f = jax.vmap(log_smooth_visibility, (None, None, None, 0))
        hard = jnp.where(visible(rb, 5.0, 1.6), 0.0, -jnp.inf)
        return f(rb, 5.0, 1.6, tau), hard, jax.jacfwd(f)(rb, 5.0, 1.6, tau)

    tau = f64([[0.5, 0.1], [0.0, 0.0], [1e-4, 1e-4]])
    logp, hard, grad = check(f64([4.0, 0.3]), tau)
    expect = jax.nn.log_sigmoid(1.0 / 0.5) + jax.nn.log_sigmoid(0.5 / 0.1) + jax.nn.log_sigmoid(1.1 / 0.1)
    np.testing.assert_allclose(logp[0], expect, rtol=1e-14)
    # Temperature 0 is the paper's footprint (with zero gradient); small temperatures approach it.
    for rb in [(4.0, 0.3), (5.5, 0.3), (4.0, -0.9), (4.0, 0.79), (4.0, -3.1)]:
        logp, hard, grad = check(f64(rb), tau)
        assert float(logp[1]) == float(hard)
        np.testing.assert_allclose(np.exp(logp[2]), np.exp(hard), atol=1e-6)
        assert np.all(np.isfinite(grad)) and not np.any(grad[1])
    # Even in the bearing (so smooth at 0) and so continuous across ±π.
    for b in (0.2, 3.1):
        np.testing.assert_allclose(check(f64([4.0, b]), tau)[0], check(f64([4.0, -b]), tau)[0], rtol=1e-14)
    assert float(check(f64([4.0, 0.0]), tau)[2][0, 1]) == 0.0


def test_model_keeps_the_hard_visibility_by_default(unchecked_types, scenario):
    model = hs.model_from_scenario(scenario)
    assert model.sensor.visibility_temperature is None
    sensor = hs.SensorModel(model.sensor.geometric_cov, model.sensor.classifier, model.sensor.max_range, model.sensor.fov)
    assert sensor.visibility_temperature is None
    smooth = hs.model_from_scenario(scenario, visibility_temperature=0.3)
    np.testing.assert_allclose(smooth.sensor.visibility_temperature, [0.3, 0.3 / scenario.max_range])
    both = hs.with_smooth_visibility(model, 0.3, 0.05)
    np.testing.assert_allclose(both.sensor.visibility_temperature, [0.3, 0.05])
    np.testing.assert_allclose(hs.with_smooth_visibility(model.sensor, 0.2, 0.1).visibility_temperature, [0.2, 0.1])
    with pytest.raises(ValueError, match="visibility_temperature"):
        hs.model_from_scenario(scenario, visibility_temperature=(0.1, 0.2, 0.3))


def test_functionals():
    """The functionals against direct computations on a multi-hypothesis belief."""
    p, q = _ambiguous_scene()
    priors = hs.Priors(p["robot_mean"], q["robot_cov"], p["object_means"], q["object_covs"])
    sensor = hs.SensorModel(p["geometric_cov"], Mirror(p["alpha"], p["K"]), q["max_range"], q["fov"], p["temperature"])
    model = hs.Model(p["motion_cov"], sensor, q["class_prior"], q["prune_ratio"])
    belief = init_belief(priors, model, 4, T, 2)
    # Four components with hand-set weights, means, covariances and histories.
    w = np.array([0.5, 0.3, 0.2, 0.0])
    hist = np.full(belief.history.shape, -1, np.int32)
    hist[:, 0, 0] = [0, 1, 0, 1]
    hist[:, 1, 0] = [1, 0, 0, 0]
    hist[2, 1, 0] = 1  # components 0 and 2 share the history [[0], [1]]
    hist[3, 1, 0] = 2
    mean = np.array(belief.mean)
    mean[:, :2] = [[1.0, 0.0], [1.2, 0.3], [0.8, -0.1], [9.0, 9.0]]
    cov = np.array(belief.cov)
    cov[0, :3, :3] = [[0.2, 0.05, 0.0], [0.05, 0.1, 0.01], [0.0, 0.01, 0.03]]
    belief = hs.Belief(jnp.log(f64(w)), f64(mean), f64(cov), belief.classes, jnp.asarray(hist), jnp.asarray(2, jnp.int32),
                       model)
    truth = f64([1.0, 0.1])

    @jax.jit
    def evaluate(log_weights, mean, cov):
        b = hs.Belief(log_weights, mean, cov, belief.classes, belief.history, belief.k, model)
        return jnp.stack([
            expected_association_entropy(b),
            hypothesis_neg_log_weight(b, jnp.asarray(hist[0])), hypothesis_neg_log_weight(b, jnp.asarray(hist[1, :1])),
            hypothesis_neg_log_weight(b, jnp.asarray(hist[3])),  # only on a dead slot
            best_pose_log_det(b), best_pose_log_det(b, position_only=True),
            expected_position_error(b, truth), expected_position_error(b, truth, squared=True),
        ]), hs.metrics(b, jnp.r_[truth, 0.0])

    values, metrics = evaluate(belief.log_weights, belief.mean, belief.cov)
    err = np.linalg.norm(mean[:3, :2] - np.array([1.0, 0.1]), axis=1)
    sq = err**2 + np.trace(cov[:3, :2, :2], axis1=1, axis2=2)
    expect = [
        -(0.7 * np.log(0.7) + 0.3 * np.log(0.3)), -np.log(0.7), -np.log(0.3), np.inf,
        np.linalg.slogdet(cov[0, :3, :3])[1], np.linalg.slogdet(cov[0, :2, :2])[1], w[:3] @ err, w[:3] @ sq,
    ]
    np.testing.assert_allclose(values, expect, rtol=1e-13)
    np.testing.assert_allclose([values[0], values[6]], [metrics.entropy, metrics.err_wavg], rtol=1e-13)  # the metrics
    # Gradients are finite, also for the +inf of an absent hypothesis (zero) and at the true position
    # itself, where the distance has no derivative (zero, not NaN).
    at_truth = belief.mean.at[0, :2].set(truth)
    jac = jax.jacrev(lambda *a: evaluate(*a)[0], argnums=(0, 1, 2))(belief.log_weights, at_truth, belief.cov)
    assert all(bool(jnp.all(jnp.isfinite(j))) for j in jac)
    assert not np.any(np.asarray(jac[0][3]))


# --------------------------------------------------------------------------------------------
# Through the smoothers (implicit differentiation of the Levenberg-Marquardt solution)
# --------------------------------------------------------------------------------------------

# ml and gpda share max-mixture's single-Gaussian step and its class update (checked by hand: 2e-8 to
# 4e-8 filter, 4e-6 full; docs/gradients.md), left out for the suite's time. The smoother's own
# implicit derivative (the solve's custom_jvp rule, its transpose and the marginal) is checked where it
# lives, tests/test_smoother.py::test_derivatives_of_a_nonlinear_solution_and_its_marginal_match_finite_differences
# (reverse mode there: the transpose of that rule); each case here adds an estimator's path into and out of
# it: the hybrid belief's per-component solve (the graph built from the histories and the smoothed
# marginal's use in the weights) through the fixed-lag window with its marginalized prior (`Lag(1)`: the
# window slides at step 2), the whole-trajectory solve (`Full()`) through the single-Gaussian estimators'
# max-mixture factors and multimodal's clusters. (The hybrid belief with `Full()` builds its graph and uses
# its marginal as with `Lag`, and solves as max-mixture does with `Full()`: left out for the suite's time.) All in
# forward mode, one random direction (a jvp, no batching: the smallest program that checks the tangents;
# half the compile of the pullback). Reverse mode through the hybrid scan (what jax.grad does, transposed
# through the scan) is checked by ``test_gradients_match_finite_differences[sampled]``; ``"reverse"`` in
# ``SMOOTHED`` still selects one pullback per functional.
SMOOTHED = {"hybrid, lag:1": ("hybrid", "lag:1", "forward"),
            "max-mixture, full": ("max-mixture", "full", "forward"),
            "multimodal, full": ("multimodal", "full", "forward")}


@pytest.mark.slow  # one program per case, 15-40 s to compile
@pytest.mark.parametrize("case", list(SMOOTHED))
def test_gradients_through_the_smoothers_match_finite_differences(case):
    """Reverse or forward mode (``SMOOTHED``) through two steps of a smoother estimator (the paper setup; every component
    re-solves its trajectory by Levenberg-Marquardt each step) along random directions of the odometry,
    Σ_v, Σ_w, alpha and K, against central differences: relative error ≤ 1e-3 (``RTOL``), with the
    discrete choices (histories, surviving components) unchanged within ±h."""
    name, smoother, mode = SMOOTHED[case]
    scenario = hs.simulate(0, steps=T)
    # The mixtures with 4 component slots (their default: 64): the same program, which runs several
    # times faster (each evaluation of the finite differences too).
    options = {"hybrid": dict(weights="linearized", capacity=4), "multimodal": dict(capacity=4)}.get(name, {})
    estimator = hs.make_estimator(name, smoother=smoother, **options)
    state0 = estimator.init(scenario)
    stacked = hs.stack_steps(scenario, int(estimator.view(state0).history.shape[-1]))
    detections, truth = hs.stacked_detections(stacked), f64(scenario.true_robot_poses[T][:2])
    model = state0.model
    p = {"odometry": f64(stacked.odometry), "geometric_cov": model.sensor.geometric_cov,
         "motion_cov": model.motion_cov, "alpha": model.sensor.classifier.alpha,
         "K": model.sensor.classifier.K}
    p = jax.tree.map(np.asarray, p)  # the compiled program's argument types, also at p ± h·v

    def functionals(p):
        state = eqx.tree_at(lambda s: (s.model.sensor.geometric_cov, s.model.motion_cov,
                                       s.model.sensor.classifier.alpha, s.model.sensor.classifier.K),
                            state0, (p["geometric_cov"], p["motion_cov"], p["alpha"], p["K"]))
        inputs = hs.Inputs(p["odometry"], detections, jnp.arange(T, dtype=jnp.int32),
                           jnp.full((T, 3), jnp.nan), jnp.ones(T, bool))
        state, trace = hs.scan(estimator, state, inputs, jax.random.PRNGKey(0))
        view = estimator.view(state)
        w = jax.nn.softmax(view.log_weights)
        best = jnp.argmax(view.log_weights)
        values = jnp.stack([jnp.sum(w * jnp.linalg.norm(view.mean[:, :2] - truth[None], axis=-1)),
                            jnp.linalg.slogdet(view.cov[best])[1], jnp.sum(w * view.mean[:, 2])])
        return values, (view.history, view.log_weights > -jnp.inf)

    rng = np.random.default_rng(0)
    directions = []
    for _ in range(2 if mode == "reverse" else 1):
        v = {k: rng.normal(size=np.shape(x)) * 0.1 * (np.abs(np.asarray(x)) + 0.01) for k, x in p.items()}
        for k in ("geometric_cov", "motion_cov"):
            v[k] = (v[k] + v[k].T) / 2
        directions.append(v)

    def value_and_derivative(p, v):
        """The functionals, the discrete choices, and: in forward mode their derivative along ``v`` (one
        jvp), in reverse mode the gradient of ``v @ functionals`` (one pullback, what ``jax.grad``
        builds). One program, also for the finite differences' evaluations: each case compiles once."""
        if mode == "reverse":
            values, pullback, aux = jax.vjp(functionals, p, has_aux=True)
            return values, aux, pullback(v)[0]
        values, tangent, aux = jax.jvp(functionals, (p,), (v,), has_aux=True)
        return values, aux, tangent

    with _fast_compile():
        program = jax.jit(value_and_derivative).lower(p, directions[0] if mode == "forward" else np.eye(3)[0]).compile()
    if mode == "forward":
        values, choice, tangent = program(p, directions[0])
        derivatives = np.asarray(tangent)[None]
        value = lambda q: program(q, directions[0])[:2]  # noqa: E731
    else:
        rows = [program(p, c) for c in np.eye(3)]  # ∂F_i/∂p: one pullback per functional
        values, choice = rows[0][:2]
        dot = lambda g, v: sum(float(np.vdot(np.asarray(g[k]), v[k])) for k in p)  # noqa: E731
        derivatives = np.array([[dot(r[2], v) for r in rows] for v in directions])
        value = lambda q: program(q, np.eye(3)[0])[:2]  # noqa: E731
    assert np.all(np.isfinite(np.asarray(values)))
    h = 1e-4
    for v, ad in zip(directions, derivatives):
        shifted = (jax.tree.map(lambda a, b: a + s * h * b, p, v) for s in (1, -1))
        (plus, c_plus), (minus, c_minus) = (value(q) for q in shifted)
        for a, b, c in zip(jax.tree.leaves(choice), jax.tree.leaves(c_plus), jax.tree.leaves(c_minus)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
        fd = np.asarray(plus - minus) / (2 * h)
        np.testing.assert_allclose(ad, fd, rtol=RTOL, atol=RTOL * np.max(np.abs(fd)), err_msg=case)
        assert np.any(np.abs(fd) > 1e-6)
