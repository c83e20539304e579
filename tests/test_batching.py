"""map_live and map_distinct: the batched map over live slots, and once per class of equal slots."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.inference.batching import fold_live, map_distinct, map_live

K = 7  # not a multiple of the chunk: the padded last chunk is exercised too


def _fn(x, y):
    return {"sum": x + y[0], "prod": x * y}


_live = jax.jit(lambda live, x, y: map_live(_fn, live, x, y))
_distinct = jax.jit(lambda live, same, x, y: map_distinct(_fn, live, same, x, y))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 3), min_size=K, max_size=K), st.lists(st.booleans(), min_size=K, max_size=K))
def test_each_live_slot_gets_the_output_of_the_first_live_slot_of_its_class(keys, live):
    keys, live = np.array(keys), np.array(live)
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=K), rng.normal(size=(K, 2))  # equal keys, different inputs: copies are visible
    same = keys[:, None] == keys[None, :]
    out, count = _distinct(jnp.asarray(live), jnp.asarray(same), jnp.asarray(x), jnp.asarray(y))
    reference = _live(jnp.ones(K, bool), jnp.asarray(x), jnp.asarray(y))
    for i in np.flatnonzero(live):
        first = np.flatnonzero(live & (keys == keys[i]))[0]
        for name in ("sum", "prod"):
            np.testing.assert_array_equal(out[name][i], reference[name][first])
    assert int(count) == len(set(keys[live].tolist()))


def test_with_every_slot_distinct_it_is_map_live():
    live = jnp.array([True, True, False, True, False, False, True])
    x, y = jnp.arange(K, dtype=float), jnp.ones((K, 2))
    out, count = _distinct(live, jnp.eye(K, dtype=bool), x, y)
    reference = _live(live, x, y)
    for name in ("sum", "prod"):
        np.testing.assert_array_equal(np.asarray(out[name])[np.asarray(live)],
                                      np.asarray(reference[name])[np.asarray(live)])
    assert int(count) == 4


def test_live_slots_equal_vmap_for_every_chunk_size_and_under_an_outer_vmap():
    """chunk=1 calls fn unbatched (no size-1 vmap); every chunk size must give vmap's values on live slots."""
    live = jnp.array([True, False, True, True, False, False, False])
    x, y = jnp.linspace(-1.0, 1.0, K), jnp.arange(2.0 * K).reshape(K, 2)
    reference = jax.vmap(_fn)(x, y)
    for chunk in (1, 3, 4, K):
        out = jax.jit(lambda lv, a, b, c=chunk: map_live(_fn, lv, a, b, chunk=c))(live, x, y)
        for name in ("sum", "prod"):
            np.testing.assert_array_equal(np.asarray(out[name])[np.asarray(live)],
                                          np.asarray(reference[name])[np.asarray(live)])
    # Two tracks under an outer vmap with its axis name: a slot live in either track is computed.
    lives = jnp.stack([live, jnp.zeros(K, bool).at[6].set(True)])
    xs, ys = jnp.stack([x, -x]), jnp.stack([y, 2 * y])
    for chunk in (1, 4):  # jitted: one program each (op by op, every operation of map_live compiles alone)
        out = jax.jit(jax.vmap(lambda lv, a, b, c=chunk: map_live(_fn, lv, a, b, chunk=c, axis_name="t"),
                               axis_name="t"))(lives, xs, ys)
        for t in range(2):
            ref = jax.vmap(_fn)(xs[t], ys[t])
            mask = np.asarray(lives[t])
            np.testing.assert_array_equal(np.asarray(out["prod"][t])[mask], np.asarray(ref["prod"])[mask])


def _sum_live(live, x, chunk, axis_name=None):
    """Σ over the live slots of x² via fold_live, and the number of chunks visited."""
    def fold(acc, first, lv, xc):
        assert xc.shape[0] == min(chunk, K)  # fn sees its chunk batched
        total, chunks = acc
        real = first + jnp.arange(xc.shape[0]) < K  # the last chunk is padded with copies of slot 0
        return total + jnp.sum(jnp.where(lv & real, xc**2, 0.0)), chunks + 1
    return fold_live(fold, (jnp.zeros(()), jnp.zeros((), jnp.int32)), live, live, x, chunk=chunk, axis_name=axis_name)


def test_fold_live_visits_only_chunks_with_a_live_slot():
    live = jnp.array([False, False, False, True, False, False, True])
    x = jnp.linspace(-1.0, 2.0, K)
    want = float(jnp.sum(jnp.where(live, x**2, 0.0)))
    for chunk, visited in ((1, 2), (3, 2), (4, 2), (K, 1)):
        total, chunks = jax.jit(lambda lv, a, c=chunk: _sum_live(lv, a, c))(live, x)
        np.testing.assert_allclose(total, want, rtol=1e-15)
        assert int(chunks) == visited, chunk
    # Under an outer vmap with its axis name, a chunk live in either track is visited in both.
    lives = jnp.stack([live, jnp.zeros(K, bool).at[0].set(True)])
    total, chunks = jax.jit(jax.vmap(lambda lv, a: _sum_live(lv, a, 4, "t"), axis_name="t"))(lives, jnp.stack([x, x]))
    np.testing.assert_allclose(total, [want, float(x[0] ** 2)], rtol=1e-15)
    assert chunks.tolist() == [2, 2]
