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


@jax.jit  # one compiled program (op by op: about a hundred tiny compiles)
@jax.numpy_rank_promotion("allow")  # jax.scipy's logpdf broadcasts internally
def _linear_gaussian_evidence(hs_):
    """The toy of the test below: Eq. 16's estimate, its relative Monte-Carlo error and the exact
    evidence of every pair ``(i_1, i_2)``, each ``(3, 3)``."""
    mu, p = jnp.array([0.5, -0.2]), jnp.array([[0.3, 0.1], [0.1, 0.2]])
    r = 0.5 * jnp.eye(2)
    z = jnp.array([[0.4, 0.1], [-0.3, 0.6]])  # two detections
    x = jax.random.multivariate_normal(jax.random.PRNGKey(1), mu, p, (20000,))
    tables = jnp.stack(
        [jnp.stack([mvn.logpdf(z[j][None, :] - x @ hs_[i].T, jnp.zeros(2), r) for i in range(3)], -1) for j in range(2)], 1
    )  # (S, 2, 3)
    estimate = log_mean_exp_outer(tables)
    per_sample = tables[:, 0, :, None] + tables[:, 1, None, :]
    rel_err = jnp.std(jnp.exp(per_sample), 0) / jnp.mean(jnp.exp(per_sample), 0) / np.sqrt(x.shape[0])
    exact = [[mvn.logpdf(z.reshape(-1), h @ mu, h @ p @ h.T + jnp.kron(jnp.eye(2), r))
              for h in (jnp.concatenate([hs_[i1], hs_[i2]]) for i2 in range(3))] for i1 in range(3)]
    return estimate, rel_err, jnp.asarray(exact)


def test_log_mean_exp_outer_matches_linear_gaussian_evidence():
    """Linear-Gaussian toy: z_j = H_i x + v, x ~ N(mu, P). The Monte-Carlo mean of Eq. 16 over
    samples of x must equal the analytic marginal likelihood N(z; H mu, H P Hᵀ + R) of every pair
    (i_1, i_2), within its own Monte-Carlo error."""
    rng = np.random.default_rng(0)
    hs_ = jnp.asarray(rng.normal(size=(3, 2, 2)))  # three candidate "objects"
    estimate, rel_err, exact = (np.asarray(a) for a in _linear_gaussian_evidence(hs_))
    for i1 in range(3):
        for i2 in range(3):
            assert abs(float(estimate[i1, i2] - exact[i1, i2])) < 4 * float(rel_err[i1, i2]) + 1e-3


def test_log_mean_exp_outer_is_exact_in_the_log_domain():
    """Any absolute scale (here around -5000 nats) and entries hundreds of nats apart: entries within
    600 nats of the best are exact; ones further below may only underflow to -inf (pruned anyway)."""
    t = np.array([[[-900.0, -1.0], [-2.0, -1200.0]], [[-905.0, -3.0], [-1.0, -300.0]]]) - 2500.0
    brute = np.logaddexp.reduce(t[:, 0, :, None] + t[:, 1, None, :], axis=0) - np.log(2)
    got = np.asarray(jax.jit(log_mean_exp_outer)(jnp.asarray(t)))
    near = brute > brute.max() - 600
    np.testing.assert_allclose(got[near], brute[near], rtol=1e-12)
    assert bool(np.all((got[~near] == -np.inf) | np.isclose(got[~near], brute[~near], rtol=1e-12)))
    assert int(near.sum()) >= 2 and int((~near).sum()) >= 1


