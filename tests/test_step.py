"""Algorithm 1 end to end: marginals, lazy class realizations, tracing, determinism, overflow."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam.driver import compiled, inputs_from_scenario, scan

from .conftest import CAPACITY, SAMPLES, SLOTS

# One jitted step for the file: estimators of equal settings and beliefs of equal shapes share it.
STEP = eqx.filter_jit(lambda estimator, belief, *inputs: estimator.step(belief, *inputs))


def _inputs(scenario, k):
    st = hs.stack_steps(scenario, SLOTS)
    det = hs.Detections(jnp.asarray(st.geo[k]), jnp.asarray(st.scores[k]), jnp.asarray(st.mask[k]))
    return jnp.asarray(st.odometry[k]), det


def _estimator(classifier="mirror", prune_ratio=150.0, **settings):
    settings = {"capacity": CAPACITY, "max_detections": SLOTS, **settings}
    if settings.get("weights", "laplace-is") != "linearized":
        settings.setdefault("samples", SAMPLES)
    return hs.make_estimator("hybrid", classifier=classifier, prune_ratio=prune_ratio, **settings)


def _belief(scenario, classifier="mirror", prune_ratio=150.0, **settings):
    """An estimator and its initial belief for ``scenario``."""
    estimator = _estimator(classifier, prune_ratio, **settings)
    return estimator, estimator.init(scenario)


# Geometry only, never pruned, half the shared capacity: several association hypotheses stay alive and
# the belief overflows (test_capacity_overflow_is_counted_not_silent). One program for the file's driver
# runs: the run_none fixture, the seed and compile-once tests and the fallback test's step.
RUN_NONE = dict(classifier="none", capacity=CAPACITY // 2, samples=SAMPLES, max_detections=SLOTS, prune_ratio=1e300,
                smoother="filter")


@pytest.fixture(scope="module")
def run_none(scenario):
    """A full belief of several association hypotheses (some dropped): a good one to check marginals on."""
    return hs.run_estimator(scenario, **RUN_NONE)


def test_weights_and_marginals_sum_to_one(run_none):
    belief = run_none.belief
    assert int(belief.alive.sum()) > 1
    np.testing.assert_allclose(belief.weights[belief.alive].sum(), 1.0, rtol=1e-12)
    np.testing.assert_allclose(hs.class_probabilities(belief).sum(-1), 1.0, rtol=1e-12)
    w, means, covs = hs.pose_mixture(belief)
    np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-12)
    # Eq. 8: one probability per distinct association history, summing to 1.
    p = np.asarray(hs.association_probabilities(belief))
    hist = np.asarray(belief.history)
    distinct = {hist[i].tobytes(): p[i] for i in np.flatnonzero(np.asarray(belief.alive))}
    np.testing.assert_allclose(sum(distinct.values()), 1.0, rtol=1e-12)
    for record in run_none.result.steps:
        np.testing.assert_allclose(sum(c.weight for c in record.components), 1.0, rtol=1e-12)
        assert record.metrics["num_components"] == len(record.components)


def test_lazy_class_realizations_equal_full_enumeration(scenario, key):
    """Sec. IV-D: keeping unassociated objects' classes open gives the same P(C | H) as carrying all
    M^N realizations explicitly. A 2-object map keeps M^N = 4 small."""
    small = scenario.replace(
        object_prior_means=scenario.object_prior_means[:2], object_prior_covs=scenario.object_prior_covs[:2],
        class_prior=np.array([[0.3, 0.7], [0.6, 0.4]]), true_object_poses=None, true_classes=None,
        steps=tuple(_first_detection_of(s, 2) for s in scenario.steps[:3]), true_robot_poses=None,
    )
    estimator, lazy = _belief(small, capacity=16, max_steps=3, prune_ratio=1e300, weights="linearized", exhaustive=True,
                              smoother="filter")
    realizations = jnp.array([[0, 0], [0, 1], [1, 0], [1, 1]], dtype=jnp.int32)
    prior = jnp.prod(jnp.asarray(small.class_prior)[jnp.arange(2), realizations], axis=1)
    full = eqx.tree_at(
        lambda b: (b.classes, b.log_weights),
        lazy,
        # log weights of the lazy belief's dtype, not weakly typed: both beliefs run one compiled step
        (lazy.classes.at[:4].set(realizations),
         jnp.full(16, -jnp.inf, lazy.log_weights.dtype).at[:4].set(jnp.log(prior))),
    )
    for k in range(3):
        odometry, det = _inputs(small, k)
        lazy, _ = STEP(estimator, lazy, odometry, det, jax.random.fold_in(key, k))
        full, _ = STEP(estimator, full, odometry, det, jax.random.fold_in(key, k))
    assert int(lazy.alive.sum()) < int(full.alive.sum())  # the point of being lazy
    np.testing.assert_allclose(hs.class_probabilities(lazy), hs.class_probabilities(full), rtol=1e-9)
    np.testing.assert_allclose(hs.association_entropy(lazy), hs.association_entropy(full), rtol=1e-9)


def _first_detection_of(step, num_objects):
    from hybridslam.io.scenario import Step

    dets = tuple(d for d in step.detections if d.true_object is not None and d.true_object < num_objects)[:1]
    return Step(step.odometry, dets)


def test_a_run_compiles_its_step_once_and_model_parameters_are_traced(scenario, run_none):
    """One compile per run (the driver compiles the scan over one step ahead of time, and
    ``lax.scan`` refuses a step whose state changes type), also when model parameters change between
    runs: a run with another geometric covariance (it lives in the belief's model, as the classifier's
    alpha and K do) reuses the program and computes with its own covariance."""
    wider = scenario.replace(geometric_cov=2.0 * np.asarray(scenario.geometric_cov))
    other = hs.run_estimator(wider, **RUN_NONE)
    assert other.result.timing["compile_s"] == 0.0
    weights = [[c.weight for s in r.result.steps for c in s.components] for r in (other, run_none)]
    assert not np.allclose(*weights)


def test_same_seed_same_result_and_different_seed_differs(scenario):
    a = hs.run_estimator(scenario, seed=3, **RUN_NONE).result
    b = hs.run_estimator(scenario, seed=3, **RUN_NONE).result
    c = hs.run_estimator(scenario, seed=4, **RUN_NONE).result
    weights = lambda r: [c.weight for s in r.steps for c in s.components]  # noqa: E731
    assert weights(a) == weights(b)
    assert weights(a) != weights(c)


def test_capacity_overflow_is_counted_not_silent(run_none):
    # Never pruned, the belief holds 8 components by step 6 (a capacity of 8 is just enough): half of it overflows.
    run = run_none
    assert RUN_NONE["capacity"] == CAPACITY // 2 and RUN_NONE["prune_ratio"] == 1e300
    dropped = [int(i.dropped_capacity) for i in run.infos]
    assert max(dropped) > 0
    assert all(int(i.num_components) <= CAPACITY // 2 for i in run.infos)
    assert any("lack of capacity" in line for i in run.infos for line in i.warnings())


def test_history_overflow_is_refused(scenario):
    """A scenario longer than the history the estimator keeps is refused before any step runs."""
    estimator = _estimator(max_steps=scenario.num_steps)
    with pytest.raises(ValueError, match="max_steps: 6, but the scenario has 7 steps"):
        hs.run(estimator, scenario.replace(steps=scenario.steps + scenario.steps[:1], true_robot_poses=None))


def test_unexplainable_detection_falls_back_to_likelihood(scenario, run_none):
    """The robot surely faces away from every object, yet detects two: no hypothesis has its
    objects in view (a model violation). The step weighs by likelihood instead and stays finite.
    (One step of the program ``hs.run`` compiled for the run fixture: no compile of its own.)"""
    estimator = hs.make_estimator("hybrid", **RUN_NONE)
    belief = estimator.init(scenario)
    inputs = jax.tree.map(lambda a: np.asarray(a)[:1], inputs_from_scenario(scenario, SLOTS))  # as in hs.run
    inputs = eqx.tree_at(lambda i: i.detections.mask, inputs, np.ones((1, SLOTS), bool))
    away = eqx.tree_at(lambda b: (b.mean, b.cov), belief, (belief.mean.at[:, 2].set(np.pi), belief.cov * 1e-4))
    step, _ = compiled(scan, estimator, away, inputs, jax.random.PRNGKey(0), steps=1)
    new, trace = step(estimator, away, inputs, jax.random.PRNGKey(0))
    info = jax.tree.map(lambda a: np.asarray(a)[0], trace.info)
    assert bool(info.visibility_ignored)
    assert bool(jnp.all(jnp.isfinite(new.log_weights[new.alive])))
    np.testing.assert_allclose(new.weights[new.alive].sum(), 1.0)


# Two studies of their own (25 s each): the extended suite, CI; the default study shows the same drop.
@pytest.mark.slow
@pytest.mark.parametrize("weights", ["sampled", "linearized"])
def test_viewpoint_dependent_model_lowers_entropy(weights):
    """The paper's Fig. 5a at alpha = 0.25: with the mirror model the association entropy after 10
    steps is lower than with geometry only, averaged over tracks. Sampled weights use the paper's
    n_s = 1000: with far fewer samples the broad start prior (σ = 10 m) loses hypotheses by chance."""
    mean_entropy = {}
    for clf in ("mirror", "none"):
        finals = []
        for seed in range(4):
            sc = hs.simulate(seed, steps=10)
            samples = 1000 if weights == "sampled" else None
            run = hs.run_estimator(sc, classifier=clf, capacity=16, samples=samples, weights=weights, max_detections=SLOTS,
                                   smoother="filter")
            finals.append(run.result.steps[-1].metrics["entropy"])
        mean_entropy[clf] = np.mean(finals)
    assert mean_entropy["mirror"] < mean_entropy["none"] - 0.1, mean_entropy


def test_clear_compiled_forgets_the_kept_executables(monkeypatch):
    """``driver.compiled`` keeps one executable per program (a second equal call compiles nothing);
    after ``clear_compiled`` the same call compiles again, and JAX's caches were cleared. (On a
    private cache and a stand-in for ``jax.clear_caches``: the rest of the suite keeps its programs.)"""
    from hybridslam import compilation, driver

    monkeypatch.setattr(compilation, "_COMPILED", {})
    cleared = []
    monkeypatch.setattr(jax, "clear_caches", lambda: cleared.append(True))

    def double(x):
        return 2.0 * x

    x = jnp.arange(3.0)
    _, first = driver.compiled(double, x)
    assert first > 0.0 and driver.compiled(double, x)[1] == 0.0
    driver.clear_compiled()
    again, seconds = driver.compiled(double, x)
    assert cleared == [True] and seconds > 0.0 and np.allclose(again(x), 2.0 * x)


def _children(belief):
    """``{(association history, classes): weight}`` of a belief's live components."""
    alive = np.flatnonzero(np.asarray(belief.alive))
    hist, classes, w = np.asarray(belief.history), np.asarray(belief.classes), np.asarray(belief.weights)
    return {(hist[i].tobytes(), classes[i].tobytes()): float(w[i]) for i in alive}


