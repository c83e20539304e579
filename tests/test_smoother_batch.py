"""The smoothed trajectory of a run equals an independent batch nonlinear least-squares solve.

With the associations fixed (those in the run's own result file), the factor graph of the ``ml``
smoother is rebuilt here from the scenario file alone, with residuals written in numpy (prior on
``[x_0, objects]`` with wrapped headings, GTSAM's ``BetweenFactor<Pose2>`` odometry residual
``Log(u⁻¹ ∘ x_{k-1}⁻¹ ∘ x_k)``, range and bearing of the object's position), and solved from dead
reckoning by scipy's Levenberg-Marquardt. The result file's ``trajectory`` and ``objects`` must
equal that solution to 1e-6 (issue 13 §4).

The fixed-lag smoother (``smoother=Lag(L)``) on the same run: a window as long as the run is this
smoother; a short one freezes the poses that left it and stays close to it (tests/test_lag.py
has the mixtures and the option's errors).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import least_squares

import hybridslam as hs
from hybridslam.estimators.smoothers.kinds import FINAL_ATOL, Incremental, Lag
from hybridslam.io.scenario import Classifier
from hybridslam.sim.hallway import hallway


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _compose(a, b):
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], _wrap(a[2] + b[2])])


def _inverse(a):
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2]])


def _log(p):
    theta = _wrap(p[2])
    if abs(theta) < 1e-9:
        a, b = 1.0, 0.5 * theta
    else:
        a, b = np.sin(theta) / theta, (1 - np.cos(theta)) / theta
    v_inv = np.array([[a, b], [-b, a]]) / (a * a + b * b)
    return np.concatenate([v_inv @ p[:2], [theta]])


def _sqrt_info(cov):
    return np.linalg.cholesky(np.linalg.inv(cov)).T  # RᵀR = Σ⁻¹


def _residual_function(scenario, history, num_objects=None):
    """The residuals of the graph of ``scenario`` with the associations ``history`` (per step, per
    detection; −1: none) over ``[poses (T+1, 3), objects (N, 3)]``. ``num_objects``: ``N``, the
    scenario's objects and then those a run created (an unknown map's), whose prior is on the
    heading only (``N(0, new_object_orientation_var)``, the package's convention for a created slot)."""
    t, known = scenario.num_steps, scenario.num_objects
    n = known if num_objects is None else num_objects
    w_odo, w_geo = _sqrt_info(scenario.motion_cov), _sqrt_info(scenario.geometric_cov)
    prior_mean = np.zeros(3 + 3 * n)
    prior_mean[:3] = scenario.robot_prior_mean
    prior_mean[3 : 3 + 3 * known] = np.reshape(scenario.object_prior_means, -1)
    w_prior = np.zeros((3 + 3 * n, 3 + 3 * n))
    w_prior[:3, :3] = _sqrt_info(scenario.robot_prior_cov)
    for i in range(known):
        w_prior[3 + 3 * i : 6 + 3 * i, 3 + 3 * i : 6 + 3 * i] = _sqrt_info(scenario.object_prior_covs[i])
    for i in range(known, n):
        w_prior[5 + 3 * i, 5 + 3 * i] = 1.0 / np.sqrt(scenario.discovery.new_object_orientation_var)
    factors = [(k + 1, obj, np.array([d.range, d.bearing]))
               for k, (step, assoc) in enumerate(zip(scenario.steps, history))
               for d, obj in zip(step.detections, assoc) if obj >= 0]
    assert len(factors) > 4

    def residuals(y):
        poses, objects = y[: 3 * (t + 1)].reshape(t + 1, 3), y[3 * (t + 1) :].reshape(n, 3)
        d = np.concatenate([poses[0], objects.reshape(-1)]) - prior_mean
        d[2::3] = _wrap(d[2::3])
        out = [w_prior @ d]
        for k, step in enumerate(scenario.steps, start=1):
            between = _compose(_inverse(poses[k - 1]), poses[k])
            out.append(w_odo @ _log(_compose(_inverse(np.asarray(step.odometry)), between)))
        for k, obj, z in factors:
            dx, dy = objects[obj, :2] - poses[k, :2]
            pred = np.array([np.hypot(dx, dy), np.arctan2(dy, dx) - poses[k, 2]])
            r = z - pred
            r[1] = _wrap(r[1])
            out.append(w_geo @ r)
        return np.concatenate(out)

    return residuals, prior_mean


def _least_squares(residuals, y0, t):
    sol = least_squares(residuals, y0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=10000)
    poses = sol.x[: 3 * (t + 1)].reshape(t + 1, 3)
    poses[:, 2] = _wrap(poses[:, 2])
    return poses, sol.x[3 * (t + 1) :].reshape(-1, 3)


def _batch_solve(scenario, history) -> tuple[np.ndarray, np.ndarray]:
    """The graph of ``scenario`` with the associations ``history`` (per step, per detection; −1: none),
    solved from dead reckoning by scipy's Levenberg-Marquardt: the poses ``(T+1, 3)`` and the
    objects ``(N, 3)``."""
    residuals, prior_mean = _residual_function(scenario, history)
    dead_reckoning = [np.asarray(scenario.robot_prior_mean, float)]
    for step in scenario.steps:
        dead_reckoning.append(_compose(dead_reckoning[-1], np.asarray(step.odometry, float)))
    y0 = np.concatenate([np.reshape(dead_reckoning, -1), prior_mean[3:]])
    return _least_squares(residuals, y0, scenario.num_steps)


def _solve_from_the_result(scenario, run) -> tuple[np.ndarray, np.ndarray]:
    """The graph rebuilt from the result's top component's associations (objects: the result's
    count), solved by scipy's Levenberg-Marquardt from the result's own ``trajectory`` and ``objects``:
    a result that describes its solution does not move."""
    objects = np.asarray(run.result.objects, float)
    residuals, _ = _residual_function(scenario, run.result.steps[-1].components[0].associations, len(objects))
    y0 = np.concatenate([np.reshape(run.result.trajectory, -1), objects.reshape(-1)])
    return _least_squares(residuals, y0, scenario.num_steps)


def _assert_trajectory_is(run, solution):
    poses, objects = solution
    smoothed = np.asarray(run.result.trajectory)
    assert smoothed.shape == poses.shape
    np.testing.assert_allclose(smoothed[:, :2], poses[:, :2], atol=1e-6)
    np.testing.assert_allclose(_wrap(smoothed[:, 2] - poses[:, 2]), 0.0, atol=1e-6)
    # The result file's objects are that solution's too (headings: the prior's, unobserved).
    mapped = np.asarray(run.result.objects)
    assert mapped.shape == objects.shape
    np.testing.assert_allclose(mapped[:, :2], objects[:, :2], atol=1e-6)
    np.testing.assert_allclose(_wrap(mapped[:, 2] - objects[:, 2]), 0.0, atol=1e-6)
    # ... and it is the online estimate at the last step (the smoother's x_T).
    np.testing.assert_allclose(run.result.steps[-1].components[0].pose_mean, smoothed[-1], atol=1e-9)


def test_ml_trajectory_equals_a_batch_least_squares_solve():
    scenario = hs.simulate(0, steps=6)
    run = hs.run_estimator(scenario, "ml")  # smoother=Full() by default
    assert all(int(i.skipped) == 0 and int(i.rejected) == 0 for i in run.infos)  # every detection has a factor
    _assert_trajectory_is(run, _batch_solve(scenario, run.result.steps[-1].components[0].associations))


@pytest.mark.slow  # the hybrid belief's smoother compile, 20 s: the extended suite, CI
def test_hybrid_trajectory_equals_a_batch_least_squares_solve():
    """The hybrid belief's best component, where components that differ only in their classes share
    one smoothing (a viewpoint-independent classifier: the classes do not move the solution)."""
    scenario = hs.simulate(0, steps=6)  # scores too noisy (K = 1) to settle the classes: 8 components
    scenario = dataclasses.replace(scenario, classifier=Classifier("independent", alpha=0.25, K=1.0))
    run = hs.run_estimator(scenario, "hybrid", capacity=8, weights="linearized")
    assert any(int(i.details.smoothings) < int(i.num_components) for i in run.infos)  # copies were made
    _assert_trajectory_is(run, _batch_solve(scenario, run.result.steps[-1].components[0].associations))


def _moves(scenario, run) -> tuple[float, float]:
    """How far Levenberg-Marquardt on the graph rebuilt from ``run``'s result file moves its
    trajectory from where the file says it is: metres, radians."""
    poses, _ = _solve_from_the_result(scenario, run)
    smoothed = np.asarray(run.result.trajectory)
    return (float(np.max(np.linalg.norm(poses[:, :2] - smoothed[:, :2], axis=1))),
            float(np.max(np.abs(_wrap(poses[:, 2] - smoothed[:, 2])))))


@pytest.mark.parametrize("name", ["ml", "max-mixture"])
def test_the_result_file_describes_its_own_solution_on_an_unknown_map(name):
    """A simulated hallway (20 steps, noisy odometry tr(Λ) = 0.05, objects created as they are
    seen): the graph rebuilt from the top component's associations, started at the file's trajectory
    and map, is already at its optimum. For max-mixture the associations must be the components
    active at that solution (Eq. 4.16): those chosen online, at each step's estimate, moved this
    trajectory by 0.47 m and 0.045 rad; the components at the solution move it by 1.4e-6 m, as much
    as ``ml``'s (1.3e-6 m): the smoother stops within ``FINAL_ATOL`` nats of the optimum, about
    ``√(2·FINAL_ATOL) ≈ 5e-5`` standard deviations. (gpda's factors are weighted sums over candidates
    whose weights a result file does not carry: its graph cannot be rebuilt from the file.)"""
    scenario = hallway(0, 0.05, steps=20)
    run = hs.run_estimator(scenario, name)  # smoother=Full() by default
    metres, radians = _moves(scenario, run)
    assert metres < 1e-5 and radians < 1e-5, (metres, radians)


def _incremental_and_lag(scenario, name, length):
    """``name`` run with ``Incremental(length)`` and with ``Lag(length)``, and how far each result's
    graph, rebuilt and solved, moves its trajectory (metres, radians)."""
    runs = [hs.run_estimator(scenario, name, smoother=s) for s in (Incremental(length), Lag(length))]
    return runs, [_moves(scenario, r) for r in runs]


def test_incremental_steps_as_the_lag_and_ends_at_the_batch_solution():
    """``incremental:3`` on the hallway of the test above: every step before the last is ``lag:3``'s
    (the same online estimates), and the last re-solves the whole graph, so the result file's
    trajectory is that graph's optimum; ``lag:3``'s, whose old poses stay where they left the
    window, is not (it moves by tenths of a metre)."""
    scenario = hallway(0, 0.05, steps=20)
    (inc, lag), (inc_moves, lag_moves) = _incremental_and_lag(scenario, "ml", 3)
    for a, b in zip(inc.result.steps[:-1], lag.result.steps[:-1], strict=True):
        np.testing.assert_allclose(a.components[0].pose_mean, b.components[0].pose_mean, rtol=0, atol=1e-9)
    assert inc_moves[0] < 1e-5 and inc_moves[1] < 1e-5, inc_moves
    assert lag_moves[0] > 0.1, lag_moves


@pytest.mark.slow  # their own compiles, 20 s each: the extended suite, CI
@pytest.mark.parametrize("name", ["max-mixture", "hybrid", "multimodal"])
def test_incremental_ends_at_the_batch_solution_for_the_mixtures(name):
    """As above for max-mixture (its associations rewritten by the closing solve, as the full
    smoother's), and the hybrid belief's and ``multimodal``'s top component (``lag:3`` leaves them
    1e-3 m and 0.67 m from it)."""
    scenario = hallway(0, 0.05, steps=20)
    metres, radians = _moves(scenario, hs.run_estimator(scenario, name, smoother=Incremental(3)))
    assert metres < 1e-5 and radians < 1e-5, (metres, radians)


# Fixed lag (sharing the compiled full-smoother step above)

STEPS = 6


def _first_steps(scenario, k):
    """The scenario cut after ``k`` steps."""
    return dataclasses.replace(scenario, steps=scenario.steps[:k], true_robot_poses=scenario.true_robot_poses[: k + 1])


@pytest.mark.slow  # its own lag compile, 20 s: the extended suite, CI
def test_a_window_as_long_as_the_run_is_the_full_smoother():
    """``Lag(L)`` with ``L`` the run's steps never marginalizes: it is the full smoother."""
    scenario = hs.simulate(0, steps=STEPS)
    full = hs.run_estimator(scenario, "ml")  # the compiled step of the test above
    lag = hs.run_estimator(scenario, "ml", smoother=Lag(STEPS))
    np.testing.assert_allclose(lag.result.trajectory, full.result.trajectory, atol=1e-12)
    for a, b in zip(lag.result.steps, full.result.steps):
        np.testing.assert_allclose(a.components[0].pose_mean, b.components[0].pose_mean, atol=1e-12)
        np.testing.assert_allclose(a.components[0].pose_cov, b.components[0].pose_cov, atol=1e-12)


def _lag2(scenario):
    """``ml`` with ``Lag(2)``, its shapes fixed (every cut of the scenario shares one compile), every
    step solved to the last step's tolerance (a cut's last step is solved tighter than the others)."""
    return hs.make_estimator("ml", smoother=Lag(2, step_atol=FINAL_ATOL), max_steps=STEPS,
                             max_detections=max(scenario.max_detections, 1))


@pytest.mark.slow  # its own lag:2 compiles, 20 s: the extended suite, CI
def test_poses_that_left_the_window_keep_their_last_smoothed_value():
    """With ``Lag(2)`` pose ``j`` is last re-solved at step ``j + 2`` and marginalized at ``j + 3``."""
    scenario = hs.simulate(0, steps=STEPS)
    est = _lag2(scenario)
    traj = {k: hs.run_estimator(_first_steps(scenario, k), est).result.trajectory for k in range(2, STEPS + 1)}
    for k in range(3, STEPS + 1):
        for j in range(0, k - 2):
            np.testing.assert_array_equal(traj[k][j], traj[min(j + 2, STEPS)][j], err_msg=f"pose {j} after step {k}")
        assert not np.array_equal(traj[k][k], traj[k - 1][k - 1])  # the window still moves


def test_a_short_window_stays_close_to_the_full_smoother():
    """Marginalizing at the current estimate is the fixed-lag approximation: the online estimate
    moves by a small fraction of its standard deviation (a dropped window prior would not)."""
    scenario = hs.simulate(0, steps=STEPS)
    full = hs.run_estimator(scenario, "ml")
    lag = hs.run_estimator(scenario, _lag2(scenario))
    for a, b in zip(lag.result.steps, full.result.steps):
        sd = np.sqrt(np.diag(b.components[0].pose_cov))
        assert np.all(np.abs(a.components[0].pose_mean - b.components[0].pose_mean) < 0.1 * sd), (a.k, sd)
