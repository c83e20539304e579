"""Unknown maps in the hybrid belief: new-object hypotheses, object creation, gating.

One tiny scenario (three objects passed in a row, at most two detections per step, an object
capacity of 5) and one compiled step per structure: the runs are module-scoped fixtures.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam.estimators.base import summarize
from hybridslam.estimators.hybrid.hypotheses import NEW, children, hypothesis_table
from hybridslam.estimators.hybrid.weights import linearized_log_likelihood, sampled_log_likelihood
from hybridslam.inference.discovery import back_project, create_object, create_objects
from hybridslam.inference.gating import gate
from hybridslam.io.scenario import Classifier, Discovery, Step
from hybridslam.models.registry import make_classifier
from hybridslam.sim.paper import PaperSetup, _between, _compose, observe

TRUTH = np.array([[3.0, 1.5, 0.3], [5.5, -1.5, 2.0], [8.0, 1.5, -1.0]])
CAPACITY = 5  # object slots
RUN = {"capacity": 8, "max_detections": 2, "weights": "linearized", "smoother": "filter"}
# One jitted step for the file: estimators of equal settings and beliefs of equal shapes share it.
STEP = eqx.filter_jit(lambda estimator, belief, *inputs: estimator.step(belief, *inputs))
# create_object jitted (op by op, each test's calls compiled some 60-90 small programs).
CREATE_OBJECT = jax.jit(create_object)


def _world(steps: int = 8) -> hs.Scenario:
    """A clean pass along a row of three objects: small noise, a tight robot prior, no prior objects."""
    setup = PaperSetup(geometric_cov=(0.01, 0.003), max_range=4.0, motion_cov=(1e-4, 1e-4, 1e-5))
    rng = np.random.default_rng(0)
    classifier = make_classifier("mirror", 2, 0.25, 15.0)
    poses = [np.zeros(3)]
    for _ in range(steps):
        poses.append(_compose(poses[-1], np.array([1.0, 0.0, 0.0])))
    scenario_steps = tuple(
        Step(_between(poses[k - 1], poses[k]), observe(rng, poses[k], TRUTH, classifier, setup))
        for k in range(1, steps + 1)
    )
    return hs.Scenario(
        num_classes=2, object_prior_means=np.zeros((0, 3)), object_prior_covs=np.zeros((0, 3, 3)),
        class_prior=np.zeros((0, 2)), robot_prior_mean=poses[0], robot_prior_cov=np.diag([1e-4, 1e-4, 1e-5]),
        motion_cov=np.diag(setup.motion_cov), geometric_cov=np.diag(setup.geometric_cov),
        classifier=Classifier("mirror", alpha=0.25, K=15.0), max_range=setup.max_range, fov=setup.fov,
        steps=scenario_steps, true_robot_poses=np.stack(poses),
        discovery=Discovery(CAPACITY, -2.0, 9.87), true_objects=tuple((o, 0) for o in TRUTH),
    )


@pytest.fixture(scope="module")
def world() -> hs.Scenario:
    return _world()


@pytest.fixture(scope="module")
def exact(world):
    return hs.run_estimator(world, **RUN)


@pytest.fixture(scope="module")
def known_map(world):
    """The same sequence with all three objects mapped (priors at the truth)."""
    return world.replace(
        object_prior_means=TRUTH, object_prior_covs=np.broadcast_to(np.diag([0.05, 0.05, 0.5e-3]), (3, 3, 3)).copy(),
        class_prior=np.full((3, 2), 0.5), discovery=None, true_objects=None,
    )


def _true_objects(scenario):
    return [[d.true_object for d in s.detections] for s in scenario.steps]


def test_unknown_map_creates_each_true_object_once(world, exact):
    """A clean sequence past three objects from an empty map: the top component creates each true
    object exactly once (in the order first seen) and associates every later detection with it."""
    top = exact.result.steps[-1].components[0]
    assert top.weight > 0.9
    assert top.associations == _true_objects(world)  # first seen 0, 1, 2: created in that order
    belief = exact.belief
    assert int(belief.num_created[jnp.argmax(belief.log_weights)]) == 3
    assert top.classes[:3] == [0, 0, 0] and top.classes[3:] == [-1, -1]  # true class 0; uncreated: -1
    # The created objects sit where the truth is (the robot prior anchors the frame).
    best = int(jnp.argmax(belief.log_weights))
    positions = np.asarray(belief.mean[best, 3:12]).reshape(3, 3)[:, :2]
    np.testing.assert_allclose(positions, TRUTH[:, :2], atol=0.3)
    for record in exact.result.steps:  # records index objects in creation order
        for c in record.components:
            seen = {o for step in c.associations for o in step}
            assert seen <= set(range(CAPACITY))


def _hypotheses(belief, detections, gate_size):
    """Every valid child of every live component: {(component, β_k, classes): (log prior, linearized log ψ)}."""
    sensor, n = belief.model.sensor, belief.num_objects
    table = hypothesis_table(gate_size or n, 2, 2, new_objects=True, gated=gate_size is not None)
    cands = None
    if gate_size is not None:
        cands = jax.vmap(gate, (None, 0, 0, None, 0, None))(sensor, belief.mean, belief.cov, detections,
                                                          belief.num_created, gate_size)
    kids = jax.vmap(children, (None, 0, None, None, None, 0, 0))(
        table, belief.classes, detections.mask, belief.model.class_prior, True, belief.num_created, cands)
    log_psi = jax.vmap(linearized_log_likelihood, (None, 0, 0, None, None, 0))(
        sensor, belief.mean, belief.cov, detections, table, kids)[0]
    return kids, log_psi


def _as_dict(kids, log_psi, alive):
    kids, log_psi = jax.device_get((kids, log_psi))
    return {
        (i, tuple(kids.assign[i, a]), tuple(kids.slot_class[i, a, m])): (kids.log_prior[i, a, m], log_psi[i, a, m])
        for i, a, m in zip(*np.nonzero(kids.valid & alive[:, None, None]))
    }


def test_full_object_slots_are_reported_not_silent(world):
    """Two object slots for three landmarks: once the likely components have used both, the third
    landmark is an unmapped object (weighed as new, not stored), never an old object, and every step
    with detections says so (StepInfo.object_overflow, StepInfo.unmapped); before that, nothing is
    flagged. The belief stays a finite distribution."""
    run = hs.run_estimator(world.replace(discovery=Discovery(2, -2.0, 9.87)), **RUN)
    third = [(k, j) for k, s in enumerate(world.steps) for j, d in enumerate(s.detections) if d.true_object == 2]
    assert third and all(run.result.steps[k].components[0].associations[-1][j] == -1 for k, j in third)
    assert [int(i.unmapped) for i in run.infos] == [sum(1 for kk, _ in third if kk == k) for k in range(len(run.infos))]
    flags = [bool(i.object_overflow) for i in run.infos]
    created = [len({o for a in st.components[0].associations for o in a if o >= 0}) for st in run.result.steps]
    assert not flags[0] and created[0] < 2
    has_detections = [len(s.detections) > 0 for s in world.steps]
    # From the step after the top component reached 2 objects, while it keeps the lead.
    first = created.index(2) + 1
    assert flags[first:] == has_detections[first:] and any(flags)
    assert all(any("object capacity full" in w for w in i.warnings()) for i, f in zip(run.infos, flags) if f)
    stacked = jax.tree.map(lambda *a: np.stack(a), *run.infos)  # a whole run's summary counts the steps
    lines = " ".join(summarize(stacked))
    assert f"no free object slot, at {sum(flags)} step(s))" in lines
    assert f"{len(third)} detection(s) of new objects with no free object slot were weighed" in lines
    weights = np.exp(np.asarray(run.belief.log_weights))
    assert np.isfinite(np.asarray(run.belief.mean)).all() and weights.sum() == pytest.approx(1.0)


def _one_more_slot(belief):
    """``belief`` with one more (uncreated) object slot: placeholder mean 0, covariance I, class open,
    uniform class prior (as :func:`~hybridslam.estimators.hybrid.belief.priors_from_scenario`)."""
    k, d = belief.mean.shape
    cov = jnp.zeros((k, d + 3, d + 3)).at[:, :d, :d].set(belief.cov).at[:, d:, d:].set(jnp.eye(3))
    m = belief.model.class_prior.shape[1]
    prior = jnp.concatenate([belief.model.class_prior, jnp.full((1, m), 1.0 / m)])
    return eqx.tree_at(lambda b: (b.mean, b.cov, b.classes, b.model.class_prior), belief,
                       (jnp.concatenate([belief.mean, jnp.zeros((k, 3))], axis=1), cov,
                        jnp.concatenate([belief.classes, jnp.full((k, 1), -1, belief.classes.dtype)], axis=1), prior))


def _children_by_key(belief, drop_slot=None):
    """``{(β_k, classes): summed weight}`` of a belief's live components; ``drop_slot``: that object
    slot read as unassociated and its class dropped (the children that store it, summed)."""
    hist, classes = np.asarray(belief.history[:, int(belief.k) - 1]), np.asarray(belief.classes)
    out: dict = {}
    for i in np.flatnonzero(np.asarray(belief.alive)):
        h, c = hist[i], classes[i]
        if drop_slot is not None:
            h, c = np.where(h == drop_slot, -1, h), np.delete(c, drop_slot)
        out[(tuple(h), tuple(c))] = out.get((tuple(h), tuple(c)), 0.0) + float(np.asarray(belief.weights)[i])
    return out


def test_an_unmapped_object_weighs_what_its_stored_classes_weigh(world):
    """A component with no free object slot (two slots, two objects) weighs a detection's new-object
    hypothesis as an unmapped object: the same children and weights (to 1e-9) as the same component
    with one more slot, where that hypothesis stores the object once per class and those children
    are summed (the class marginal of Sec. IV-D). The exhaustive table and the beam agree: both
    give the full component those children and weights (one program each, and the exhaustive
    table's for the roomier component)."""
    scenario = world.replace(discovery=Discovery(2, -2.0, 9.87))
    settings = {"classifier": "mirror", "capacity": 16, "max_detections": 2, "weights": "linearized",
                "smoother": "filter", "prune_ratio": 1e300}
    exhaustive = hs.make_estimator("hybrid", exhaustive=True, **settings)
    beam = hs.make_estimator("hybrid", max_children=512, **settings)
    belief = exhaustive.init(scenario)
    slots = hs.stack_steps(scenario, 2)
    inputs = [(jnp.asarray(slots.odometry[k]), hs.Detections(jnp.asarray(slots.geo[k]), jnp.asarray(slots.scores[k]),
                                                            jnp.asarray(slots.mask[k]))) for k in range(3)]
    key = jax.random.PRNGKey(0)
    for k in range(2):  # objects 0 and 1 are created by steps 1-2 (see test_full_object_slots_...)
        belief, _ = STEP(exhaustive, belief, *inputs[k], key)
    top = int(jnp.argmax(belief.log_weights))  # one parent with both slots used
    belief = eqx.tree_at(lambda b: b.log_weights, belief, jnp.full_like(belief.log_weights, -jnp.inf).at[top].set(0.0))
    assert int(belief.num_created[top]) == 2 and int(inputs[2][1].mask.sum()) == 1
    two = np.array(inputs[2][1].mask)
    two[1] = True  # a second detection, a copy of the first, so that two new objects compete for one slot
    det = hs.Detections(inputs[2][1].geo.at[1].set(inputs[2][1].geo[0]), inputs[2][1].scores.at[1].set(
        inputs[2][1].scores[0]), jnp.asarray(two))
    for detections in (inputs[2][1], det):
        roomy, _ = STEP(exhaustive, _one_more_slot(belief), inputs[2][0], detections, key)
        want = _children_by_key(roomy, drop_slot=2)
        for estimator in (exhaustive, beam):
            full, info = STEP(estimator, belief, inputs[2][0], detections, key)
            got = _children_by_key(full)
            assert got.keys() == want.keys() and any(-1 in h for h, _ in got)
            for child, weight in want.items():
                np.testing.assert_allclose(got[child], weight, rtol=1e-9, atol=1e-12)
            assert int(info.dropped_capacity) == 0 and int(info.dropped_budget) == 0


def test_gating_with_all_objects_equals_exact_enumeration(world, exact):
    """G ≥ N candidates per detection keep every hypothesis of the exact enumeration, with the same
    weights; G = 1 keeps a subset that holds the best child (each detection: its nearest object or new)."""
    belief = exact.belief
    st = hs.stack_steps(world, 2)
    detections = hs.Detections(jnp.asarray(st.geo[1]), jnp.asarray(st.scores[1]), jnp.asarray(st.mask[1]))
    alive = np.asarray(belief.alive)
    assert alive.sum() > 1 and len(set(np.asarray(belief.num_created)[alive])) > 1  # a varied belief
    run = jax.jit(lambda b: [_hypotheses(b, detections, g) for g in (None, CAPACITY, 1)])
    exact_kids, all_gated, nearest = (_as_dict(*out, alive) for out in run(belief))
    assert exact_kids.keys() == all_gated.keys()
    keys = list(exact_kids)
    np.testing.assert_allclose([exact_kids[k] for k in keys], [all_gated[k] for k in keys], rtol=1e-10)
    assert set(nearest) < set(exact_kids)
    best = max(exact_kids, key=lambda k: sum(exact_kids[k]) + float(belief.log_weights[k[0]]))
    assert best in nearest


def test_known_map_is_unchanged_by_discovery(known_map):
    """Mapped objects and an implausible new object (log density −1000): discovery changes nothing."""
    plain = hs.run_estimator(known_map, **RUN)
    open_map = hs.run_estimator(known_map.replace(discovery=Discovery(CAPACITY, -1000.0, 9.87)), **RUN)
    for a, b in zip(plain.result.steps, open_map.result.steps):
        assert len(a.components) == len(b.components)
        for ca, cb in zip(a.components, b.components):
            assert ca.associations == cb.associations
            assert ca.classes == cb.classes[:3] and cb.classes[3:] == [-1, -1]
            np.testing.assert_allclose(ca.weight, cb.weight, rtol=1e-9)
            np.testing.assert_allclose(ca.pose_mean, cb.pose_mean, rtol=1e-9, atol=1e-12)
    alive = np.asarray(plain.belief.alive)
    np.testing.assert_allclose(open_map.belief.mean[alive, :12], plain.belief.mean[alive], rtol=1e-9, atol=1e-12)
    assert np.all(np.asarray(open_map.belief.num_created)[alive] == 3)


def test_new_slot_is_no_factor_of_the_weight():
    """Sampled weights (Eq. 16): a child whose second detection creates a new object has the
    likelihood of the child with that detection left out; the shifted extra column cancels exactly.
    (The linearized and laplace-is weights simply treat a creating slot as an empty one.)"""
    sensor = hs.SensorModel(jnp.diag(jnp.array([0.1, 0.05])), make_classifier("mirror", 2, 0.25, 15.0),
                            jnp.asarray(10.0), jnp.asarray(2.0))
    mean = jnp.array([0.0, 0.0, 0.1, 3.0, 1.0, 0.2, 4.0, -1.0, 0.0, 0.0, 0.0, 0.0])  # objects 0, 1; slot 2 uncreated
    cov = jnp.diag(jnp.array([0.05, 0.05, 0.01, 0.05, 0.05, 0.01, 0.05, 0.05, 0.01, 1.0, 1.0, 1.0]))
    geo = jnp.array([[3.1, 0.22], [4.0, -0.3]])
    scores = jnp.array([[0.8, 0.2], [0.3, 0.7]])
    table = hypothesis_table(3, 2, 2, new_objects=True)
    eps = jax.random.normal(jax.random.PRNGKey(0), (400, 12))

    @jax.jit
    def weigh(mask):
        det = hs.Detections(geo, scores, mask)
        kids = children(table, jnp.array([0, -1, -1]), mask, jnp.full((3, 2), 0.5), num_created=jnp.asarray(2))
        return sampled_log_likelihood(sensor, mean, cov, det, eps, table, kids)[0], kids

    with_new, kids = weigh(jnp.array([True, True]))
    without, _ = weigh(jnp.array([True, False]))
    row_new = int(np.flatnonzero((table.assign == [[0, NEW]]).all(axis=1))[0])
    row_one = int(np.flatnonzero((table.assign == [[0, -1]]).all(axis=1))[0])
    assert bool(kids.valid[row_new, 0]) and int(kids.assign[row_new, 1]) == 2  # the next free slot
    assert bool(kids.creates[row_new, 1]) and int(kids.measured[row_new, 1]) == -1
    assert np.isfinite(without[row_one, 0])
    np.testing.assert_allclose(with_new[row_new, 0], without[row_one, 0], rtol=1e-10)


def test_create_object_covariance_matches_monte_carlo():
    """create_object's linearized covariance against samples of the back-projection (small noise)."""
    rng = np.random.default_rng(1)
    dim = 3 + 3 * 3
    a = rng.normal(size=(dim, dim)) * 0.02
    cov = a @ a.T + np.diag(np.r_[0.01, 0.01, 0.002, 0.02, 0.02, 0.01, np.ones(3), np.ones(3)])
    cov[6:9, :] = cov[:, 6:9] = 0.0  # slot 1: to be created; slot 2 stays an uncreated placeholder
    cov[9:, :] = cov[:, 9:] = 0.0
    cov[6:, 6:] = np.eye(6)
    mean = np.r_[1.0, 2.0, 0.4, 3.0, 1.0, 0.2, np.zeros(6)]
    geo, geometric_cov, var = np.array([2.0, 0.3]), np.diag([0.01, 0.004]), 9.87
    new_mean, new_cov = CREATE_OBJECT(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(1), jnp.asarray(geo),
                                      jnp.asarray(geometric_cov), jnp.asarray(var))
    n = 50_000
    y = rng.multivariate_normal(mean, cov, n)
    z = geo + rng.multivariate_normal(np.zeros(2), geometric_cov, n)
    p = np.asarray(jax.vmap(back_project)(jnp.asarray(y[:, :3]), jnp.asarray(z)))
    y[:, 6:8], y[:, 8] = p, rng.normal(0.0, np.sqrt(var), n)
    np.testing.assert_allclose(new_mean[6:8], y[:, 6:8].mean(0), atol=0.03)  # linearization bias ~ r·var(θ)/2
    sample_cov = np.cov(y.T)
    scale = np.sqrt(np.outer(np.diag(sample_cov), np.diag(sample_cov)))
    np.testing.assert_allclose(np.asarray(new_cov) / scale, sample_cov / scale, atol=0.03)
    np.testing.assert_array_equal(np.asarray(new_cov)[9:, 9:], np.eye(3))  # the placeholder is untouched


def test_create_object_equals_the_dense_affine_map_and_discards_the_slot():
    """The block-wise update equals ``A Σ Aᵀ + B Σ_v Bᵀ + var·e eᵀ`` with the dense affine map that
    drops the slot and writes ``p = back_project(x, z)`` into it, for a slot that held correlated
    values before (they are discarded) and a fully correlated state."""
    rng = np.random.default_rng(3)
    dim, slot = 3 + 3 * 4, 2
    root = rng.normal(size=(dim, dim))
    cov = root @ root.T / dim + 0.05 * np.eye(dim)
    mean = rng.normal(size=dim)
    geo, geometric_cov, var = np.array([2.5, -0.7]), np.array([[0.02, 0.003], [0.003, 0.01]]), 4.0
    new_mean, new_cov = CREATE_OBJECT(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(slot), jnp.asarray(geo),
                                      jnp.asarray(geometric_cov), jnp.asarray(var))
    j_x, j_z = (np.asarray(a) for a in jax.jit(jax.jacfwd(back_project, (0, 1)))(jnp.asarray(mean[:3]), jnp.asarray(geo)))
    rows = 3 + 3 * slot + np.arange(3)
    a = np.eye(dim)
    a[rows] = 0.0
    a[rows[:2], :3] = j_x
    b = np.zeros((dim, 2))
    b[rows[:2]] = j_z
    e = np.zeros(dim)
    e[rows[2]] = 1.0
    np.testing.assert_allclose(new_cov, a @ cov @ a.T + b @ geometric_cov @ b.T + var * np.outer(e, e),
                               rtol=1e-12, atol=1e-12)
    want_mean = mean.copy()
    want_mean[rows] = np.r_[np.asarray(jax.jit(back_project)(jnp.asarray(mean[:3]), jnp.asarray(geo))), 0.0]
    np.testing.assert_allclose(new_mean, want_mean, rtol=1e-12, atol=1e-12)


def test_create_object_with_apply_false_changes_nothing():
    """``apply=False`` (a detection that creates nothing) returns the Gaussian bit for bit, also
    under vmap with a per-member flag, where the members that apply get the full update."""
    rng = np.random.default_rng(4)
    dim = 3 + 3 * 3
    root = rng.normal(size=(dim, dim))
    cov = jnp.asarray(root @ root.T / dim + 0.05 * np.eye(dim))
    mean = jnp.asarray(rng.normal(size=dim))
    args = (jnp.asarray(1), jnp.asarray([2.0, 0.3]), jnp.eye(2) * 0.01, jnp.asarray(4.0))
    same_mean, same_cov = CREATE_OBJECT(mean, cov, *args, apply=jnp.asarray(False))
    np.testing.assert_array_equal(np.asarray(same_mean), np.asarray(mean))
    np.testing.assert_array_equal(np.asarray(same_cov), np.asarray(cov))
    full = CREATE_OBJECT(mean, cov, *args)  # the program of test_create_object_covariance_matches_monte_carlo
    batched = jax.jit(jax.vmap(lambda a: create_object(mean, cov, *args, apply=a)))(jnp.asarray([True, False]))
    # Two programs (batched and not) that XLA fuses differently: equal up to the last bits.
    np.testing.assert_allclose(np.asarray(batched[1][0]), np.asarray(full[1]), rtol=1e-13, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(batched[1][1]), np.asarray(cov))
    assert not np.allclose(np.asarray(full[1]), np.asarray(cov))


def test_create_objects_creates_in_detection_order_and_skips_the_rest():
    """``create_objects`` equals ``create_object`` applied detection by detection to the creating
    slots only (the second new object correlated with the first through the pose), and the
    non-creating entries (slot -1 included) change nothing."""
    rng = np.random.default_rng(5)
    dim = 3 + 3 * 4
    root = rng.normal(size=(dim, dim))
    cov = jnp.asarray(root @ root.T / dim + 0.05 * np.eye(dim))
    mean = jnp.asarray(rng.normal(size=dim))
    slots, creates = jnp.asarray([3, -1, 1, 2]), jnp.asarray([True, False, True, False])
    geo = jnp.asarray([[2.0, 0.3], [1.0, -0.2], [3.0, 1.1], [2.5, 0.0]])
    gcov, var = jnp.eye(2) * 0.01, jnp.asarray(4.0)
    got = jax.jit(create_objects)(mean, cov, slots, creates, geo, gcov, var)
    want = CREATE_OBJECT(mean, cov, jnp.asarray(3), geo[0], gcov, var)
    want = CREATE_OBJECT(*want, jnp.asarray(1), geo[2], gcov, var)
    for g, w in zip(got, want):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-14, atol=1e-14)
    assert abs(float(got[1][3 + 3 * 3, 3 + 3 * 1])) > 0  # the two new objects are correlated
    skipped = slice(3 + 3 * 2, 6 + 3 * 2)  # slot 2: named by a detection that creates nothing
    np.testing.assert_array_equal(np.asarray(got[0][skipped]), np.asarray(mean[skipped]))
    np.testing.assert_array_equal(np.asarray(got[1][skipped, skipped]), np.asarray(cov[skipped, skipped]))


def test_a_smoothers_result_file_maps_the_created_objects_only(world, exact):
    """``objects`` (SCENARIO_FORMAT.md, result file) holds the smoothed poses of the objects that
    exist, indexed like ``classes``; the slots never created are left out."""
    run = hs.run_estimator(world, "ml", max_detections=2)  # the full smoother
    top = run.result.steps[-1].components[0]
    assert len(top.classes) == CAPACITY and run.result.objects.shape == (3, 3)
    assert top.associations == _true_objects(world)
    np.testing.assert_allclose(run.result.objects[:, :2], TRUTH[:, :2], atol=0.3)
    assert np.all(np.abs(run.result.objects[:, 2]) <= np.pi)
    filtered = exact  # the filter (RUN's smoother="filter")
    assert filtered.result.objects is None and filtered.result.trajectory is None
