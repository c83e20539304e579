"""Importance sampling with a Laplace proposal: a low-variance estimator of Eq. 16's integral.

For one child the integral of Eq. 16 is the evidence

    ψ = ∫ P(Z_k | y) · P(β_k | y) · b⁻(y) dy,        y = (x_k, X^o_β),  b⁻ = N(μ, P)  (Eq. 17)

The paper estimates it by the mean of the likelihood over draws from the prior ``b⁻``; when
``b⁻`` is broad and the likelihood sharp, a handful of draws decide it. Here the draws come from
the Laplace approximation ``q = N(y*, Σ*)`` at the child's own measurement-updated mode (found by
Gauss-Newton, the update of Algorithm 1 line 11 done before pruning):

    ψ ≈ (1/n) Σ_i P(Z_k | y_i) P(β_k | y_i) b⁻(y_i) / q(y_i),    y_i ~ q.

It converges to the same value; for a linear-Gaussian model every term equals ψ exactly (zero
variance, normalized effective sample size 1). The ESS of the terms is returned as a diagnostic.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import optimistix as optx
from jax.scipy.special import logsumexp
from jaxtyping import Array, Float

from .update import prior_gauss_newton

_LOG_2PI = math.log(2.0 * math.pi)


class Evidence(eqx.Module):
    log_evidence: Float[Array, ""]  # log ψ with the observation model P(β | y)
    log_evidence_free: Float[Array, ""]  # log ψ without it (the step's fallback)
    ess: Float[Array, ""]  # normalized effective sample size of the importance weights, in (0, 1]
    mode: Float[Array, " d"]
    cov: Float[Array, "d d"]
    solver_result: optx.RESULTS  # of the Gauss-Newton search for the mode


def _log_gaussian(diff: Float[Array, " d"], chol: Float[Array, "d d"]) -> Float[Array, ""]:
    white = jsl.solve_triangular(chol, diff, lower=True)
    return -0.5 * jnp.sum(white**2) - jnp.sum(jnp.log(jnp.diagonal(chol))) - 0.5 * diff.shape[0] * _LOG_2PI


def laplace_is(
    measurement: Callable[[Float[Array, " d"]], tuple[Float[Array, " R"], Float[Array, ""], Float[Array, ""]]],
    mean: Float[Array, " d"],
    cov: Float[Array, "d d"],
    eps: Float[Array, "S d"],
    max_steps: int,
    difference: Callable[[Float[Array, " d"], Float[Array, " d"]], Float[Array, " d"]] = jnp.subtract,
) -> Evidence:
    """Estimate ``log ∫ exp(−½‖r(y)‖² + log_norm + log_view(y)) N(y; mean, cov) dy``.

    ``measurement(y)`` returns the whitened residual ``r(y)``, its log normalizer, and
    ``log_view(y)`` (the object observation model: 0 or ``-inf`` for the hard footprint, finite for
    the smooth one). ``eps`` are standard-normal draws (shared by all callers for common random
    numbers; the draws ``mode + L eps`` are reparameterized); ``difference(a, b)`` is ``a − b``
    on the state's manifold (angles wrapped). A mode search that does not converge leaves the
    estimate unbiased (any proposal is valid) but less efficient: see ``solver_result`` and ``ess``.
    """
    prior_chol = jnp.linalg.cholesky(cov)

    # The mode search in Kalman form (an iterated EKF): the same Gauss-Newton iterates as a dense
    # solve with the prior as a factor, and a fixed-point loop that traces and compiles in less time
    # than optimistix.GaussNewton's.
    mode, post_cov, result = prior_gauss_newton(lambda y, _: measurement(y)[0], mean, cov, None, max_steps,
                                                difference=difference)
    post_chol = jnp.linalg.cholesky(post_cov)
    draws = mode[None, :] + eps @ post_chol.T

    def log_terms(y, white):
        r, log_norm, log_view = measurement(y)
        log_lik = log_norm - 0.5 * jnp.sum(r**2) + _log_gaussian(difference(y, mean), prior_chol)
        log_q = -0.5 * jnp.sum(white**2) - jnp.sum(jnp.log(jnp.diagonal(post_chol))) - 0.5 * y.shape[0] * _LOG_2PI
        return log_lik + log_view - log_q, log_lik - log_q

    with_view, free = jax.vmap(log_terms)(draws, eps)
    n = eps.shape[0]
    log_ev = _log_mean_exp(with_view)
    ess = jnp.exp(2.0 * logsumexp(with_view) - logsumexp(2.0 * with_view)) / n
    ess = jnp.where(jnp.isfinite(ess), ess, 0.0)
    return Evidence(log_ev, _log_mean_exp(free), ess, mode, post_cov, result)


def logsumexp_or_minus_inf(terms: Float[Array, "*S"], axis: int | None = None) -> Float[Array, "*R"]:
    """``logsumexp(terms, axis)``, ``-inf`` with a zero (not NaN) gradient where every term is ``-inf``
    (a double ``where``: logsumexp's derivative there is NaN, and a ``where`` around it does not stop
    a NaN cotangent)."""
    some = jnp.any(terms > -jnp.inf, axis=axis, keepdims=True)
    total = logsumexp(jnp.where(some, terms, 0.0), axis=axis, keepdims=True)
    return jnp.squeeze(jnp.where(some, total, -jnp.inf), axis=axis)


def _log_mean_exp(terms: Float[Array, " S"]) -> Float[Array, ""]:
    """``log mean exp(terms)``; ``-inf`` with a zero (not NaN) gradient when every term is ``-inf``."""
    return logsumexp_or_minus_inf(terms) - math.log(terms.shape[0])
