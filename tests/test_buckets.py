"""Static-size buckets (hybridslam.inference.buckets) and the smoother's solves on the live prefix.

The bucketed solve and marginal must equal the whole-graph ones whatever bucket the live poses and
objects fall in, also under ``jax.vmap`` with a different live count per member (the switch index
is then the batch's largest, unbatched).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam  # noqa: F401  (float64)
from hybridslam.inference import buckets
from hybridslam.inference import smoother as sm
from tests.test_smoother import N, P, _graph


def test_bucket_sizes_cover_each_long_axis_in_quarters_and_keep_short_ones_whole():
    assert buckets.bucket_sizes(11, 6) == ((11, 6),)  # the paper setup: one compile
    assert buckets.bucket_sizes(61, 70) == ((16, 18), (31, 35), (46, 53), (61, 70))  # the hallway
    assert buckets.bucket_sizes(201, 15) == ((51, 15), (101, 15), (151, 15), (201, 15))  # MRCLAM, known map
    assert buckets.bucket_sizes(61, 70, count=1) == ((61, 70),)


def test_batch_max_is_the_batch_maximum_unbatched_under_vmap():
    x = jnp.array([[3, 1], [2, 7]])
    assert int(buckets.batch_max(jnp.asarray(4))) == 4
    # out_axes=None: vmap fails unless the output is unbatched.
    assert int(jax.vmap(buckets.batch_max, out_axes=None)(x[0])) == 3
    assert int(jax.vmap(jax.vmap(buckets.batch_max, out_axes=None), out_axes=None)(x)) == 7  # nested: over both


@pytest.mark.parametrize("live", [0, 1, 3, 4, 5, 9])
def test_by_bucket_runs_the_first_bucket_that_holds_the_live_count(live):
    sizes = ((2, 1), (4, 1), (6, 1))
    got = buckets.by_bucket(sizes, (live, 0), lambda size, x: x + size[0], jnp.asarray(0))
    assert int(got) == {0: 2, 1: 2, 3: 4, 4: 4, 5: 6, 9: 6}[live]


@pytest.fixture
def small_buckets(monkeypatch):
    monkeypatch.setattr(buckets, "MIN_BUCKETED", 2)  # P = 5, N = 3 in quarters: (2, 1) (3, 2) (4, 3) (5, 3)


def _prefix_graph(seed: int, poses: int, objects: int) -> sm.FactorGraph:
    """A random graph of P poses and N objects of which the first ``poses`` / ``objects`` are active."""
    graph = _graph(np.random.default_rng(seed), independent=True)
    pose_active = jnp.arange(P) < poses
    object_active = jnp.arange(N) < objects
    live = pose_active[graph.meas_pose][:, None] & object_active[graph.meas_objects]
    return dataclasses.replace(
        graph, pose_active=pose_active, object_active=object_active,
        odometry_active=pose_active[1:], meas_log_weight=jnp.where(live, graph.meas_log_weight, -jnp.inf))


def _whole(lin: sm.Linearization) -> sm.Linearization:
    return dataclasses.replace(lin, live_poses=None, live_objects=None)


# Compiled programs of this file's own functions (traced under ``small_buckets``: the bucket sizes are
# fixed at trace time, so no other file's program may stand in for them); the live counts are traced.
@jax.jit
def _bucketed_solves(graph, start, k):
    """The linearization's live counts, dense ``H``, ``g`` and bucketed solutions; the bucketed
    marginal of ``[x_k, O]`` at the solver's solution, and that of the whole graph."""
    lin = sm.linearize(graph, start, jnp.zeros((N, 3)))
    solutions = {m: sm.solve_normal(lin, m) for m in ("poses-first", "objects-first")}
    sol = sm.solve(graph, start, jnp.zeros((N, 3)), max_steps=5)
    whole = dataclasses.replace(sol, linearization=_whole(sol.linearization))
    return (lin.live_poses, lin.live_objects), lin.dense(), solutions, sm.marginal(sol, k), sm.marginal(whole, k)


