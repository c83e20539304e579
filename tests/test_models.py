"""Motion, geometry and classifier models against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam.models import geometry, motion, se2


def test_range_bearing_and_viewpoint_conventions():
    x = jnp.array([1.0, 2.0, np.pi / 2])  # facing +y
    obj = jnp.array([1.0, 5.0, np.pi])  # 3 m ahead, facing -x
    np.testing.assert_allclose(geometry.range_bearing(x, obj), [3.0, 0.0], atol=1e-12)
    # The camera is at -y of the object in the world; R(pi)ᵀ (0, -3) = (0, 3): +90 degrees.
    np.testing.assert_allclose(geometry.viewpoint_angle(x, obj), np.pi / 2, atol=1e-12)


def test_visibility_footprint():
    x = jnp.zeros(3)
    assert geometry.visible(geometry.range_bearing(x, jnp.array([5.0, 0.0, 0.0])), 6.0, 2.0)
    assert not geometry.visible(geometry.range_bearing(x, jnp.array([7.0, 0.0, 0.0])), 6.0, 2.0)
    assert not geometry.visible(geometry.range_bearing(x, jnp.array([0.0, 3.0, 0.0])), 6.0, 2.0)


@pytest.mark.parametrize("rb, var", [((5.5, 0.4), (0.25, 0.01)), ((3.0, -0.55), (0.04, 0.02)), ((6.4, 0.0), (0.09, 0.3))])
def test_in_view_probability_of_a_gaussian_prediction_matches_monte_carlo(rb, var):
    """``log_visibility_probability``: the 0/1 footprint averaged over ``N(rb, diag(var))``."""
    from hybridslam.models.classifier import NoClassifier
    from hybridslam.models.measurement import SensorModel, log_visibility_probability

    sensor = SensorModel(jnp.eye(2) * 0.01, NoClassifier(2), jnp.asarray(6.0), jnp.asarray(1.2))
    got = float(jnp.exp(log_visibility_probability(sensor, jnp.asarray(rb), jnp.asarray(var))))
    draws = np.random.default_rng(0).normal(rb, np.sqrt(var), (400_000, 2))
    want = np.mean((draws[:, 0] <= 6.0) & (np.abs(draws[:, 1]) <= 0.6))
    assert 0.02 < want < 0.98
    assert got == pytest.approx(want, abs=4e-3)


def test_propagate_mean_and_covariance_match_monte_carlo():
    mean = jnp.array([1.0, -1.0, 0.3, 5.0, 5.0, 0.0])
    cov = jnp.diag(jnp.array([0.02, 0.03, 0.01, 0.05, 0.05, 1e-3]))
    u, q = jnp.array([1.0, 0.2, 0.1]), jnp.diag(jnp.array([0.01, 0.005, 0.002]))
    new_mean, new_cov = motion.propagate(mean, cov, u, q)
    rng = np.random.default_rng(0)
    x0 = rng.multivariate_normal(np.asarray(mean[:3]), np.asarray(cov[:3, :3]), 200_000)
    w = rng.multivariate_normal(np.zeros(3), np.asarray(q), 200_000)
    x1 = jax.vmap(lambda a, b: se2.compose(se2.compose(a, u), se2.exp(b)))(jnp.asarray(x0), jnp.asarray(w))
    np.testing.assert_allclose(new_mean[:3], x1.mean(0), atol=5e-3)
    np.testing.assert_allclose(new_cov[:3, :3], np.cov(np.asarray(x1).T), atol=2e-3)
    np.testing.assert_array_equal(new_cov[3:, 3:], cov[3:, 3:])  # objects are static


def test_propagate_is_the_dense_ekf_prediction_with_correlated_objects():
    """The pose-rows-only update equals ``A P Aᵀ + B Σ_w Bᵀ`` with the dense ``A = blockdiag(F_x, I)``
    (Eq. 11), cross-covariances with the objects included."""
    rng = np.random.default_rng(1)
    root = rng.standard_normal((9, 9))
    mean, cov = jnp.asarray(rng.standard_normal(9)), jnp.asarray(root @ root.T + 0.1 * np.eye(9))
    u, q = jnp.array([0.8, -0.3, 0.4]), jnp.diag(jnp.array([0.01, 0.005, 0.002]))
    _, new_cov = motion.propagate(mean, cov, u, q)
    zero = jnp.zeros(3)
    move = lambda x, w: se2.compose(se2.compose(x, u), se2.exp(w))  # noqa: E731
    f_x, f_w = jax.jacfwd(move, 0)(mean[:3], zero), jax.jacfwd(move, 1)(mean[:3], zero)
    a = np.eye(9)
    a[:3, :3] = f_x
    b = np.zeros((9, 3))
    b[:3] = f_w
    np.testing.assert_allclose(new_cov, a @ np.asarray(cov) @ a.T + b @ np.asarray(q) @ b.T, rtol=1e-12, atol=1e-12)


def test_odometry_residual_is_zero_on_the_odometry():
    x0, u = jnp.array([2.0, 1.0, -0.4]), jnp.array([0.7, -0.1, 0.25])
    np.testing.assert_allclose(motion.odometry_residual(x0, se2.compose(x0, u), u), jnp.zeros(3), atol=1e-12)


def test_mirror_matches_eq18():
    clf = hs.Mirror(0.25, 15.0)
    theta = 1.1
    v = jnp.array([np.cos(theta), np.sin(theta)])
    s = np.sin(theta / 2) ** 2
    np.testing.assert_allclose(clf.class_means(v)[0], [0.25 * s + 0.75, 0.25 - 0.25 * s])
    np.testing.assert_allclose(clf.class_means(v)[1], [0.25 - 0.25 * s, 0.25 * s + 0.75])
    r = 15.0 * np.array([[1.0, -0.5], [0.0, 1.0]])
    z = jnp.array([0.7, 0.2])
    cov = np.linalg.inv(r.T @ r)
    d = np.asarray(z) - np.asarray(clf.class_means(v)[1])
    expected = -0.5 * d @ np.linalg.solve(cov, d) - 0.5 * np.log(np.linalg.det(2 * np.pi * cov))
    np.testing.assert_allclose(clf.log_likelihood(z, 1, v), expected, rtol=1e-10)


@pytest.mark.parametrize("alpha", [0.1, 0.25, 0.5])
def test_independent_is_the_viewpoint_average_of_mirror(alpha):
    mirror, indep = hs.Mirror(alpha, 15.0), hs.Independent(alpha, 15.0)
    thetas = np.linspace(-np.pi, np.pi, 20001)[:-1]
    dirs = jnp.stack([jnp.cos(thetas), jnp.sin(thetas)], -1)
    means = jax.vmap(mirror.class_means)(dirs)[:, 0]  # (n, 2) class-0 means
    r = np.asarray(mirror.class_sqrt_informations(dirs[0])[0])
    total_cov = np.linalg.inv(r.T @ r) + np.cov(np.asarray(means).T, bias=True)
    np.testing.assert_allclose(indep.class_means(dirs[0])[0], means.mean(0), atol=1e-9)
    np.testing.assert_allclose(indep.covariance(), total_cov, atol=1e-8)


def test_alpha_k_is_mirror_or_independent_as_its_traced_leaf_says():
    """One jitted function of AlphaK (the sweeps' shared program) gives each model's own numbers."""
    from hybridslam.models.classifier import AlphaK

    dirs = jnp.array([[1.0, 0.0], [0.6, 0.8], [-1.0, 0.0]])
    scores = jnp.array([0.3, 0.9])

    @jax.jit
    def parts(model, v):
        return model.class_means(v), model.class_sqrt_informations(v), model.residuals(scores, v)

    for model, dependence in ((hs.Mirror(0.3, 15.0), 1.0), (hs.Independent(0.3, 15.0), 0.0)):
        shared = AlphaK(0.3, 15.0, dependence)
        assert shared.viewpoint_dependent
        for v in dirs:
            for a, b in zip(jax.tree.leaves(parts(shared, v)), jax.tree.leaves(parts(model, v)), strict=True):
                np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14)


def test_none_classifier_ignores_scores():
    clf = hs.NoClassifier(2)
    v = jnp.array([1.0, 0.0])
    assert float(clf.log_likelihood(jnp.array([0.3, 0.9]), 0, v)) == 0.0
    assert not clf.uses_scores


def test_mirror_sampling_matches_its_covariance():
    clf = hs.Mirror(0.25, 15.0)
    v = jnp.array([0.0, 1.0])
    keys = jax.random.split(jax.random.PRNGKey(0), 20000)
    z = jax.vmap(lambda k: clf.sample(k, 0, v))(keys)
    r = np.asarray(clf.class_sqrt_informations(v)[0])
    np.testing.assert_allclose(np.cov(np.asarray(z).T), np.linalg.inv(r.T @ r), rtol=0.05)
    np.testing.assert_allclose(z.mean(0), clf.class_means(v)[0], atol=2e-3)


def test_confusion_and_unknown_map_scenarios_build_models():
    from hybridslam.io.scenario import Classifier, Discovery

    scenario = hs.simulate(0, steps=1)
    confusion = scenario.replace(classifier=Classifier("confusion", matrix=np.eye(2)))
    assert hs.model_from_scenario(confusion).num_classes == 2  # issue 4 (tests/test_classifier_confusion.py)
    hs.model_from_scenario(confusion, "none")  # an explicit override still runs the file
    unknown_map = scenario.replace(discovery=Discovery(10, -4.0, 9.87))
    model = hs.model_from_scenario(unknown_map)  # issue 4 (tests/test_discovery.py)
    assert model.class_prior.shape[0] == 10  # one class-prior row per object slot
