"""SE(2) poses as ``[x, y, theta]`` vectors: compose, inverse, between, Exp/Log, wrap.

Every function handles one pose (shape ``(3,)``); batch with ``jax.vmap``. All are
differentiable, including at theta = 0 (the small-angle branches use the double-``where``
trick so no NaN leaks into gradients). Conventions follow SCENARIO_FORMAT.md: ``between(a, b)``
is ``a⁻¹ ∘ b`` and angles are wrapped to (-pi, pi].
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

Pose = Float[Array, "3"]

_SMALL = 1e-6


def wrap(angle: Float[ArrayLike, "*B"]) -> Float[Array, "*B"]:
    """Wrap angles (radians) to (-pi, pi]. Floor-mod, no trigonometry: it sits in the hottest loop."""
    return jnp.pi - jnp.mod(jnp.pi - angle, 2 * jnp.pi)


def rotation(theta: Float[Array, ""]) -> Float[Array, "2 2"]:
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.array([[c, -s], [s, c]])


def compose(a: Pose, b: Pose) -> Pose:
    """``a ∘ b``: the pose ``b`` (given in ``a``'s frame) expressed in the world frame."""
    t = a[:2] + rotation(a[2]) @ b[:2]
    return jnp.concatenate([t, wrap(a[2:] + b[2:])])


def inverse(a: Pose) -> Pose:
    t = -rotation(a[2]).T @ a[:2]
    return jnp.concatenate([t, wrap(-a[2:])])


def between(a: Pose, b: Pose) -> Pose:
    """``a⁻¹ ∘ b``: the pose of ``b`` seen from ``a`` (SCENARIO_FORMAT.md, Conventions)."""
    t = rotation(a[2]).T @ (b[:2] - a[:2])
    return jnp.concatenate([t, wrap(b[2:] - a[2:])])


def _v_coeffs(theta: Float[Array, ""]) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """sin(t)/t and (1 - cos t)/t, with Taylor branches near 0 that keep gradients finite."""
    small = jnp.abs(theta) < _SMALL
    safe = jnp.where(small, 1.0, theta)
    a = jnp.where(small, 1.0 - theta**2 / 6.0, jnp.sin(safe) / safe)
    b = jnp.where(small, theta / 2.0 - theta**3 / 24.0, (1.0 - jnp.cos(safe)) / safe)
    return a, b


def exp(xi: Float[Array, "3"]) -> Pose:
    """SE(2) exponential map of a tangent vector ``[v_x, v_y, omega]``."""
    a, b = _v_coeffs(xi[2])
    v = jnp.array([[a, -b], [b, a]])
    return jnp.concatenate([v @ xi[:2], wrap(xi[2:])])


def log(p: Pose) -> Float[Array, "3"]:
    """SE(2) logarithm: the tangent vector ``xi`` with ``exp(xi) == p`` (theta wrapped)."""
    theta = wrap(p[2])
    a, b = _v_coeffs(theta)
    det = a * a + b * b
    v_inv = jnp.array([[a, b], [-b, a]]) / det
    return jnp.concatenate([v_inv @ p[:2], theta[None]])
