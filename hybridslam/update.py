"""The measurement update of one component (Eq. 9-11, Algorithm 1 line 11) by Gauss-Newton.

The posterior of a child is ``b ∝ P(Z_k | X_k, C, β_k) · b⁻`` (Eq. 9) with the propagated
Gaussian ``b⁻`` as a prior factor and one factor per associated detection (Eq. 10). We find its
mode with :class:`optimistix.GaussNewton` (``throw=False``; the solver result is returned so a
failed solve is visible, not fatal) and take the covariance from the Gauss-Newton Hessian ``JᵀJ``
at the mode. The covariance is formed in square-root form: ``J = Q R`` and ``Σ = R⁻¹ R⁻ᵀ``, which
is symmetric positive definite by construction.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import optimistix as optx
from jaxtyping import Array, Float, Int

from . import se2
from .belief import Detections
from .measurement import SensorModel, slot_residuals

GN_TOLERANCE = 1e-6  # on the state: 1 µm, 1 µrad — far below the posterior spread of Sec. V (cm)


def wrap_angles(state: Float[Array, " D"]) -> Float[Array, " D"]:
    """Wrap every heading (indices 2, 5, 8, ...) of a ``[x_k, x^o_1, ...]`` state."""
    return state.at[2::3].set(se2.wrap(state[2::3]))


def _residuals(y, args):
    sensor, mean, chol, assign, slot_class, detections = args
    prior = jsl.solve_triangular(chol, wrap_angles(y - mean), lower=True)
    x, objs = y[:3], y[3:].reshape(-1, 3)
    meas, _ = slot_residuals(
        sensor, x, objs[jnp.maximum(assign, 0)], detections.geo, detections.scores, assign, slot_class
    )
    return jnp.concatenate([prior, meas])


def gauss_newton(
    residuals: Callable, y0: Float[Array, " D"], args, max_steps: int
) -> tuple[Float[Array, " D"], Float[Array, "D D"], optx.RESULTS]:
    """Minimize ``½‖residuals(y, args)‖²`` by Gauss-Newton; covariance ``(JᵀJ)⁻¹`` at the solution.

    The residuals must be whitened. The covariance is formed in square-root form (``J = QR``,
    ``Σ = R⁻¹R⁻ᵀ``): symmetric positive definite by construction.
    """
    solver = optx.GaussNewton(rtol=GN_TOLERANCE, atol=GN_TOLERANCE)
    sol = optx.least_squares(residuals, solver, y0, args, max_steps=max_steps, throw=False)
    r = jnp.linalg.qr(jax.jacfwd(residuals)(sol.value, args), mode="r")
    r_inv = jsl.solve_triangular(r, jnp.eye(r.shape[0], dtype=r.dtype), lower=False)
    return sol.value, r_inv @ r_inv.T, sol.result


def gauss_newton_update(
    sensor: SensorModel,
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    assign: Int[Array, " Dmax"],
    slot_class: Int[Array, " Dmax"],
    detections: Detections,
    max_steps: int,
) -> tuple[Float[Array, " D"], Float[Array, "D D"], optx.RESULTS]:
    """Posterior mean, covariance and solver result of one child (slots with ``assign < 0`` are empty)."""
    args = (sensor, mean, jnp.linalg.cholesky(cov), assign, slot_class, detections)
    value, new_cov, result = gauss_newton(_residuals, mean, args, max_steps)
    return wrap_angles(value), new_cov, result
