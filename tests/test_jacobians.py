"""Closed-form Jacobians (Eq. 10, Eq. 11, discovery's back-projection) against ``jax.jacfwd``.

Each closed form is compared with JAX's own derivative of the same function written without it
(``geometry._range_bearing``, ``geometry._viewpoint``, ``motion._move``, ``discovery.back_project``)
on a fixed random batch of poses, first and second derivatives (``jax.grad`` and ``jax.hessian``
go through the closed forms), all in one jitted program.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hybridslam.inference import discovery
from hybridslam.models import geometry, motion

_BATCH = 64


def _errors(x, obj, odometry, geo):
    """Largest absolute difference of each closed form from its automatic derivative."""
    zero = jnp.zeros(3, x.dtype)
    vmap = jax.vmap
    raw_rb = geometry._range_bearing
    raw_vp = lambda a, b: geometry._viewpoint(a, b)[0]  # noqa: E731
    weights = jnp.array([1.0, -2.0])
    out = {
        "range_bearing jvp": (vmap(jax.jacfwd(geometry.range_bearing, (0, 1)))(x, obj),
                              vmap(jax.jacfwd(raw_rb, (0, 1)))(x, obj)),
        "range_bearing_jacobians": (vmap(geometry.range_bearing_jacobians)(x, obj),
                                    vmap(jax.jacfwd(raw_rb, (0, 1)))(x, obj)),
        "range_bearing hessian": (
            vmap(jax.hessian(lambda a, b: weights @ geometry.range_bearing(a, b) ** 2, (0, 1)))(x, obj),
            vmap(jax.hessian(lambda a, b: weights @ raw_rb(a, b) ** 2, (0, 1)))(x, obj)),
        "viewpoint jvp": (vmap(jax.jacfwd(geometry.viewpoint, (0, 1)))(x, obj),
                          vmap(jax.jacfwd(raw_vp, (0, 1)))(x, obj)),
        "viewpoint hessian": (
            vmap(jax.hessian(lambda a, b: weights @ geometry.viewpoint(a, b), (0, 1)))(x, obj),
            vmap(jax.hessian(lambda a, b: weights @ raw_vp(a, b), (0, 1)))(x, obj)),
        "motion_jacobians": (vmap(motion.motion_jacobians)(x, odometry),
                             vmap(lambda a, u: jax.jacfwd(motion._move, (0, 1))(a, zero, u))(x, odometry)),
        # The closed form is itself differentiable: d(∂f/∂x)/du, as jax.grad through propagate needs.
        "motion_jacobians d/du": (vmap(jax.jacfwd(motion.motion_jacobians, 1))(x, odometry),
                                  vmap(jax.jacfwd(lambda a, u: jax.jacfwd(motion._move, (0, 1))(a, zero, u), 1))(
                                      x, odometry)),
        "back_project_jacobians": (vmap(discovery.back_project_jacobians)(x, geo),
                                   vmap(jax.jacfwd(discovery.back_project, (0, 1)))(x, geo)),
    }
    def error(got, want):  # relative to 1 + |want|: derivatives near the robot reach 1/r² ~ 1e6
        return jnp.max(jnp.stack([jnp.max(jnp.abs(a - b) / (1.0 + jnp.abs(b)))
                                  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True)]))

    return {k: error(got, want) for k, (got, want) in out.items()}


@pytest.fixture(scope="module")
def errors():
    rng = np.random.default_rng(7)
    x = rng.uniform([-20, -20, -np.pi], [20, 20, np.pi], (_BATCH, 3))
    obj = rng.uniform([-20, -20, -np.pi], [20, 20, np.pi], (_BATCH, 3))
    obj[:4, :2] = x[:4, :2] + rng.normal(0, 1e-3, (4, 2))  # objects close to the robot
    odometry = rng.uniform([-2, -2, -1], [2, 2, 1], (_BATCH, 3))
    odometry[:4, 2] = 0.0  # straight moves
    geo = np.c_[rng.uniform(0.0, 30.0, _BATCH), rng.uniform(-np.pi, np.pi, _BATCH)]
    return {k: float(v) for k, v in jax.jit(_errors)(x, obj, odometry, geo).items()}


@pytest.mark.parametrize("name", ["range_bearing jvp", "range_bearing_jacobians", "range_bearing hessian",
                                  "viewpoint jvp", "viewpoint hessian", "motion_jacobians",
                                  "motion_jacobians d/du", "back_project_jacobians"])
def test_closed_form_matches_jacfwd(errors, name):
    assert errors[name] < 1e-9, errors


def test_range_bearing_derivative_at_the_robot_is_zero():
    """An object on the robot (created from a zero-range detection): range and bearing have a zero
    derivative there, as :func:`geometry.range_bearing` defines, and no NaN."""

    @jax.jit
    def at_origin(x):
        return jax.jacfwd(geometry.range_bearing, (0, 1))(x, x), geometry.range_bearing_jacobians(x, x)

    for jac in jax.tree.leaves(at_origin(jnp.array([1.0, -2.0, 0.3]))):
        np.testing.assert_array_equal(np.asarray(jac)[:, :2], 0.0)
        assert np.all(np.isfinite(np.asarray(jac)))
