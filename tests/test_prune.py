import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.estimators.hybrid.prune import prune
from hybridslam.inference.ties import TIE_RESOLUTION

# One compiled prune per capacity: the examples' weights padded with impossible (-inf) candidates to
# one length, which changes nothing kept or counted (test_paper_rule_ratio_150 has fewer candidates
# than slots: prune's own padding).
_prune = jax.jit(prune, static_argnums=1)


def _padded(log_w, size: int) -> jnp.ndarray:
    return jnp.pad(jnp.asarray(log_w, float), (0, size - len(log_w)), constant_values=-jnp.inf)


# Subnormal log-weights are excluded: XLA on CPU flushes them to zero (a weight of -2e-313 nats
# *is* 0 to it) while numpy compares them exactly, so the reference and the kernel would disagree
# on a difference far below float64's resolution of a log-weight. Derandomized: CI sees the same examples.
@settings(deadline=None, max_examples=25, database=None, derandomize=True)
@given(
    st.lists(st.one_of(st.floats(-30, 0, allow_subnormal=False), st.just(-np.inf)), min_size=1, max_size=40),
    st.integers(1, 12),
    st.floats(1.0, 1e4),
)
def test_prune_keeps_exactly_what_the_rule_says(log_w, capacity, ratio):
    log_w = np.asarray(log_w)
    index, kept, stats = _prune(_padded(log_w, 40), capacity, jnp.asarray(ratio))
    finite = np.isfinite(log_w)
    above = finite & (log_w >= log_w.max() - np.log(ratio)) if finite.any() else finite
    # Heaviest first; weights within TIE_RESOLUTION of each other (one bin of the rank key, bins
    # centred on the largest) tie, and tied ones go by index.
    key = np.floor((log_w - (log_w[finite].max() if finite.any() else 0.0)) / TIE_RESOLUTION + 0.5)
    expected = log_w[sorted(np.flatnonzero(above), key=lambda i: (-key[i], i))[:capacity]]
    alive = np.isfinite(np.asarray(kept))
    assert alive.sum() == len(expected)
    np.testing.assert_array_equal(np.asarray(log_w)[np.asarray(index)[alive]], expected)
    if len(expected):
        np.testing.assert_allclose(np.exp(np.asarray(kept)[alive]).sum(), 1.0)
        np.testing.assert_allclose(np.exp(np.asarray(kept)[alive]), np.exp(expected) / np.exp(expected).sum())
    assert int(stats.dropped_capacity) == max(int(above.sum()) - capacity, 0)
    assert int(stats.dropped_threshold) == int(finite.sum() - above.sum())


def test_paper_rule_ratio_150():
    w = jnp.log(jnp.array([0.5, 0.4, 0.5 / 149, 0.5 / 151]))
    _, kept, stats = prune(w, 8, jnp.asarray(150.0))
    assert int(jnp.sum(kept > -jnp.inf)) == 3 and int(stats.dropped_threshold) == 1


@settings(deadline=None, max_examples=25, database=None, derandomize=True)
@given(st.lists(st.integers(-12, 0), min_size=1, max_size=12), st.integers(1, 8), st.data())
def test_tied_weights_are_ranked_by_index_whatever_their_last_bits(levels, capacity, data):
    """Every weight twice (an exact tie, as two class realizations no detection told apart), each
    copy moved by up to 1e-12 (the last bits another CPU's machine code moves): the kept children and
    their order are those of the exact weights, tied ones by index (``inference.ties``)."""
    exact = np.tile(np.asarray(levels, float) * 0.37, 2)  # copies at i and i + n
    moved = exact + np.asarray(data.draw(st.lists(st.floats(-1e-12, 1e-12), min_size=exact.size,
                                                  max_size=exact.size)))
    want, _, _ = _prune(_padded(exact, 24), capacity, jnp.asarray(1e9))
    got, _, _ = _prune(_padded(moved, 24), capacity, jnp.asarray(1e9))
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    order = np.asarray(want)[: min(capacity, exact.size)]
    key = [(-exact[i], i) for i in order]
    assert key == sorted(key)  # heaviest first, ties by index