def _near_linear_setup():
    """One precisely known robot looking at two objects 5 m away: range-bearing is nearly linear."""
    scenario = hs.simulate(0, steps=1)
    model = hs.model_from_scenario(scenario, "mirror")
    mean = jnp.array([0.0, 0.0, 0.0, 5.0, 1.0, 0.4, 5.0, -1.5, 2.0])
    cov = jnp.diag(jnp.array([1e-3, 1e-3, 1e-4, 0.02, 0.02, 1e-3, 0.02, 0.02, 1e-3]))
    det = hs.Detections(jnp.array([[5.15, 0.2], [0.0, 0.0]]), jnp.array([[0.9, 0.2], [0.0, 0.0]]), jnp.array([True, False]))
    table = hypothesis_table(2, 2, 2)
    kids = jax.jit(children)(table, jnp.array([-1, -1]), det.mask, jnp.full((2, 2), 0.5))
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
    def both(det):
        kids = children(table, jnp.array([-1, -1]), det.mask, jnp.full((2, 2), 0.5))
        sampled = sampled_log_likelihood(model.sensor, mean, cov, det, eps, table, kids)[0]
        return kids.valid, sampled, linearized_log_likelihood(model.sensor, mean, cov, det, table, kids)[0]

    for mask, plausible in (([True, False], 2), ([False, True], 1), ([True, True], 1)):
        det = hs.Detections(geo, scores, jnp.array(mask))
        valid, sampled, linear = (np.asarray(a) for a in both(det))
        ok = valid & (linear > -20)  # the plausible children
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
    eps = jax.random.normal(jax.random.PRNGKey(3), (256, mean.shape[0]))

    @jax.jit
    def weights():
        kids = children(table, parent_classes, det.mask, class_prior)
        got, _, _ = sampled_log_likelihood(sensor, mean, cov, det, eps, table, kids)
        return kids.valid, kids.slot_class, got + kids.log_prior

    valid, slot_class, got = (np.asarray(a) for a in weights())
    samples = mean[None, :] + eps @ jnp.linalg.cholesky(cov).T

    def per_sample(s, objs, cls):
        x, o = s[:3], s[3:].reshape(-1, 3)
        total = 0.0
        for j in range(2):
            r, log_norm = detection_residual(sensor, x, o[objs[j]], det.geo[j], det.scores[j], cls[j])
            seen = visible(range_bearing(x, o[objs[j]]), sensor.max_range, sensor.fov)
            total = total + jnp.where(seen, log_norm - 0.5 * jnp.sum(r**2), -jnp.inf)
        return total

    @jax.jit  # one compile for every child below
    def log_mean(objs, cls):
        return logsumexp(jax.vmap(per_sample, (0, None, None))(samples, objs, cls)) - np.log(samples.shape[0])

    log_class_prior = np.log(np.asarray(class_prior))
    expected = {}
    for objs in itertools.permutations(range(3), 2):
        open_ = [n for n in objs if int(parent_classes[n]) < 0]
        for new_classes in itertools.product(range(2), repeat=len(open_)):
            realized = dict(zip(open_, new_classes))
            cls = [realized.get(n, int(parent_classes[n])) for n in objs]
            prior = sum(float(log_class_prior[n, c]) for n, c in realized.items())
            expected[(objs, tuple(cls))] = float(log_mean(jnp.array(objs), jnp.array(cls))) + prior

    found = {}
    assign = np.asarray(table.assign)
    for a, m in zip(*np.nonzero(valid)):
        key_ = (tuple(int(o) for o in assign[a]), tuple(int(c) for c in slot_class[a, m]))
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
    m = sensor.classifier.num_classes

    def row(state, o, c, j):  # detection j's whitened residual and log normalizer, object o, class c
        return detection_residual(sensor, state[:3], state[3:].reshape(-1, 3)[o], det.geo[j], det.scores[j], c)

    @jax.jit  # one compiled program for the tables and every reference below, not dispatched op by op
    def tables_and_references():
        got = linear_tables(sensor, mean, cov, det, objs)
        # Every (detection, object, class) row on its own, class by class: (2, O, M, ...).
        rows = jax.vmap(lambda j: jax.vmap(lambda o: jax.vmap(lambda c: row(mean, o, c, j))(jnp.arange(m)))(objs))(
            jnp.arange(2))
        jac = jax.vmap(jax.vmap(jax.jacfwd(lambda s, o, c: row(s, o, c, 0)[0]), (None, None, 0)), (None, 0, None))(
            mean, objs, jnp.arange(m))
        jac = jac.reshape(-1, mean.shape[0])
        idx = jnp.concatenate([jnp.broadcast_to(jnp.arange(3), (objs.shape[0], 3)),
                               3 + 3 * objs[:, None] + jnp.arange(3)[None, :]], axis=1)  # [x, its object] per term
        vis = jax.vmap(lambda i: _log_visibility_probability(sensor, mean[i], cov[i[:, None], i[None, :]]))(idx)
        return got, rows, jac @ cov @ jac.T, vis

    got, (r, log_norm), gram, vis = jax.tree.map(np.asarray, tables_and_references())
    # every class's rows come from one residual evaluation: the same as class by class
    np.testing.assert_allclose(got.r_bar, r, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(got.log_norm, log_norm, rtol=1e-15)
    np.testing.assert_allclose(got.gram, gram, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got.log_vis, vis, rtol=1e-13)  # each in-view term sees Σ over [x, its object] only
    assert bool(np.all(np.isfinite(got.log_vis)))


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
    got = [np.asarray(a) for a in
           jax.jit(sampled_children)(sensor, mean, cov, det, eps, alive, parent, measured, slot_class)]
    live_children = np.asarray(alive)[np.asarray(parent)]
    assert np.all(np.isfinite(np.asarray(got[1])[live_children]))
    assert np.sum(np.isfinite(np.asarray(got[0])[live_children])) >= 2  # some children in view, too

    @jax.jit  # one compile for the parents below, not dispatched op by op
    def tables(mean_p, cov_p):  # a parent's draws mean + L eps and their likelihood tables
        draws = mean_p[None, :] + eps @ jnp.linalg.cholesky(cov_p).T
        return jax.vmap(log_likelihood_table, (None, 0, None))(sensor, draws, det)

    alive, parent, measured, slot_class = (np.asarray(a) for a in (alive, parent, measured, slot_class))
    for i in range(parent.shape[0]):
        p = int(parent[i])
        if not bool(alive[p]):  # masked by the caller
            continue
        lik, view = (np.asarray(a) for a in tables(mean[p], cov[p]))
        terms_free = sum(lik[:, j, measured[i, j], slot_class[i, j]] for j in range(2) if measured[i, j] >= 0)
        terms = terms_free + sum(view[:, measured[i, j]] for j in range(2) if measured[i, j] >= 0)
        log_mean = lambda t: np.logaddexp.reduce(t) - np.log(s)  # noqa: E731
        np.testing.assert_allclose(got[0][i], log_mean(terms), rtol=1e-12)
        np.testing.assert_allclose(got[1][i], log_mean(terms_free), rtol=1e-12)
        if np.isfinite(float(got[0][i])):
            np.testing.assert_allclose(got[2][i], np.exp(2 * log_mean(terms) - log_mean(2 * terms)), rtol=1e-10)
