"""Merging equivalent components (hybridslam.inference.merging) and the hybrid belief's ``merge_threshold``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridslam as hs
from hybridslam.inference.merging import merge_equivalent, squared_distances

_merge = jax.jit(merge_equivalent)


def _reference(log_w, mean, cov, same, threshold):
    """Greedy in rank order (weight, then slot): each component joins the first survivor above it that
    is equivalent to it, else survives."""
    order = sorted(np.flatnonzero(np.isfinite(log_w)), key=lambda i: (-log_w[i], i))
    out = np.full_like(log_w, -np.inf)
    survivors: list[int] = []
    for i in order:
        for j in survivors:
            d = mean[i] - mean[j]
            if same[i, j] and d @ np.linalg.solve(cov[j], d) <= threshold:
                out[j] = np.logaddexp(out[j], log_w[i])
                break
        else:
            survivors.append(i)
            out[i] = log_w[i]
    return out


def test_squared_distances_are_mahalanobis_under_the_second_component():
    mean = np.array([[0.0, 0.0], [1.0, 2.0]])
    cov = np.array([np.diag([1.0, 4.0]), np.diag([0.25, 1.0])])
    d2 = np.asarray(squared_distances(jnp.asarray(mean), jnp.asarray(cov)))
    np.testing.assert_allclose(d2, [[0.0, 1 / 0.25 + 4 / 1.0], [1 / 1.0 + 4 / 4.0, 0.0]])


def test_headings_across_pi_are_close():
    """A heading of π − 0.01 and one of −π + 0.01 are 0.02 rad apart, not 2π − 0.02."""
    mean = np.array([[0.0, 0.0, np.pi - 0.01], [0.0, 0.0, -np.pi + 0.01]])
    cov = np.tile(np.diag([1.0, 1.0, 0.01]), (2, 1, 1))
    d2 = np.asarray(squared_distances(jnp.asarray(mean), jnp.asarray(cov)))
    np.testing.assert_allclose(d2, [[0.0, 0.04], [0.04, 0.0]], atol=1e-9)


def test_copies_become_one_component_with_their_summed_weight():
    """Three copies of one Gaussian and a distinct one: the copies merge into the likeliest (its
    weight their sum), the distinct one stays, the total mass is unchanged."""
    log_w = np.log([0.1, 0.3, 0.2, 0.4])
    mean = np.array([[0.0, 0.0], [0.0, 0.01], [0.01, 0.0], [5.0, 5.0]])
    cov = np.tile(np.eye(2), (4, 1, 1))
    same = np.ones((4, 4), bool)
    out, into, n = _merge(jnp.asarray(log_w), jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(same), 0.01)
    np.testing.assert_allclose(np.exp(np.asarray(out)), [0.0, 0.6, 0.0, 0.4])
    np.testing.assert_array_equal(np.asarray(into), [1, 1, 1, 3])
    assert int(n) == 2


def test_different_classes_or_a_distant_mean_never_merge():
    log_w = np.log([0.5, 0.5])
    mean = np.array([[0.0, 0.0], [0.0, 0.0]])
    cov = np.tile(np.eye(2), (2, 1, 1))
    out, _, n = _merge(jnp.asarray(log_w), jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(np.eye(2, dtype=bool)), 1.0)
    np.testing.assert_allclose(np.asarray(out), log_w)  # same = False off the diagonal
    assert int(n) == 0
    far = mean + np.array([[0.0, 0.0], [0.0, 1.5]])  # d2 = 2.25
    out, _, n = _merge(jnp.asarray(log_w), jnp.asarray(far), jnp.asarray(cov), jnp.ones((2, 2), bool), 2.0)
    assert int(n) == 0


def test_tied_copies_merge_into_the_lower_slot_whatever_their_last_bits():
    """Equal weights, moved by a few ulps (another CPU's last bits): the survivor is the first slot."""
    for eps in (0.0, 1e-15, -1e-15):
        log_w = np.log([0.25, 0.25, 0.25, 0.25]) + np.array([0.0, eps, -eps, 0.0])
        mean = np.zeros((4, 2))
        out, into, n = _merge(jnp.asarray(log_w), jnp.asarray(mean), jnp.tile(jnp.eye(2), (4, 1, 1)),
                              jnp.ones((4, 4), bool), 0.0)
        np.testing.assert_array_equal(np.asarray(into), [0, 0, 0, 0])
        np.testing.assert_allclose(float(out[0]), 0.0, atol=1e-12)


@settings(deadline=None, max_examples=25, database=None, derandomize=True)
@given(st.data())
def test_merge_matches_the_greedy_rule_and_keeps_the_mass(data):
    """Random weights (some empty), means on a coarse grid (so that many pairs are equivalent),
    random SPD covariances and class groups: the kernel equals the greedy reference, and the
    survivors' weights sum to the input's."""
    k = 6
    log_w = np.array(data.draw(st.lists(st.one_of(st.floats(-6, 0, allow_subnormal=False), st.just(-np.inf)),
                                        min_size=k, max_size=k)))
    log_w[0] = 0.0  # at least one component
    rng = np.random.default_rng(data.draw(st.integers(0, 2**16)))
    mean = rng.integers(0, 3, size=(k, 3)) * 0.5
    a = rng.normal(size=(k, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2) + 0.5 * np.eye(3)
    group = rng.integers(0, 2, size=k)
    same = group[:, None] == group[None, :]
    threshold = data.draw(st.sampled_from([0.0, 0.3, 2.0, 10.0]))
    out, _, n = _merge(jnp.asarray(log_w), jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(same), threshold)
    expected = _reference(log_w, mean, cov, same, threshold)
    np.testing.assert_array_equal(np.isfinite(np.asarray(out)), np.isfinite(expected))
    np.testing.assert_allclose(np.asarray(out)[np.isfinite(expected)], expected[np.isfinite(expected)], rtol=1e-12)
    np.testing.assert_allclose(np.logaddexp.reduce(np.asarray(out)), np.logaddexp.reduce(log_w), rtol=1e-12)
    assert int(n) == int(np.isfinite(log_w).sum() - np.isfinite(expected).sum())


def _cluster_scenario() -> hs.Scenario:
    """A known map of two landmarks 0.2 m apart (one cluster), both read at every step from 2 m away:
    every step's two readings fit either assignment, so histories multiply while the Gaussians
    stay together (MRCLAM's repeated readings of a tube cluster, in small)."""
    setup = hs.PaperSetup(object_poses=((2.0, 0.1, 0.0), (2.0, -0.1, 0.0)), robot_cov=(0.01, 0.01, 0.0004),
                          step_length=0.0, turn_std=0.0, max_detections=2)
    return hs.simulate(seed=3, steps=6, setup=setup)


def test_hybrid_merge_holds_one_component_per_hypothesis():
    sc = _cluster_scenario()
    plain = hs.run(hs.Hybrid(capacity=8, weights=hs.Linearized(), smoother=hs.Filter()), sc)
    merged = hs.run(hs.Hybrid(capacity=8, weights=hs.Linearized(), smoother=hs.Filter(), merge_threshold=1e6), sc)
    # With every component equivalent (one class, a known map, an unbounded distance), the belief
    # holds one component, and its Gaussian is the likeliest's of the plain run at the first step.
    assert all(len(s.components) == 1 for s in merged.result.steps)
    assert max(len(s.components) for s in plain.result.steps) > 1
    assert sum(int(i.merged) for i in merged.infos) > 0 and sum(int(i.merged) for i in plain.infos) == 0
    np.testing.assert_allclose(merged.result.steps[0].components[0].pose_mean,
                               plain.result.steps[0].components[0].pose_mean, atol=1e-9)


def test_hybrid_merge_rejects_a_negative_distance():
    with pytest.raises(ValueError, match="Hybrid.merge_threshold"):
        hs.Hybrid(merge_threshold=-1.0)