@pytest.mark.parametrize(("poses", "objects"), [(1, 0), (2, 1), (3, 3), (5, 1), (5, 3)])
def test_bucketed_solve_and_marginal_equal_the_whole_graphs(small_buckets, poses, objects):
    graph = _prefix_graph(poses * 10 + objects, poses, objects)
    start = jnp.asarray(np.random.default_rng(0).normal(size=(P, 3)) * 0.1)
    live, (h, g), solutions, (mean, cov), (mean_w, cov_w) = _bucketed_solves(graph, start, jnp.asarray(poses - 1))
    assert tuple(int(n) for n in live) == (poses, objects)
    ref = -np.linalg.solve(np.asarray(h), np.asarray(g))
    for method, (d_p, d_o) in solutions.items():
        got = np.concatenate([np.asarray(d_p).reshape(-1), np.asarray(d_o).reshape(-1)])
        np.testing.assert_allclose(got, ref, atol=1e-10, err_msg=method)
    np.testing.assert_allclose(np.asarray(cov), np.asarray(cov_w), rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(mean), np.asarray(mean_w))


_marginalize_bucketed = jax.jit(lambda *args: sm.marginalize_first_information(*args))
_marginalize_whole = jax.jit(lambda *args: sm.marginalize_first_information(*args))  # traced with BUCKETS = 1


@pytest.mark.parametrize("objects", [0, 1, 2, 3])
def test_bucketed_marginalization_of_the_first_pose_equals_the_whole_graphs(small_buckets, monkeypatch, objects):
    """The fixed-lag marginalization factors only the live objects' head of ``H'``; the inactive
    objects keep their value and identity blocks of ``R`` and ``H'``, as on the whole graph."""
    graph = _prefix_graph(7 + objects, P, objects)
    rng = np.random.default_rng(objects)
    poses, objs = jnp.asarray(rng.normal(size=(P, 3)) * 0.1), jnp.asarray(rng.normal(size=(N, 3)) * 0.1)
    got = _marginalize_bucketed(graph, poses, objs)
    monkeypatch.setattr(buckets, "BUCKETS", 1)
    want = _marginalize_whole(graph, poses, objs)
    for a, b, name in zip(got, want, ("mean", "R", "H'")):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12, err_msg=name)
    tail = slice(3 + 3 * objects, None)
    np.testing.assert_array_equal(np.asarray(got[2])[tail, tail], np.eye(3 * (N - objects)))


def test_bucketed_solve_under_vmap_with_a_live_count_per_member(small_buckets):
    graphs = [_prefix_graph(seed, poses, objects) for seed, (poses, objects) in enumerate([(2, 1), (5, 2), (3, 3)])]
    start = jnp.asarray(np.random.default_rng(1).normal(size=(P, 3)) * 0.1)
    linearize = jax.jit(lambda g: sm.linearize(g, start, jnp.zeros((N, 3))))
    lins = [linearize(g) for g in graphs]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *lins)
    d_p, d_o = jax.jit(jax.vmap(sm.solve_normal))(batch)
    solve_whole = jax.jit(lambda lin: sm.solve_normal(_whole(lin)))
    for i, lin in enumerate(lins):
        ref_p, ref_o = solve_whole(lin)
        np.testing.assert_allclose(np.asarray(d_p[i]), np.asarray(ref_p), atol=1e-10)
        np.testing.assert_allclose(np.asarray(d_o[i]), np.asarray(ref_o), atol=1e-10)


def test_the_environment_sets_the_number_of_buckets_and_rejects_nonsense(monkeypatch):
    monkeypatch.setenv("HYBRIDSLAM_BUCKETS", "1")
    assert buckets.buckets_from_environment() == 1
    for bad in ("0", "-2", "four"):
        monkeypatch.setenv("HYBRIDSLAM_BUCKETS", bad)
        with pytest.raises(ValueError, match="HYBRIDSLAM_BUCKETS"):
            buckets.buckets_from_environment()
    monkeypatch.setattr(buckets, "BUCKETS", 1)
    assert buckets.bucket_sizes(61, 70) == ((61, 70),)
