"""The Gauss-Newton measurement update (Eq. 9-11)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import hybridslam as hs
from hybridslam.inference.update import _residuals, gauss_newton, gauss_newton_update
from hybridslam.models import geometry

# Jitted once per shape: op by op, the update's surrounding array code costs seconds of dispatch.
# Both update tests use the same shapes (robot and two objects, two detection slots): one program.
_update = jax.jit(gauss_newton_update, static_argnums=6)
MEAN = jnp.array([0.0, 0.0, 0.1, 5.0, 1.0, 0.4, 5.0, -1.5, 2.0])
COV = jnp.diag(jnp.array([0.5, 0.5, 0.02, 0.05, 0.05, 1e-3, 0.05, 0.05, 1e-3]))


def test_gauss_newton_equals_direct_solve_on_a_linear_problem():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(12, 5)), rng.normal(size=12)
    solve = eqx.filter_jit(lambda a, b: gauss_newton(lambda y, _: a @ y - b, jnp.zeros(5), None, 20))
    value, cov, result = solve(jnp.asarray(a), jnp.asarray(b))
    assert result == optx.RESULTS.successful
    np.testing.assert_allclose(value, np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(cov, np.linalg.inv(a.T @ a), rtol=1e-10)


def test_update_reaches_the_stationary_point_of_eq9():
    """Nonlinear case: at the returned mean a further Gauss-Newton step is ~0 and the covariance is (JᵀJ)⁻¹."""
    scenario = hs.simulate(0, steps=1)
    sensor = hs.model_from_scenario(scenario, "mirror").sensor
    mean, cov = MEAN, COV
    # Measurements near what the prior mean predicts (off by about one noise sigma).
    geo = jnp.stack([geometry.range_bearing(mean[:3], mean[3:6]), geometry.range_bearing(mean[:3], mean[6:9])])
    det = hs.Detections(geo + jnp.array([[0.3, -0.1], [-0.2, 0.15]]), jnp.array([[0.9, 0.2], [0.3, 0.75]]), jnp.array([True, True]))
    assign, cls = jnp.array([0, 1]), jnp.array([0, 1])
    new_mean, new_cov, result = _update(sensor, mean, cov, assign, cls, det, 20)
    args = (sensor, mean, jnp.linalg.cholesky(cov), assign, cls, det)
    jacobian_and_residuals = jax.jit(lambda y: (jax.jacfwd(_residuals)(y, args), _residuals(y, args)))
    jac, res = (np.asarray(a) for a in jacobian_and_residuals(new_mean))
    new_cov, cov = np.asarray(new_cov), np.asarray(cov)
    newton_step = np.linalg.solve(jac.T @ jac, jac.T @ res)
    assert result == optx.RESULTS.successful
    assert float(np.max(np.abs(newton_step))) < 1e-6
    np.testing.assert_allclose(new_cov, np.linalg.inv(jac.T @ jac), rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(new_cov, new_cov.T, atol=0)
    assert bool(np.all(np.linalg.eigvalsh(new_cov) > 0))
    assert float(np.linalg.det(new_cov[:2, :2])) < float(np.linalg.det(cov[:2, :2]))  # information was added


def test_update_without_detections_keeps_the_prior():
    scenario = hs.simulate(0, steps=1)
    sensor = hs.model_from_scenario(scenario, "mirror").sensor
    mean, cov = MEAN, COV
    det = hs.Detections(jnp.zeros((2, 2)), jnp.zeros((2, 2)), jnp.array([False, False]))
    new_mean, new_cov, _ = _update(sensor, mean, cov, jnp.array([-1, -1]), jnp.array([0, 0]), det, 20)
    np.testing.assert_allclose(new_mean, mean, atol=1e-12)
    np.testing.assert_allclose(new_cov, cov, rtol=1e-10, atol=1e-15)


def test_kalman_form_gauss_newton_equals_gauss_newton_with_a_prior_factor():
    """update.prior_gauss_newton (iterated EKF) has the same mode and covariance as update.gauss_newton."""
    import jax.scipy.linalg as jsl

    from hybridslam.inference.update import gauss_newton, prior_gauss_newton, support_of, wrap_angles
    from hybridslam.models import geometry

    rng = np.random.default_rng(0)
    mean = jnp.asarray(rng.normal(size=12)).at[2::3].set(0.3)
    a = rng.normal(size=(12, 12)) * 0.3
    cov = jnp.asarray(a @ a.T + 0.05 * np.eye(12))
    z = jnp.array([[3.0, 0.2], [2.0, -0.4]])

    def measurement(y, _):
        objs = y[3:].reshape(-1, 3)
        return jnp.concatenate([geometry.geometric_residual(z[i], geometry.range_bearing(y[:3], objs[i])) / 0.1
                                for i in range(2)])

    def with_prior(y, _):
        white = jsl.solve_triangular(jnp.linalg.cholesky(cov), wrap_angles(y - mean), lower=True)
        return jnp.concatenate([white, measurement(y, None)])

    @eqx.filter_jit  # one compiled program for the three solves (op by op: hundreds of tiny compiles)
    def solves():
        support = support_of(jnp.array([0, 1, -1]))
        return (prior_gauss_newton(measurement, mean, cov, None, 50), gauss_newton(with_prior, mean, None, 50),
                prior_gauss_newton(measurement, mean, cov, None, 50, support))

    (y1, c1, r1), (y2, c2, _), (y3, c3, _) = solves()
    assert r1 == optx.RESULTS.successful
    np.testing.assert_allclose(y1, y2, atol=1e-10)
    np.testing.assert_allclose(c1, c2, atol=1e-10)
    # The Jacobian over the entries the measurement reads (robot, objects 0 and 1; object 0 named
    # twice, as an empty slot names it): the same mode and covariance; object 2 moves only through
    # its prior correlation.
    np.testing.assert_allclose(y3, y1, atol=1e-12)
    np.testing.assert_allclose(c3, c1, atol=1e-12)
