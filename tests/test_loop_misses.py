"""Negative information of the loop-closure search (hybridslam.estimators.loops.misses): the
probability that an object was in view under the solved graph's covariance, against a numpy
reimplementation from the dense ``H⁻¹`` and against the point test in the limit of no uncertainty;
the log-likelihood of the undetected pairs, by hand and as properties."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from hybridslam.estimators.loops import misses as loop_misses, verify as loop_verify
from hybridslam.estimators.loops.settings import LoopClosureSettings
from hybridslam.inference import smoother as sm
from hybridslam.sim.hallway import hallway

from .test_smoother import N, P, _graph, exact_solve

FOOTPRINT = (1.2, 2.0)  # m, rad: objects of the random graph lie near the edges of it


def _range_bearing(z):
    x, o = z[:3], z[3:5]
    d = o - x[:2]
    b = math.atan2(d[1], d[0]) - x[2]
    return np.array([math.hypot(d[0], d[1]), math.atan2(math.sin(b), math.cos(b))])


def _phi(v):
    return 0.5 * (1.0 + math.erf(v / math.sqrt(2.0)))


def _reference(sol, max_range, fov):
    """The in-view probability from the dense ``H⁻¹`` and central differences, in numpy."""
    h, _ = sol.linearization.dense()
    cov = np.linalg.inv(np.asarray(h))
    poses, objects = np.asarray(sol.poses), np.asarray(sol.objects)
    out = np.zeros((P, N))
    for t in range(P):
        for j in range(N):
            z = np.concatenate([poses[t], objects[j, :2]])
            idx = np.concatenate([np.arange(3 * t, 3 * t + 3), 3 * P + 3 * j + np.arange(2)])
            jac = np.stack([(_range_bearing(z + e) - _range_bearing(z - e)) / 2e-6 for e in np.eye(5) * 1e-6], axis=1)
            var = np.diag(jac @ cov[np.ix_(idx, idx)] @ jac.T)
            r, b = _range_bearing(z)
            sr, sb = np.sqrt(var)
            out[t, j] = _phi((max_range - r) / sr) * (_phi((fov / 2 - b) / sb) - _phi((-fov / 2 - b) / sb))
    return out


@pytest.fixture(scope="module")
def solved():
    """A solved random graph (its ``H``) with the poses along a line and the objects beside it, so
    that ranges are 0.3-2 m and bearings spread: the footprint's edges cut through the estimates."""
    graph = _graph(np.random.default_rng(11), linear=False)
    sol = exact_solve(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    poses = np.stack([np.linspace(0.0, 2.0, P), np.zeros(P), np.linspace(-0.6, 0.9, P)], axis=1)
    objects = np.array([[0.5, 0.8, 0.0], [1.5, -0.4, 0.0], [2.6, 0.3, 0.0]])
    return eqx.tree_at(lambda s: (s.poses, s.objects), sol, (jnp.asarray(poses), jnp.asarray(objects)))


def test_in_view_probability_matches_the_dense_inverse(solved):
    got = np.asarray(jax.jit(loop_misses.in_view_probability)(solved, *FOOTPRINT))
    want = _reference(solved, *FOOTPRINT)
    assert 0.05 < want.min() or want.max() < 0.95 or np.ptp(want) > 0.1  # not all certain: the test has teeth
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_a_certain_estimate_gives_the_point_test(solved):
    """With the information scaled up a million-fold, the probability is the footprint's indicator at
    the estimate (margin 0), away from its edges."""
    blocks = lambda s: (s.linearization.pose_diag, s.linearization.pose_off, s.linearization.pose_object,  # noqa: E731
                        s.linearization.object)
    sharp = eqx.tree_at(blocks, solved, tuple(b * 1e6 for b in blocks(solved)))
    got = np.asarray(loop_misses.in_view_probability(sharp, *FOOTPRINT))
    scenario = hallway(0, steps=2).replace(max_range=FOOTPRINT[0], fov=FOOTPRINT[1])
    point = loop_misses.point_in_view(scenario, np.asarray(solved.poses), np.asarray(solved.objects), (0.0, 0.0))
    clear = np.abs(got - 0.5) > 0.49
    assert clear.sum() >= P * N // 2
    np.testing.assert_array_equal(np.round(got[clear]), point[clear])


def test_a_full_circle_passes_every_bearing(solved):
    got = np.asarray(loop_misses.in_view_probability(solved, 100.0, 2 * math.pi))
    np.testing.assert_allclose(got, 1.0, atol=1e-12)


def test_miss_log_likelihood_by_hand():
    in_view = np.array([[9.0, 9.0, 9.0],  # x_0: no step, never read
                        [1.0, 0.5, 0.0],
                        [0.2, 1.0, 1.0]])
    history = np.array([[0, -1], [2, -1]])  # step 1 saw object 0, step 2 object 2
    s = LoopClosureSettings(detection_probability=0.9, min_miss_probability=0.05)
    want = math.log(1 - 0.45) + math.log(1.0) + math.log(1 - 0.18) + math.log(0.1)
    assert loop_misses.miss_log_likelihood(in_view, history, 3, s) == pytest.approx(want)
    assert loop_misses.miss_log_likelihood(in_view, history, 2, s) == pytest.approx(want - math.log(1.0))
    floored = LoopClosureSettings(detection_probability=1.0, min_miss_probability=0.3)
    assert loop_misses.miss_log_likelihood(in_view, history, 3, floored) == pytest.approx(
        math.log(0.5) + math.log(0.8) + math.log(0.3))
    assert loop_misses.miss_log_likelihood(in_view, history, 3, LoopClosureSettings(detection_probability=0.0)) == 0.0


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(float, (6, 4), elements=st.floats(0.0, 1.0)), hnp.arrays(np.int64, (5, 2), elements=st.integers(-1, 3)),
       st.floats(0.01, 1.0), st.floats(1e-4, 1.0))
