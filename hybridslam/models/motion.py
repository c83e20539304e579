"""Motion model: odometry ``u_k`` measures ``between(x_{k-1}, x_k)`` (SCENARIO_FORMAT.md).

Noise enters on the right, in the tangent space: ``x_k = x_{k-1} ∘ u_k ∘ Exp(w)``,
``w ~ N(0, Σ_w)`` — the convention of GTSAM's ``BetweenFactor<Pose2>``, whose residual is
``Log(u_k⁻¹ ∘ between(x_{k-1}, x_k))``. This is the paper's ``P(x_k | x_{k-1}, a_{k-1})``
(Sec. III) used in the propagation step, Eq. 11 / Algorithm 1 line 3.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from . import se2


def odometry_residual(x_prev: se2.Pose, x: se2.Pose, odometry: se2.Pose) -> Float[Array, "3"]:
    """Unwhitened residual ``Log(u⁻¹ ∘ between(x_prev, x))``, shape ``(3,)``."""
    return se2.log(se2.between(odometry, se2.between(x_prev, x)))


def _move(x_prev: se2.Pose, w: Float[Array, "3"], odometry: se2.Pose) -> se2.Pose:
    return se2.compose(se2.compose(x_prev, odometry), se2.exp(w))


def motion_jacobians(x_prev: se2.Pose, odometry: se2.Pose) -> tuple[Float[Array, "3 3"], Float[Array, "3 3"]]:
    """``∂f/∂x_{k-1}`` and ``∂f/∂w`` of ``f(x, w) = x ∘ u ∘ Exp(w)`` at ``w = 0``, in closed form.

    With ``x = [t, θ]`` and ``u = [t_u, θ_u]``, ``x ∘ u = [t + R(θ) t_u, θ + θ_u]`` (Eq. 11, thesis
    Eq. 2.3), so ``∂f/∂x = [[I, R'(θ) t_u], [0, 1]]`` with ``R'(θ) t_u = [−s u_x − c u_y,
    c u_x − s u_y]``; ``Exp(w) = [w_t, w_θ] + O(‖w‖²)``, so ``∂f/∂w = blockdiag(R(θ + θ_u), 1)``
    (the noise enters in the moved pose's frame). The same matrices as ``jax.jacfwd`` of the
    composition (tests/test_jacobians.py), a fraction of its program.
    """
    c, s = jnp.cos(x_prev[2]), jnp.sin(x_prev[2])
    cw, sw = jnp.cos(x_prev[2] + odometry[2]), jnp.sin(x_prev[2] + odometry[2])
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    f_x = jnp.stack([
        jnp.stack([one, zero, -s * odometry[0] - c * odometry[1]]),
        jnp.stack([zero, one, c * odometry[0] - s * odometry[1]]),
        jnp.stack([zero, zero, one]),
    ])
    f_w = jnp.stack([jnp.stack([cw, -sw, zero]), jnp.stack([sw, cw, zero]), jnp.stack([zero, zero, one])])
    return f_x, f_w


def propagate(
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    odometry: se2.Pose,
    motion_cov: Float[Array, "3 3"],
) -> tuple[Float[Array, " D"], Float[Array, "D D"]]:
    """Propagate a joint Gaussian over ``[x_k, objects...]`` through the motion model (Eq. 11).

    The robot pose occupies ``mean[:3]``; object poses are static. Linearized (EKF) prediction:
    ``P' = A P Aᵀ + B Σ_w Bᵀ`` with ``A = blockdiag(∂f/∂x, I)``, ``B = [∂f/∂w; 0]``.
    """
    x_prev = mean[:3]
    f_x, f_w = motion_jacobians(x_prev, odometry)
    # A P Aᵀ touches only the pose rows and columns: two 3-row products, not two dense D×D ones
    # (16 components of a 213-dimensional hallway state: 10 ms per step dense).
    new_cov = cov.at[:3, :].set(f_x @ cov[:3, :])
    new_cov = new_cov.at[:, :3].set(new_cov[:, :3] @ f_x.T)
    new_cov = new_cov.at[:3, :3].add(f_w @ motion_cov @ f_w.T)
    new_mean = mean.at[:3].set(_move(x_prev, jnp.zeros(3, mean.dtype), odometry))
    return new_mean, 0.5 * (new_cov + new_cov.T)