def test_beam_children_and_weights_equal_the_exhaustive_enumeration(key):
    """Issue 14's exactness check: on steps of up to 3 detections and a 6-object map, a beam wide
    enough for every partial child (its joint density carried in sequential form) keeps the same
    children with the same weights (to 1e-9) as the exhaustive enumeration (each child's joint
    density at once), from the same multi-component parents, with nothing dropped."""
    scenario = hs.simulate(2, steps=4, setup=hs.PaperSetup(max_detections=3, max_range=12.0))
    counts = [len(s.detections) for s in scenario.steps]
    assert max(counts) == 3, counts
    settings = dict(weights="linearized", smoother="filter", capacity=4, max_detections=3)
    exhaustive = _estimator(prune_ratio=1e300, exhaustive=True, **settings)
    beam = _estimator(prune_ratio=1e300, max_children=4096, **settings)  # > 4 parents × 6·5·4·2³
    belief = exhaustive.init(scenario)
    slots = hs.stack_steps(scenario, 3)
    for k in range(scenario.num_steps):
        inputs = (jnp.asarray(slots.odometry[k]),
                  hs.Detections(jnp.asarray(slots.geo[k]), jnp.asarray(slots.scores[k]), jnp.asarray(slots.mask[k])))
        step_key = jax.random.fold_in(key, k)
        want, _ = STEP(exhaustive, belief, *inputs, step_key)
        got, info = STEP(beam, belief, *inputs, step_key)
        assert int(info.dropped_budget) == 0
        a, b = _children(want), _children(got)
        assert a.keys() == b.keys() and len(a) > 1
        for child, weight in a.items():
            np.testing.assert_allclose(b[child], weight, rtol=1e-9, atol=1e-12)
        belief = want


