"""The unrolled short sums and small Cholesky of ``hybridslam.models.unrolled`` against numpy."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.models import unrolled


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10), st.integers(0, 3), st.integers(0, 2**31 - 1))
def test_sum_last_is_jnp_sum(n, batch, seed):
    a = np.random.default_rng(seed).standard_normal((batch, 3, n))
    np.testing.assert_allclose(unrolled.sum_last(jnp.asarray(a)), a.sum(-1), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("n", [1, 2, 3, 8, 12, 13])  # 13: the LAPACK path
def test_gaussian_terms_are_the_mahalanobis_distance_and_log_determinant(n):
    rng = np.random.default_rng(n)
    a = rng.standard_normal((n, n))
    s = a @ a.T + 0.1 * np.eye(n)
    r = rng.standard_normal(n)
    mats = [s]
    if n <= unrolled.MAX_UNROLLED_CHOLESKY:  # the unrolled path reads the lower triangle only
        mats.append(np.tril(s) + np.triu(np.full((n, n), 1e6), 1))
    for mat in mats:
        maha, log_det = unrolled.gaussian_terms(jnp.asarray(mat), jnp.asarray(r))
        np.testing.assert_allclose(maha, r @ np.linalg.solve(s, r), rtol=1e-10)
        np.testing.assert_allclose(log_det, np.linalg.slogdet(s)[1], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("n", [2, 13])
def test_gaussian_terms_of_an_indefinite_matrix_are_nan(n):
    s = np.eye(n)
    s[1, 1] = -1.0
    maha, log_det = unrolled.gaussian_terms(jnp.asarray(s), jnp.ones(n))
    assert np.isnan(maha) and np.isnan(log_det)


@pytest.mark.parametrize("n", [1, 4, 13])  # 13: the LAPACK path
def test_cholesky_whiten_gives_the_lower_factor_and_the_whitened_residual(n):
    rng = np.random.default_rng(10 + n)
    a = rng.standard_normal((n, n))
    s = a @ a.T + 0.1 * np.eye(n)
    r = rng.standard_normal(n)
    low, white, log_det = unrolled.cholesky_whiten(jnp.asarray(s), jnp.asarray(r))
    np.testing.assert_allclose(low, np.linalg.cholesky(s), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(white, np.linalg.solve(np.linalg.cholesky(s), r), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(log_det, np.linalg.slogdet(s)[1], rtol=1e-10, atol=1e-12)
