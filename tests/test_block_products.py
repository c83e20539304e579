"""Products the steps compute by blocks, against the dense formulas they replace.

``weights._gram``: ``J Σ Jᵀ`` of rows whose Jacobian touches the pose and one object (the linearized
weights' tables, Eq. 16); ``step._equal_rows``: which association histories are equal (one
smoothing per distinct factor graph), exact from a float64 product of integer rows.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.estimators.hybrid.step import _equal_rows
from hybridslam.estimators.hybrid.weights import _gram


@settings(max_examples=25, deadline=None)
@given(objects=st.integers(1, 9), rows=st.integers(1, 5), seed=st.integers(0, 2**31 - 1))
def test_the_block_gram_is_the_dense_product(objects, rows, seed):
    rng = np.random.default_rng(seed)
    e = 3 + 3 * objects
    jac_x, jac_o = rng.normal(size=(objects * rows, 3)), rng.normal(size=(objects, rows, 3))
    a = rng.normal(size=(e, e))
    cov = a @ a.T
    dense = np.zeros((objects * rows, e))
    dense[:, :3] = jac_x
    for o in range(objects):
        dense[o * rows:(o + 1) * rows, 3 + 3 * o:6 + 3 * o] = jac_o[o]
    expected = dense @ cov @ dense.T
    got = np.asarray(_gram(jnp.asarray(jac_x), jnp.asarray(jac_o), jnp.asarray(cov)))
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())


@settings(max_examples=25, deadline=None)
@given(components=st.integers(1, 12), length=st.integers(1, 400), objects=st.integers(1, 200),
       seed=st.integers(0, 2**31 - 1))
def test_equal_rows_are_found_exactly(components, length, objects, seed):
    rng = np.random.default_rng(seed)
    rows = rng.integers(-1, objects, size=(components, length))
    copies = rng.integers(0, components, size=components)
    rows = rows[copies]  # repeated rows
    near = rows.copy()
    near[0, rng.integers(length)] += 1  # a row that differs from its copies in one entry
    for r in (rows, near):
        expected = np.all(r[:, None] == r[None, :], axis=-1)
        np.testing.assert_array_equal(np.asarray(_equal_rows(jnp.asarray(r, jnp.int32))), expected)