def _duplicated_detection():
    """The paper setup's first step with a spurious copy of its first detection (0.3 m farther) in
    slot 1, and the step's inputs over three slots."""
    scenario = hs.simulate(2, steps=2, setup=hs.PaperSetup(max_detections=2, max_range=12.0))
    first = scenario.steps[0]
    assert len(first.detections) == 2
    near = dataclasses.replace(first.detections[0], range=first.detections[0].range + 0.3, true_object=None)
    steps = (dataclasses.replace(first, detections=(first.detections[0], near, first.detections[1])),)
    scenario = scenario.replace(steps=steps + scenario.steps[1:])
    slots = hs.stack_steps(scenario, 3)
    inputs = (jnp.asarray(slots.odometry[0]),
              hs.Detections(jnp.asarray(slots.geo[0]), jnp.asarray(slots.scores[0]), jnp.asarray(slots.mask[0])))
    return scenario, first, inputs


def test_a_known_map_step_that_no_child_names_whole_skips_the_fewest_detections(key):
    """Two detections whose gate (one candidate each) holds the same object: no injective child
    names all three detections. The beam keeps the children that leave exactly one unassociated
    (-1, counted in ``skipped``), and the belief, instead of losing the whole step."""
    scenario, first, inputs = _duplicated_detection()
    estimator = _estimator(gate=1, weights="linearized", smoother="filter", max_detections=3)
    belief, info = STEP(estimator, estimator.init(scenario), *inputs, key)
    assert int(info.skipped) == 1
    alive = np.isfinite(np.asarray(belief.log_weights))
    assert alive.any() and np.isclose(np.exp(np.asarray(belief.log_weights)[alive]).sum(), 1.0)
    for assoc in np.asarray(belief.history)[alive, 0]:
        assert (assoc[:2] < 0).sum() == 1 and assoc[2] >= 0  # one of the two rivals, the third always
    best = np.asarray(belief.history)[np.argmax(np.asarray(belief.log_weights)), 0]
    assert best[0] == first.detections[0].true_object and best[1] == -1  # the true detection wins