def test_misses_cost_more_the_surer_the_object_was_in_view(in_view, history, p, floor):
    """Non-positive; a pair made surer in view never raises it; a detected pair costs nothing; the
    point test's indicator gives the count times ``log max(1 − p_d, floor)``."""
    s = LoopClosureSettings(detection_probability=p, min_miss_probability=floor)
    ll = loop_misses.miss_log_likelihood(in_view, history, 4, s)
    assert ll <= 0.0
    surer = np.minimum(in_view + 0.3, 1.0)
    assert loop_misses.miss_log_likelihood(surer, history, 4, s) <= ll + 1e-12
    seen = np.zeros((5, 4), bool)
    for t, j in zip(*np.nonzero(history >= 0)):
        seen[t, history[t, j]] = True
    changed = in_view.copy()
    changed[1:][seen] = np.where(changed[1:][seen] > 0.5, 0.0, 1.0)
    assert loop_misses.miss_log_likelihood(changed, history, 4, s) == pytest.approx(ll)
    indicator = (in_view > 0.5).astype(float)
    count = int(np.sum(indicator[1:] * ~seen))
    assert loop_misses.miss_log_likelihood(indicator, history, 4, s) == pytest.approx(
        count * math.log(max(1 - p, floor)))


def test_a_pair_without_a_finite_probability_takes_the_point_test():
    """Where the solved covariance is not finite (a singular ``H``), those pairs are judged at the
    estimate; the others keep their marginal probability."""
    scenario = hallway(0, steps=2).replace(max_range=2.0, fov=2.0)
    poses = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    objects = np.array([[1.0, 0.0, 0.0], [0.0, 5.0, 0.0]])  # ahead of x_1, behind x_2; far to the side
    history = np.array([[-1], [-1]])
    s = LoopClosureSettings(detection_probability=0.9, min_miss_probability=0.05)
    in_view = np.array([[0.5, 0.0], [0.3, 0.2], [np.nan, 0.1]])
    got = loop_verify.misses(scenario, poses, objects, in_view, history, 2, s)
    # object 0 lies behind x_2: the point test says 0 there
    want = loop_misses.miss_log_likelihood(np.array([[0.5, 0.0], [0.3, 0.2], [0.0, 0.1]]), history, 2, s)
    assert got == pytest.approx(want)
    point = loop_verify.misses(scenario, poses, objects, in_view, history, 2, dataclasses.replace(s, misses="point"))
    assert point == pytest.approx(math.log(1 - 0.9))  # object 0 from x_1 only
    # the point test needs no probabilities (a solve skips them); the marginal one refuses to go without
    assert loop_verify.misses(scenario, poses, objects, None, history, 2, dataclasses.replace(s, misses="point")) == point
    assert not loop_misses.uses_marginal(dataclasses.replace(s, misses="point"))
    assert not loop_misses.uses_marginal(dataclasses.replace(s, detection_probability=0.0))
    with pytest.raises(ValueError, match="in_view"):
        loop_verify.misses(scenario, poses, objects, None, history, 2, s)
