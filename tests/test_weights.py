"""PropWeights (Eq. 16) against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.stats import multivariate_normal as mvn

import hybridslam as hs
from hybridslam.estimators.hybrid.hypotheses import children, hypothesis_table
from hybridslam.estimators.hybrid.weights import (
    linearized_log_likelihood,
    log_mean_exp_outer,
    sampled_log_likelihood,
)


@jax.numpy_rank_promotion("allow")  # jax.scipy's logpdf broadcasts internally
def test_log_mean_exp_outer_matches_linear_gaussian_evidence():
    """Linear-Gaussian toy: z_j = H_i x + v, x ~ N(mu, P). The Monte-Carlo mean of Eq. 16 over
    samples of x must equal the analytic marginal likelihood N(z; H mu, H P Hᵀ + R) of every pair
    (i_1, i_2), within its own Monte-Carlo error."""
    rng = np.random.default_rng(0)
    mu, p = jnp.array([0.5, -0.2]), jnp.array([[0.3, 0.1], [0.1, 0.2]])
    hs_ = jnp.asarray(rng.normal(size=(3, 2, 2)))  # three candidate "objects"
    r = 0.5 * jnp.eye(2)
    z = jnp.array([[0.4, 0.1], [-0.3, 0.6]])  # two detections
    x = jax.random.multivariate_normal(jax.random.PRNGKey(1), mu, p, (20000,))
    tables = jnp.stack(
        [jnp.stack([mvn.logpdf(z[j][None, :] - x @ hs_[i].T, jnp.zeros(2), r) for i in range(3)], -1) for j in range(2)], 1
    )  # (S, 2, 3)
    estimate = log_mean_exp_outer(tables)
    per_sample = tables[:, 0, :, None] + tables[:, 1, None, :]
    rel_err = jnp.std(jnp.exp(per_sample), 0) / jnp.mean(jnp.exp(per_sample), 0) / np.sqrt(x.shape[0])
    for i1 in range(3):
        for i2 in range(3):
            h = jnp.concatenate([hs_[i1], hs_[i2]])
            cov = h @ p @ h.T + jnp.kron(jnp.eye(2), r)
            exact = mvn.logpdf(z.reshape(-1), h @ mu, cov)
            assert abs(float(estimate[i1, i2] - exact)) < 4 * float(rel_err[i1, i2]) + 1e-3


def test_log_mean_exp_outer_is_exact_in_the_log_domain():
    """Any absolute scale (here around -5000 nats) and entries hundreds of nats apart: entries within
    600 nats of the best are exact; ones further below may only underflow to -inf (pruned anyway)."""
    t = jnp.array([[[-900.0, -1.0], [-2.0, -1200.0]], [[-905.0, -3.0], [-1.0, -300.0]]]) - 2500.0
    brute = jax.scipy.special.logsumexp(t[:, 0, :, None] + t[:, 1, None, :], axis=0) - np.log(2)
    got = log_mean_exp_outer(t)
    near = brute > brute.max() - 600
    np.testing.assert_allclose(got[near], brute[near], rtol=1e-12)
    assert bool(jnp.all((got[~near] == -jnp.inf) | jnp.isclose(got[~near], brute[~near], rtol=1e-12)))
    assert int(near.sum()) >= 2 and int((~near).sum()) >= 1


def _near_linear_setup():
    """One precisely known robot looking at two objects 5 m away: range-bearing is nearly linear."""
    scenario = hs.simulate(0, steps=1)
    model = hs.model_from_scenario(scenario, "mirror")
    mean = jnp.array([0.0, 0.0, 0.0, 5.0, 1.0, 0.4, 5.0, -1.5, 2.0])
    cov = jnp.diag(jnp.array([1e-3, 1e-3, 1e-4, 0.02, 0.02, 1e-3, 0.02, 0.02, 1e-3]))
    det = hs.Detections(jnp.array([[5.15, 0.2], [0.0, 0.0]]), jnp.array([[0.9, 0.2], [0.0, 0.0]]), jnp.array([True, False]))
    table = hypothesis_table(2, 2, 2)
    kids = children(table, jnp.array([-1, -1]), det.mask, jnp.full((2, 2), 0.5))
    return model, mean, cov, det, table, kids


def test_sampled_weight_matches_linearized_where_the_model_is_linear(monkeypatch):
    """Near-linear measurements: the Monte-Carlo weight equals the linearized closed form (thesis
    Eq. 4.14-4.15) for every plausible child, whichever slots hold the detections. Chunks of 2 table
    rows make the linearized weights skip most of the table (only rows matching the mask are
    evaluated), so a wrongly skipped child would show up here as a mismatch."""
    from hybridslam.estimators.hybrid import weights

    monkeypatch.setattr(weights, "ROW_CHUNK", 2)
    model, mean, cov, _, table, _ = _near_linear_setup()
    geo, scores = jnp.array([[5.15, 0.2], [5.3, -0.25]]), jnp.array([[0.9, 0.2], [0.3, 0.7]])
    eps = jax.random.normal(jax.random.PRNGKey(0), (20000, mean.shape[0]))

    # Jitted (op by op, 20000 samples through the vmapped tables take ~30 s of dispatch); the mask is traced.
    @jax.jit
    def both(det, kids):
        sampled = sampled_log_likelihood(model.sensor, mean, cov, det, eps, table, kids)[0]
        return sampled, linearized_log_likelihood(model.sensor, mean, cov, det, table, kids)[0]

    for mask, plausible in (([True, False], 2), ([False, True], 1), ([True, True], 1)):
        det = hs.Detections(geo, scores, jnp.array(mask))
        kids = children(table, jnp.array([-1, -1]), det.mask, jnp.full((2, 2), 0.5))
        sampled, linear = both(det, kids)
        ok = kids.valid & (linear > -20)  # the plausible children
        assert int(ok.sum()) == plausible, mask
        np.testing.assert_allclose(sampled[ok], linear[ok], atol=0.02)


def test_weights_are_log_probabilities_of_the_children():
    """Children of one parent that are not valid for the detection mask are never used."""
    _, _, _, det, table, kids = _near_linear_setup()
    # 1 detection among 2 objects, 2 classes each: 4 valid children.
    assert int(kids.valid.sum()) == 4


def test_children_and_sampled_weights_match_brute_force():
    """Reference for PropWeights: enumerate the children of one parent by hand (object 0 already of
    class 1, objects 1-2 open) and average the joint likelihood × visibility over the same samples."""
    import itertools

    from jax.scipy.special import logsumexp

    from hybridslam.models.geometry import range_bearing, visible
    from hybridslam.models.measurement import detection_residual

    scenario = hs.simulate(0, steps=1)
    sensor = hs.model_from_scenario(scenario, "mirror").sensor
    mean = jnp.array([0.0, 0.0, 0.0, 4.0, 1.0, 0.4, 4.5, -1.5, 2.0, -3.0, 3.5, -1.0])  # object 2 behind
    cov = jnp.diag(jnp.array([0.3, 0.3, 0.05, 0.05, 0.05, 1e-3, 0.05, 0.05, 1e-3, 0.05, 0.05, 1e-3]))
    det = hs.Detections(jnp.array([[4.2, 0.3], [4.6, -0.35]]), jnp.array([[0.9, 0.2], [0.3, 0.7]]), jnp.array([True, True]))
    parent_classes = jnp.array([1, -1, -1], dtype=jnp.int32)
    class_prior = jnp.array([[0.5, 0.5], [0.2, 0.8], [0.6, 0.4]])
    table = hypothesis_table(3, 2, 2)
    kids = children(table, parent_classes, det.mask, class_prior)
    eps = jax.random.normal(jax.random.PRNGKey(3), (256, mean.shape[0]))
    got, _, _ = jax.jit(lambda: sampled_log_likelihood(sensor, mean, cov, det, eps, table, kids))()
    got = got + kids.log_prior

    samples = mean[None, :] + eps @ jnp.linalg.cholesky(cov).T

    @jax.jit
    def per_sample(s, objs, cls):
        x, o = s[:3], s[3:].reshape(-1, 3)
        total = 0.0
        for j in range(2):
            r, log_norm = detection_residual(sensor, x, o[objs[j]], det.geo[j], det.scores[j], cls[j])
            seen = visible(range_bearing(x, o[objs[j]]), sensor.max_range, sensor.fov)
            total = total + jnp.where(seen, log_norm - 0.5 * jnp.sum(r**2), -jnp.inf)
        return total

    expected = {}
    for objs in itertools.permutations(range(3), 2):
        open_ = [n for n in objs if int(parent_classes[n]) < 0]
        for new_classes in itertools.product(range(2), repeat=len(open_)):
            realized = dict(zip(open_, new_classes))
            cls = [realized.get(n, int(parent_classes[n])) for n in objs]
            lik = jax.vmap(per_sample, (0, None, None))(samples, jnp.array(objs), jnp.array(cls))
            prior = sum(float(jnp.log(class_prior[n, c])) for n, c in realized.items())
            expected[(objs, tuple(cls))] = float(logsumexp(lik) - np.log(samples.shape[0])) + prior

    found = {}
    assign = np.asarray(table.assign)
    for a, m in zip(*np.nonzero(np.asarray(kids.valid))):
        key_ = (tuple(int(o) for o in assign[a]), tuple(int(c) for c in np.asarray(kids.slot_class[a, m])))
        assert key_ not in found  # every child appears once
        found[key_] = float(got[a, m])
    assert found.keys() == expected.keys() and len(found) == 16
    for key_, value in expected.items():
        if value > -np.inf:
            np.testing.assert_allclose(found[key_], value, rtol=1e-9, atol=1e-9)
        else:
            assert found[key_] == -np.inf
    assert any(v > -np.inf for v in expected.values()) and any(v == -np.inf for v in expected.values())



def test_linear_tables_equal_the_dense_jacobian_products():
    """The tables take each row's Jacobian as two 3-column blocks (pose, its object) and Σ over
    [x, objs] only: J Σ Jᵀ equals the product with the dense Jacobian over the whole state, on a
    random full covariance, with a candidate list that repeats an object (gating); each in-view
    term reads its own [x, object] block."""
    from hybridslam.estimators.hybrid.weights import _log_visibility_probability, linear_tables
    from hybridslam.models.measurement import detection_residual

    scenario = hs.simulate(0, steps=1)
    sensor = hs.model_from_scenario(scenario, "mirror").sensor
    rng = np.random.default_rng(3)
    n = 5
    mean = jnp.asarray(np.concatenate([[0.3, -0.2, 0.1], rng.normal(0, 4, 3 * n)]))
    a = rng.normal(size=(3 + 3 * n, 3 + 3 * n))
    cov = jnp.asarray(0.05 * a @ a.T / (3 + 3 * n) + 1e-3 * np.eye(3 + 3 * n))
    det = hs.Detections(jnp.array([[4.0, 0.3], [2.0, -0.5]]), jnp.array([[0.7, 0.3], [0.2, 0.8]]),
                        jnp.array([True, True]))
    objs = jnp.array([3, 0, 3, 1])
    got = linear_tables(sensor, mean, cov, det, objs)
    m = sensor.classifier.num_classes

    @jax.jit  # compiled once for the 16 (detection, object, class) checks below, not dispatched op by op
    def row(state, o, c, j):  # detection j's whitened residual and log normalizer, object o, class c
        return detection_residual(sensor, state[:3], state[3:].reshape(-1, 3)[o], det.geo[j], det.scores[j], c)

    for j in range(2):  # every class's rows come from one residual evaluation: the same as class by class
        for i, o in enumerate(np.asarray(objs)):
            for c in range(m):
                r, log_norm = row(mean, o, jnp.asarray(c), j)
                np.testing.assert_allclose(got.r_bar[j, i, c], r, rtol=1e-15, atol=1e-15)
                np.testing.assert_allclose(got.log_norm[j, i, c], log_norm, rtol=1e-15)
    jac = jax.vmap(jax.vmap(jax.jacfwd(lambda s, o, c: row(s, o, c, 0)[0]), (None, None, 0)), (None, 0, None))(
        mean, objs, jnp.arange(m))
    jac = jac.reshape(-1, mean.shape[0])
    np.testing.assert_allclose(got.gram, jac @ cov @ jac.T, rtol=1e-10, atol=1e-12)
    for i, o in enumerate(np.asarray(objs)):  # each in-view term sees Σ over [x, its object] only
        idx = np.r_[0:3, 3 + 3 * o: 6 + 3 * o]
        want = _log_visibility_probability(sensor, mean[idx], cov[np.ix_(idx, idx)])
        np.testing.assert_allclose(got.log_vis[i], want, rtol=1e-13)
    assert bool(jnp.all(jnp.isfinite(got.log_vis)))


def test_sampled_children_are_each_childs_monte_carlo_mean_over_its_parents_draws():
    """The beam's sampled weights (Eq. 16 per child, parents' tables reduced chunk by chunk, never
    stacked) equal the plain Monte-Carlo mean of each child's likelihood over its parent's draws
    ``mean + L eps`` (L = chol(Σ)), with and without the visibility term, and its ESS."""
    from hybridslam.estimators.hybrid.weights import log_likelihood_table, sampled_children

    scenario = hs.simulate(1, steps=1)
    sensor = hs.model_from_scenario(scenario, "mirror").sensor
    rng = np.random.default_rng(5)
    n, k, s = scenario.num_objects, 6, 64
    d = 3 + 3 * n
    mean = jnp.asarray(np.concatenate([scenario.robot_prior_mean[None, :], np.zeros((1, 3 * n))], 1)
                       + rng.normal(0, 0.05, (k, d)) + np.r_[[0.0] * 3, np.asarray(scenario.object_prior_means).reshape(-1)])
    a = rng.normal(size=(k, d, d))
    cov = jnp.asarray(0.01 * a @ np.swapaxes(a, 1, 2) / d + 1e-3 * np.eye(d))
    det = hs.Detections(jnp.array([[4.0, 0.3], [6.0, -0.2]]), jnp.array([[0.7, 0.3], [0.2, 0.8]]),
                        jnp.array([True, True]))
    eps = jax.random.normal(jax.random.PRNGKey(0), (s, d))
    alive = jnp.array([True, False, True, True, False, True])  # chunks of 4: one wholly dead slot, one padded
    parent = jnp.array([0, 2, 3, 5, 1, 0])
    measured = jnp.array([[0, 1], [2, -1], [1, 0], [3, 4], [0, 1], [-1, 5]])
    slot_class = jnp.array([[0, 1], [1, 0], [0, 0], [1, 1], [0, 0], [0, 1]])
    got = sampled_children(sensor, mean, cov, det, eps, alive, parent, measured, slot_class)
    live_children = np.asarray(alive)[np.asarray(parent)]
    assert np.all(np.isfinite(np.asarray(got[1])[live_children]))
    assert np.sum(np.isfinite(np.asarray(got[0])[live_children])) >= 2  # some children in view, too

    @jax.jit  # one compile for the parents below, not dispatched op by op
    def tables(mean_p, cov_p):  # a parent's draws mean + L eps and their likelihood tables
        draws = mean_p[None, :] + eps @ jnp.linalg.cholesky(cov_p).T
        return jax.vmap(log_likelihood_table, (None, 0, None))(sensor, draws, det)

    for i in range(parent.shape[0]):
        p = int(parent[i])
        if not bool(alive[p]):  # masked by the caller
            continue
        lik, view = tables(mean[p], cov[p])
        terms_free = sum(lik[:, j, measured[i, j], slot_class[i, j]] for j in range(2) if measured[i, j] >= 0)
        terms = terms_free + sum(view[:, measured[i, j]] for j in range(2) if measured[i, j] >= 0)
        log_mean = lambda t: jax.scipy.special.logsumexp(t) - np.log(s)  # noqa: E731
        np.testing.assert_allclose(got[0][i], log_mean(terms), rtol=1e-12)
        np.testing.assert_allclose(got[1][i], log_mean(terms_free), rtol=1e-12)
        if np.isfinite(float(got[0][i])):
            np.testing.assert_allclose(got[2][i], np.exp(2 * log_mean(terms) - log_mean(2 * terms)), rtol=1e-10)