def test_the_clutter_hypothesis_explains_a_spurious_detection(key):
    """The same duplicated detection with a clutter hypothesis (a log density over [range, bearing]:
    the scenario's ``clutter_log_density``, which the default ``clutter`` setting reads, so both
    densities run one compiled step): the likeliest child names the true detection's object and
    calls the copy clutter (-1, counted in ``rejected``, not ``skipped``); every child that calls a
    detection clutter carries the density once per such detection."""
    scenario, first, inputs = _duplicated_detection()
    estimator = _estimator(gate=1, weights="linearized", smoother="filter", max_detections=3)
    beliefs = {}
    for density in (-10.0, -9.0):
        belief, info = STEP(estimator, estimator.init(scenario.replace(clutter_log_density=density)), *inputs, key)
        assert int(info.rejected) == 1 and int(info.skipped) == 0
        alive = np.isfinite(np.asarray(belief.log_weights))
        assert np.isclose(np.exp(np.asarray(belief.log_weights)[alive]).sum(), 1.0)
        best = np.asarray(belief.history)[np.argmax(np.asarray(belief.log_weights)), 0]
        assert best[0] == first.detections[0].true_object and best[1] == -1 and best[2] >= 0
        beliefs[density] = {tuple(h): w for h, w in zip(np.asarray(belief.history)[alive, 0].tolist(),
                                                         np.asarray(belief.log_weights)[alive])}
    # One more nat of clutter density: a child's unnormalized log weight rises by one per clutter slot,
    # so between two children the log ratio moves by the difference of their clutter counts.
    common = sorted(beliefs[-10.0].keys() & beliefs[-9.0].keys())
    assert len(common) > 1
    ref = common[0]
    for child in common[1:]:
        moved = (beliefs[-9.0][child] - beliefs[-9.0][ref]) - (beliefs[-10.0][child] - beliefs[-10.0][ref])
        np.testing.assert_allclose(moved, child.count(-1) - ref.count(-1), atol=1e-9)


def test_a_pose_belief_that_contradicts_every_association_is_flagged(key):
    """The step of the skip test from a belief 2 m off to the side with a tight covariance (a
    kidnap): its best child names objects far outside their predictions, and the step says so
    (``inconsistent``); from the true belief it does not."""
    scenario, _, inputs = _duplicated_detection()
    estimator = _estimator(gate=1, weights="linearized", smoother="filter", max_detections=3)
    belief = estimator.init(scenario)
    _, info = STEP(estimator, belief, *inputs, key)
    assert not bool(info.inconsistent)
    away = eqx.tree_at(lambda b: (b.mean, b.cov), belief, (belief.mean.at[:, 1].add(2.0), belief.cov * 1e-4))
    _, info = STEP(estimator, away, *inputs, key)
    assert bool(info.inconsistent)
    assert any("contradicts the detections" in w for w in info.warnings())
