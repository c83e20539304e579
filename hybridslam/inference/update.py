"""The measurement update of one component (Eq. 9-11, Algorithm 1 line 11) by Gauss-Newton.

The posterior of a child is ``b ∝ P(Z_k | X_k, C, β_k) · b⁻`` (Eq. 9) with the propagated
Gaussian ``b⁻`` as a prior factor and one factor per associated detection (Eq. 10). We find its
mode by Gauss-Newton in Kalman form (:func:`prior_gauss_newton`, an iterated EKF: ``O(D² m)`` per
iterate, so a large map is cheap when a step observes a few objects) and take the covariance
from the Gauss-Newton Hessian ``Σ⁻¹ + JᵀJ`` at the mode. The solver result is returned
(``throw=False``) so a failed solve is visible, not fatal.

:func:`gauss_newton` (``optimistix.GaussNewton`` on whitened residuals, covariance ``R⁻¹R⁻ᵀ`` from
``J = QR``) is the dense reference the Kalman form is tested against (``laplace-is`` searched its
modes with it until it moved to the Kalman form, which compiles faster).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import optimistix as optx
from jaxtyping import Array, Float, Int

from ..models import se2
from ..models.measurement import Detections, SensorModel, slot_residuals

GN_TOLERANCE = 1e-6  # on the state: 1 µm, 1 µrad — far below the posterior spread of Sec. V (cm)


def wrap_angles(state: Float[Array, " D"]) -> Float[Array, " D"]:
    """Wrap every heading (indices 2, 5, 8, ...) of a ``[x_k, x^o_1, ...]`` state."""
    # An elementwise select, not a strided scatter: XLA's CPU backend expands every scatter into a
    # loop compiled as a kernel of its own.
    return jnp.where(jnp.arange(state.shape[0]) % 3 == 2, se2.wrap(state), state)


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


def _measurement_residuals(y, args):
    sensor, assign, slot_class, detections = args
    x, objs = y[:3], y[3:].reshape(-1, 3)
    meas, _ = slot_residuals(
        sensor, x, objs[jnp.maximum(assign, 0)], detections.geo, detections.scores, assign, slot_class
    )
    return meas


def gauss_newton_update(
    sensor: SensorModel,
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    assign: Int[Array, " Dmax"],
    slot_class: Int[Array, " Dmax"],
    detections: Detections,
    max_steps: int,
) -> tuple[Float[Array, " D"], Float[Array, "D D"], optx.RESULTS]:
    """Posterior mean, covariance and solver result of one child (slots with ``assign < 0`` are empty).

    The mode of Eq. 9 (the propagated Gaussian as a prior, one factor per associated detection,
    Eq. 10) by :func:`prior_gauss_newton`: ``O(D² m)`` per iterate, so a large map (the hallway's
    70 object slots) costs little when a step observes a few objects.
    """
    args = (sensor, assign, slot_class, detections)
    return prior_gauss_newton(_measurement_residuals, mean, cov, args, max_steps, support_of(assign))


def support_of(objects: Int[Array, "*F"]) -> Int[Array, " P"]:
    """State indices of ``[x_k, o_{objects}...]`` (``P = 3 + 3F``; negative entries name object 0,
    harmlessly: :func:`prior_gauss_newton` allows repeated indices)."""
    obj = 3 + 3 * jnp.maximum(objects.reshape(-1), 0)[:, None] + jnp.arange(3)[None, :]
    return jnp.concatenate([jnp.arange(3), obj.reshape(-1)])


def prior_gauss_newton(
    measurement: Callable, mean: Float[Array, " D"], cov: Float[Array, "D D"], args, max_steps: int,
    support: Int[Array, " P"] | None = None, difference: Callable | None = None,
) -> tuple[Float[Array, " D"], Float[Array, "D D"], optx.RESULTS]:
    """The mode and covariance of :func:`prior_gauss_newton_gain`'s Gauss-Newton:
    ``Σ⁺ = Σ − K (JΣ)``, symmetrized."""
    value, k, js, result = prior_gauss_newton_gain(measurement, mean, cov, args, max_steps, support, difference)
    return value, downdate(cov, k, js), result


def downdate(cov: Float[Array, "D D"], gain: Float[Array, "D m"], gain_js: Float[Array, "m D"],
             idx: Int[Array, " P"] | None = None) -> Float[Array, "P P"]:
    """The Gauss-Newton covariance ``Σ − K (JΣ)`` of :func:`prior_gauss_newton_gain`, symmetrized;
    with ``idx``, only its ``[idx, idx]`` block (``O(P² m)``, not ``O(D² m)``)."""
    if idx is not None:
        cov, gain, gain_js = cov[idx][:, idx], gain[idx], gain_js[:, idx]
    c = cov - gain @ gain_js
    return 0.5 * (c + c.T)


def prior_gauss_newton_gain(
    measurement: Callable, mean: Float[Array, " D"], cov: Float[Array, "D D"], args, max_steps: int,
    support: Int[Array, " P"] | None = None, difference: Callable | None = None,
) -> tuple[Float[Array, " D"], Float[Array, "D m"], Float[Array, "m D"], optx.RESULTS]:
    """Gauss-Newton on ``½‖y ⊖ μ‖²_Σ + ½‖measurement(y, args)‖²``, in Kalman form (an iterated EKF).

    The same iterates as :func:`gauss_newton` with the prior as a factor (Bell & Cathey 1993: the
    iterated EKF *is* Gauss-Newton on this objective), but each costs ``O(D² m)`` for ``m``
    whitened measurement residuals instead of the ``O(D³)`` of a dense solve over all ``D`` state
    entries. That matters when the state holds a large map and a step observes a few objects.
    Linearized at the iterate ``y``, with ``J = ∂r/∂y`` and ``δ = μ ⊖ y``, the next iterate is
    ``μ + K ν`` with ``K = Σ Jᵀ (J Σ Jᵀ + I)⁻¹``, ``ν = −(r(y) + J δ)``; the covariance at the
    solution is ``(I − K J) Σ = (Σ⁻¹ + JᵀJ)⁻¹`` (the Gauss-Newton Hessian, as in :func:`gauss_newton`).
    Returns the mode (headings wrapped), ``K`` and ``JΣ`` at the mode: the covariance is the rank-``m``
    downdate ``Σ − K (JΣ)`` (:func:`downdate`), so a batch of updates of a few
    priors need not carry a ``D × D`` matrix each.
    Stops when no entry moves by more than ``GN_TOLERANCE``, or after ``max_steps``.

    ``support``: the state indices the measurement depends on (e.g. :func:`support_of` the robot
    pose and the observed objects; repeats allowed). ``J`` is then taken over those ``P`` entries
    only — ``P`` forward-mode passes instead of ``D``, and ``O(D P m)`` products — with the same
    result. A repeated index gets its derivative split evenly over its copies, so every product
    with ``J`` sums to the derivative once.

    ``difference(a, b)``: ``a ⊖ b`` on the state's manifold (default: every heading, indices 2, 5,
    ..., wrapped). Given one, the mode is returned as iterated (unwrapped), for callers whose state
    holds entries that are not poses.
    """

    def jacobian(y, args):
        if support is None:
            return jax.jacfwd(measurement)(y, args), slice(None)
        copies = jnp.sum(support[:, None] == support[None, :], axis=1).astype(y.dtype)
        # Differentiate at a zero offset of the support entries: the offset carries no tangent of an
        # outer differentiation (y already does), so implicit differentiation stays exact.
        bump = lambda v: measurement(y.at[support].add(v), args)  # noqa: E731
        return jax.jacfwd(bump)(jnp.zeros(support.shape, y.dtype)) / copies[None, :], support

    def gain(y, cov, args):
        r = measurement(y, args)
        jac, cols = jacobian(y, args)  # (m, P): J restricted to the columns `cols`
        js = jac @ cov[cols, :]  # J Σ, (m, D)
        s = js[:, cols] @ jac.T + jnp.eye(r.shape[0], dtype=cov.dtype)
        chol = jnp.linalg.cholesky(s)
        k = jsl.cho_solve((chol, True), js).T  # (D, m)
        return r, jac, cols, js, k

    def iterate(y, inputs):
        # Not wrapped: the iterates stay near the (wrapped) prior mean, and a wrap would look like a
        # 2π jump to the fixed-point test. The result is wrapped once at the end.
        mean, cov, args = inputs
        r, jac, cols, _, k = gain(y, cov, args)
        delta = wrap_angles(mean - y) if difference is None else difference(mean, y)
        return mean + k @ -(r + jac @ delta[cols])

    # A fixed point of `iterate` is a stationary point of the objective (Σ⁻¹(y − μ) + Jᵀr = 0), so
    # optimistix's implicit adjoint differentiates the mode exactly without unrolling the iterations.
    solver = optx.FixedPointIteration(rtol=0.0, atol=GN_TOLERANCE)
    sol = optx.fixed_point(iterate, solver, mean, (mean, cov, args), max_steps=max_steps, throw=False)
    _, _, _, js, k = gain(sol.value, cov, args)
    return (wrap_angles(sol.value) if difference is None else sol.value), k, js, sol.result
