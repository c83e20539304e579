"""Range-bearing observation geometry, viewpoint angle and the object observation model.

Conventions from SCENARIO_FORMAT.md. The geometric likelihood is the paper's
``P(z^geo | x_k, x^o) = N(h^geo(x_k, x^o), Σ_v)`` (Sec. III, Eq. 10); visibility is the object
observation model ``P(β_k | x_k, X^o)`` of Sec. IV-B (1 if every named object is in view), or its
smooth relaxation :func:`log_smooth_visibility` (differentiable; see ``docs/gradients.md``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from . import se2


def _to_frame(pose: se2.Pose, dx: Float[Array, ""], dy: Float[Array, ""]):
    """``R(θ)ᵀ [dx, dy]``, written out: tiny matmuls batch poorly on CPU, elementwise math fuses."""
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    return c * dx + s * dy, c * dy - s * dx


def _range_bearing(x: se2.Pose, obj: se2.Pose) -> Float[Array, "2"]:
    qx, qy = _to_frame(x, obj[0] - x[0], obj[1] - x[1])
    rng = jnp.sqrt(qx**2 + qy**2 + 1e-300)  # the tiny floor keeps d/dq finite at q = 0
    # atan2's derivative is 0/0 at q = 0 (an object created from a zero-range detection sits on the
    # robot): there the bearing is 0 with a zero derivative. Elsewhere the value is unchanged.
    origin = (qx == 0.0) & (qy == 0.0)
    bearing = jnp.where(origin, 0.0, jnp.arctan2(qy, jnp.where(origin, 1.0, qx)))
    return jnp.stack([rng, bearing])


@jax.custom_jvp
def range_bearing(x: se2.Pose, obj: se2.Pose) -> Float[Array, "2"]:
    """``h^geo``: ``[range, bearing]`` of the object's position seen from robot pose ``x`` (Eq. 10).

    Differentiated in closed form (:func:`range_bearing_jacobians`), not through ``atan2``'s and
    ``sqrt``'s own rules: its derivative sits inside every Jacobian of the filters and smoothers.
    """
    return _range_bearing(x, obj)


def range_bearing_position_jacobian(
    x: se2.Pose, obj: se2.Pose
) -> tuple[Float[Array, "2 2"], Float[Array, "2"]]:
    """``∂h/∂p_o`` (2×2) and ``∂h/∂θ_x`` (2,) of :func:`range_bearing` in closed form (Eq. 10).

    With ``d = p_o − p_x`` (world frame) and ``r = ‖d‖``: ``∂r/∂p_o = dᵀ/r``, ``∂b/∂p_o =
    [−d_y, d_x]/r²``, ``∂h/∂p_x = −∂h/∂p_o``, ``∂h/∂θ_x = [0, −1]``; the object's heading does not
    enter. At ``d = 0`` (an object on the robot) both are 0, as :func:`range_bearing` defines.
    """
    d = obj[:2] - x[:2]
    r2 = jnp.dot(d, d)
    origin = r2 == 0.0
    safe = jnp.where(origin, 1.0, r2)  # double where: no 0/0 in a second derivative
    perp = jnp.stack([-d[1], d[0]])
    jac = jnp.stack([d * jax.lax.rsqrt(safe), perp / safe])
    return jnp.where(origin, 0.0, jac), jnp.where(origin, 0.0, jnp.array([0.0, -1.0], jac.dtype))


@range_bearing.defjvp
def _range_bearing_jvp(primals, tangents):
    (x, obj), (dx, dobj) = primals, tangents
    jac, turn = range_bearing_position_jacobian(x, obj)
    return _range_bearing(x, obj), jac @ (dobj[:2] - dx[:2]) + turn * dx[2]


def range_bearing_jacobians(x: se2.Pose, obj: se2.Pose) -> tuple[Float[Array, "2 3"], Float[Array, "2 3"]]:
    """``(∂h/∂x, ∂h/∂o)`` of :func:`range_bearing`, ``(2, 3)`` each, in closed form
    (:func:`range_bearing_position_jacobian`; the object's heading column is 0)."""
    jac, turn = range_bearing_position_jacobian(x, obj)
    return (jnp.concatenate([-jac, turn[:, None]], axis=1),
            jnp.concatenate([jac, jnp.zeros((2, 1), jac.dtype)], axis=1))


def _viewpoint(x: se2.Pose, obj: se2.Pose) -> tuple[Float[Array, "2"], Float[Array, ""]]:
    """The unit vector of :func:`viewpoint` and ``‖v‖``."""
    vx, vy = _to_frame(obj, x[0] - obj[0], x[1] - obj[1])
    norm = jnp.sqrt(vx**2 + vy**2 + 1e-300)
    return jnp.stack([vx / norm, vy / norm]), norm


@jax.custom_jvp
def viewpoint(x: se2.Pose, obj: se2.Pose) -> Float[Array, "2"]:
    """Direction of the camera seen from the object, as the unit vector ``(cos θ, sin θ)``.

    ``θ = atan2(v_y, v_x)`` with ``v = R(θ_o)ᵀ (p_x − p_o)`` (SCENARIO_FORMAT.md). Classifier
    models take the unit vector: it is continuous across ±π and needs no ``atan2``. Differentiated
    in closed form: ``δv = R(θ_o)ᵀ(δp_x − δp_o) + [v_y, −v_x] δθ_o`` and, with ``u = v/‖v‖`` and
    ``u⊥ = [−u_y, u_x]``, ``δu = u⊥ (u⊥ · δv) / ‖v‖`` (the projection of ``δv/‖v‖`` off ``u``).
    """
    return _viewpoint(x, obj)[0]


@viewpoint.defjvp
def _viewpoint_jvp(primals, tangents):
    (x, obj), (dx, dobj) = primals, tangents
    u, norm = _viewpoint(x, obj)
    perp = jnp.stack([-u[1], u[0]])
    # δu = u⊥ u⊥ᵀ δv / ‖v‖ with δv = R(θ_o)ᵀ(δp_x − δp_o) + [v_y, −v_x] δθ_o; u⊥ᵀ [v_y, −v_x] = −‖v‖.
    project = perp[:, None] * perp[None, :] @ se2.rotation(obj[2]).T / norm
    return u, project @ (dx[:2] - dobj[:2]) - perp * dobj[2]


def viewpoint_angle(x: se2.Pose, obj: se2.Pose) -> Float[Array, ""]:
    """The viewpoint as an angle in (-pi, pi]."""
    v = viewpoint(x, obj)
    return jnp.arctan2(v[1], v[0])


def geometric_residual(z: Float[Array, "2"], predicted: Float[Array, "2"]) -> Float[Array, "2"]:
    """``z - h^geo`` with the bearing difference wrapped (unwhitened)."""
    return jnp.stack([z[0] - predicted[0], se2.wrap(z[1] - predicted[1])])


def visible(
    range_bearing_: Float[Array, "2"], max_range: Float[ArrayLike, ""], fov: Float[ArrayLike, ""]
) -> Bool[Array, ""]:
    """Sensor footprint: ``range <= max_range`` and ``|bearing| <= fov / 2``."""
    return (range_bearing_[0] <= max_range) & (jnp.abs(range_bearing_[1]) <= 0.5 * fov)


def log_smooth_visibility(
    range_bearing_: Float[Array, "2"], max_range: Float[ArrayLike, ""], fov: Float[ArrayLike, ""],
    temperature: Float[Array, "2"],
) -> Float[Array, ""]:
    """Log of the smooth sensor footprint, a product of logistic sigmoids of the three margins:

        P(visible) = σ((max_range − r) / τ_r) · σ((fov/2 − b) / τ_b) · σ((fov/2 + b) / τ_b)

    with ``temperature = (τ_r, τ_b)`` in metres and radians: the distance over which the
    probability falls from 73 % to 27 % across the edge is ``2 τ``. The two bearing factors (rather
    than one of ``|b|``) keep it smooth at ``b = 0``; the product is even in ``b``, so it is also
    continuous across ``b = ±π``. As ``τ → 0`` it tends to :func:`visible`; a temperature of exactly 0
    gives that hard limit (``0`` or ``-inf``), with zero gradient.
    """
    half = 0.5 * fov
    margins = jnp.stack([max_range - range_bearing_[0], half - range_bearing_[1], half + range_bearing_[1]])
    tau = jnp.stack([temperature[0], temperature[1], temperature[1]])
    smooth = tau > 0
    safe = jnp.where(smooth, tau, 1.0)  # double where: no NaN gradient from the τ = 0 branch
    return jnp.sum(jnp.where(smooth, jax.nn.log_sigmoid(margins / safe), jnp.where(margins >= 0, 0.0, -jnp.inf)))
