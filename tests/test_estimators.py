"""The single-Gaussian association strategies ``ml``, ``gpda``, ``max-mixture`` (Doherty's thesis).

Every scenario here has the same shapes (4 object slots with discovery, 2 detection slots, an
8-step history), so each estimator's step is compiled once for the whole file; the runs use the
filter (association, discovery and the one-step updates are the subjects here; the smoother's are
tests/test_smoother_batch.py and tests/test_smoother.py).
"""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam import cli
from hybridslam.driver import run_estimator
from hybridslam.estimators import gaussian, maxmix
from hybridslam.io.result import load_result, save_result
from hybridslam.io.scenario import Classifier, Detection, Discovery, Scenario, Step
from hybridslam.models.measurement import Detections

ALPHA, K_SHARP = 0.25, 15.0
MAX_STEPS = 8  # every run uses this history length: one compiled step per estimator
ESTIMATORS = ("ml", "gpda", "max-mixture")


# --------------------------------------------------------------------------- #
# Hand-built scenarios
# --------------------------------------------------------------------------- #


def _scenario(objects, class_prior, robot_mean, robot_cov, steps, *, geometric_cov=(0.05**2, 0.02**2),
              log_density=-3.0, max_objects=4, fov=2.0944, max_range=10.0, true_poses=None, true_objects=None):
    n = len(objects)
    return Scenario(
        num_classes=2,
        object_prior_means=np.array([o for o, _ in objects], float).reshape(n, 3),
        object_prior_covs=np.array([np.diag(c) for _, c in objects], float).reshape(n, 3, 3),
        class_prior=np.array(class_prior, float).reshape(n, 2),
        robot_prior_mean=np.array(robot_mean, float), robot_prior_cov=np.diag(robot_cov),
        motion_cov=np.diag([1e-6, 1e-6, 1e-7]), geometric_cov=np.diag(geometric_cov),
        classifier=Classifier("mirror", alpha=ALPHA, K=K_SHARP), max_range=max_range, fov=fov,
        steps=tuple(steps), true_robot_poses=true_poses,
        discovery=Discovery(max_objects, log_density, 9.87), true_objects=true_objects,
    )


def _step(*dets, odometry=(0.0, 0.0, 0.0)):
    return Step(np.array(odometry, float), tuple(Detection(r, b, np.array(s, float)) for r, b, s in dets))


def _mirror_mean(c: int, cos_vp: float) -> np.ndarray:
    s = 0.5 * (1.0 - cos_vp)
    h0 = np.array([ALPHA * s + 1.0 - ALPHA, ALPHA - ALPHA * s])
    return h0 if c == 0 else h0[::-1]


def _mirror_loglik(scores, c, cos_vp) -> float:
    """``log N(scores; h_c, (RᵀR)⁻¹)`` of Eq. 18, in numpy."""
    r = K_SHARP * np.array([[1.0, -0.5], [0.0, 1.0]]) @ (np.asarray(scores) - _mirror_mean(c, cos_vp))
    return 2.0 * math.log(K_SHARP) - math.log(2.0 * math.pi) - 0.5 * r @ r


def _cos_viewpoint(x, obj) -> float:
    c, s = math.cos(obj[2]), math.sin(obj[2])
    v = np.array([[c, s], [-s, c]]) @ (x[:2] - obj[:2])
    return v[0] / np.linalg.norm(v)


def _toy():
    """Two known landmarks A, B, two detections; discovery on (a detection may be new)."""
    objects = [((3.0, 0.5, 0.0), (0.05, 0.05, 0.1)), ((3.0, -0.5, 0.0), (0.05, 0.05, 0.1))]
    step = _step((3.05, 0.15, (0.7, 0.3)), (3.3, -0.05, (0.4, 0.6)))
    return _scenario(objects, [[0.8, 0.2], [0.3, 0.7]], (0, 0, 0), (0.02, 0.02, 0.005), [step])


def _line_toy(prior_a: float):
    """One range-only-ambiguous detection of A = (3, 0) or B = (3.6, 0) from a robot believed at
    (1.32, 0) with a wide position prior: everything stays on the x axis, where range is linear."""
    objects = [((3.0, 0.0, 0.0), (1e-4, 1e-4, 1e-4)), ((3.6, 0.0, 0.0), (1e-4, 1e-4, 1e-4))]
    step = _step((3.0, 0.0, (1.0, 0.0)))
    return _scenario(objects, [[prior_a, 1 - prior_a], [1 - prior_a, prior_a]], (1.32, 0, 0), (4.0, 4.0, 1e-4),
                     [step], geometric_cov=(0.09, 0.02**2), log_density=-50.0)


# --------------------------------------------------------------------------- #
# Brute force in numpy
# --------------------------------------------------------------------------- #


def _rb_jacobian(x, obj, n, dim):
    """Range-bearing of object ``n`` from ``x``, and its Jacobian wrt the whole state (analytic)."""
    d = obj[:2] - x[:2]
    r2 = d @ d
    r = math.sqrt(r2)
    h = np.array([r, math.atan2(d[1], d[0]) - x[2]])
    jac = np.zeros((2, dim))
    jac[0, :2], jac[1, :2], jac[1, 2] = -d / r, np.array([d[1], -d[0]]) / r2, -1.0
    jac[0, 3 + 3 * n : 5 + 3 * n], jac[1, 3 + 3 * n : 5 + 3 * n] = d / r, np.array([-d[1], d[0]]) / r2
    return h, jac


def _brute_force(mean, cov, geo, scores, class_prior, num_objects, log_density, gamma):
    """Every injective assignment (object or "new") of the detections: its normalized probability."""
    mean, cov = np.asarray(mean), np.asarray(cov)
    x, dim = mean[:3], mean.shape[0]
    out = {}
    for assign in itertools.product([*range(num_objects), "new"], repeat=len(geo)):
        objs = [a for a in assign if a != "new"]
        if len(set(objs)) < len(objs):
            continue
        logw, e, rows = 0.0, [], []
        for j, a in enumerate(assign):
            if a == "new":
                p = x[:2] + geo[j][0] * np.array([math.cos(x[2] + geo[j][1]), math.sin(x[2] + geo[j][1])])
                cos_vp = _cos_viewpoint(x, np.array([*p, 0.0]))
                logw += log_density + np.logaddexp(*[math.log(0.5) + _mirror_loglik(scores[j], c, cos_vp) for c in (0, 1)])
                continue
            obj = mean[3 + 3 * a : 6 + 3 * a]
            h, jac = _rb_jacobian(x, obj, a, dim)
            diff = np.asarray(geo[j]) - h
            diff[1] = (diff[1] + math.pi) % (2 * math.pi) - math.pi
            e.append(diff)
            rows.append(jac)
            cos_vp = _cos_viewpoint(x, obj)
            logw += np.logaddexp(*[math.log(class_prior[a][c]) + _mirror_loglik(scores[j], c, cos_vp) for c in (0, 1)])
        if e:
            e, h = np.concatenate(e), np.concatenate(rows)
            s = h @ cov @ h.T + np.kron(np.eye(len(rows)), gamma)
            logw += -0.5 * e @ np.linalg.solve(s, e) - 0.5 * np.linalg.slogdet(2 * math.pi * s)[1]
        out[assign] = logw
    total = np.logaddexp.reduce(list(out.values()))
    return {a: math.exp(v - total) for a, v in out.items()}


def _weighted_line_solution(prior_mean, prior_var, weights, z, var):
    """Closed form of the weighted linear-Gaussian update on the x axis (thesis Eq. 3.7 with a
    linear model): unknowns ``[x, a_x, b_x]``, factors ``√w_j (z − (ℓ_j − x)) / σ``."""
    info = np.diag(1.0 / np.asarray(prior_var))
    vec = info @ np.asarray(prior_mean)
    for j, w in enumerate(weights):
        row = np.zeros(3)
        row[0], row[1 + j] = -1.0, 1.0  # range = ℓ_j − x
        info += w / var * np.outer(row, row)
        vec += w / var * row * z
    return np.linalg.solve(info, vec)


# --------------------------------------------------------------------------- #
# Fixtures
# --------------------------------------------------------------------------- #


def _init(scenario):
    return hs.ML(max_detections=2, max_steps=MAX_STEPS).init(scenario)


def _dets(scenario, k=0):
    st = hs.stack_steps(scenario, 2)
    return Detections(jnp.asarray(st.geo[k]), jnp.asarray(st.scores[k]), jnp.asarray(st.mask[k]))


@pytest.fixture(scope="module")
def associate():
    return jax.jit(gaussian.associate)


_predict = jax.jit(gaussian.predict)  # op by op: about a hundred tiny compiles


_associate_beam = jax.jit(gaussian.associate, static_argnames="width")


@pytest.fixture(scope="module")
def toy():
    scenario = _toy()
    state = _init(scenario)
    mean, cov = _predict(state, jnp.zeros(3))
    return scenario, state, mean, cov


def _runs(scenario, estimator):
    return run_estimator(scenario, estimator, max_steps=MAX_STEPS, max_detections=2, smoother="filter")


# --------------------------------------------------------------------------- #
# Tests
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("width", [None, 16])
def test_association_probabilities_match_brute_force(toy, associate, width):
    """Exhaustive enumeration (``width=None``, the joint innovation density of each row) and the
    beam (one detection at a time, :mod:`hybridslam.inference.sequential`) against brute force."""
    scenario, state, mean, cov = toy
    dets = _dets(scenario)
    assoc = associate(state, mean, cov, dets) if width is None else _associate_beam(state, mean, cov, dets, width)
    want = _brute_force(mean, cov, np.asarray(dets.geo), np.asarray(dets.scores), scenario.class_prior, 2,
                        scenario.discovery.new_object_log_density, scenario.geometric_cov)
    assert len(want) == 7 and min(want.values()) > 1e-6  # every hypothesis matters
    cand = np.asarray(assoc.candidates)
    assert np.asarray(assoc.candidate_ok)[:, :2].all() and not np.asarray(assoc.candidate_ok)[:, 2].any()
    g, ok = assoc.num_candidates, np.asarray(assoc.candidate_ok)
    got = {}
    for opts, lp in zip(np.asarray(assoc.options), np.asarray(assoc.log_prob)):
        if lp > -np.inf:
            got[tuple("new" if o == g else int(cand[j, o]) for j, o in enumerate(opts))] = math.exp(lp)
    assert got.keys() == want.keys()
    for a in want:
        assert got[a] == pytest.approx(want[a], abs=1e-9)
    marg = np.asarray(assoc.marginals)
    for j in range(2):
        for o in range(g + 1):
            target = "new" if o == g else int(cand[j, o]) if ok[j, o] else None
            assert marg[j, o] == pytest.approx(sum(p for a, p in want.items() if a[j] == target), abs=1e-9)


def test_ml_fixes_the_brute_force_argmax(toy):
    scenario, state, mean, cov = toy
    dets = _dets(scenario)
    want = _brute_force(mean, cov, np.asarray(dets.geo), np.asarray(dets.scores), scenario.class_prior, 2,
                        scenario.discovery.new_object_log_density, scenario.geometric_cov)
    best = max(want, key=want.get)
    slots = iter(range(2, 4))  # new objects take the next slots in detection order
    expected = [next(slots) if a == "new" else a for a in best]
    run = _runs(scenario, "ml")
    assert run.result.steps[0].components[0].associations == [expected]
    assert int(run.belief.num_created) == 2 + sum(a == "new" for a in best)


def _line_weights(associate, scenario):
    state = _init(scenario)
    mean, cov = _predict(state, jnp.zeros(3))
    assoc = associate(state, mean, cov, _dets(scenario))
    cand = np.asarray(assoc.candidates)[0]
    w = {int(cand[g]): float(assoc.marginals[0, g]) for g in range(2)}
    return state, mean, cov, assoc, w


def test_max_mixture_factor_picks_the_likelier_component_across_a_switch(associate):
    scenario = _line_toy(0.995)
    state, mean, cov, assoc, w = _line_weights(associate, scenario)
    assert w[0] > 0.99  # the semantics make A far likelier; geometry alone slightly prefers B
    sensor = state.model.sensor
    valid = jnp.concatenate([assoc.candidate_ok[0], jnp.array([True])]) & (assoc.marginals[0] > 0)
    log_w = jnp.log(jnp.where(valid, assoc.marginals[0], 1.0))
    args = (sensor, assoc.candidates[0], _dets(scenario).geo[0], log_w, valid, state.params.new_object_log_density)

    residual = jax.jit(maxmix.max_mixture_residual)

    def active_at(robot_x):
        _, g = residual(sensor, mean.at[0].set(robot_x), *args[1:])
        return int(assoc.candidates[0, g])

    def brute_at(robot_x):  # argmax_j w_j N(z; h_j(y), Γ) in numpy
        score = {n: math.log(w[n]) - 0.5 * (3.0 - (float(mean[3 + 3 * n]) - robot_x)) ** 2 / 0.09 for n in (0, 1)}
        return max(score, key=score.get)

    for robot_x in (1.32, 0.9, 0.6, 0.3, 0.0):
        assert active_at(robot_x) == brute_at(robot_x)
    assert active_at(1.32) == 1 and active_at(0.6) == 0  # B active at the prior mean, A at B's mode: a switch
    run = _runs(scenario, "max-mixture")
    final = run.belief
    want = _weighted_line_solution([1.32, 3.0, 3.6], [4.0 + 1e-6, 1e-4, 1e-4], [1.0, 0.0], 3.0, 0.09)
    np.testing.assert_allclose(np.asarray(final.mean)[[0, 3, 6]], want, atol=1e-6)
    assert abs(float(final.mean[1])) < 1e-9 and run.result.steps[0].components[0].associations == [[0]]


def test_gpda_sits_between_the_modes_nearer_the_likelier(associate):
    scenario = _line_toy(0.7)
    *_, w = _line_weights(associate, scenario)
    assert 0.55 < w[0] < 0.8 and w[0] + w[1] == pytest.approx(1.0, abs=1e-12)
    run = _runs(scenario, "gpda")
    x = float(run.belief.mean[0])
    prior = ([1.32, 3.0, 3.6], [4.0 + 1e-6, 1e-4, 1e-4])
    mode_a = _weighted_line_solution(*prior, [1.0, 0.0], 3.0, 0.09)[0]
    mode_b = _weighted_line_solution(*prior, [0.0, 1.0], 3.0, 0.09)[0]
    t = (x - mode_a) / (mode_b - mode_a)
    assert 0.0 < t < 0.5  # between the modes, nearer A
    assert x == pytest.approx(_weighted_line_solution(*prior, [w[0], w[1]], 3.0, 0.09)[0], abs=1e-6)


def _clean_discovery_scenario():
    """A robot driving along x past 4 objects, noise-free detections, an empty initial map."""
    truth = [(np.array([2.5, 1.2, 0.3]), 0), (np.array([3.5, -1.2, -0.5]), 1),
             (np.array([6.0, 1.2, 1.0]), 1), (np.array([7.5, -1.2, 2.0]), 0)]
    poses = [np.array([1.0 * k, 0.0, 0.0]) for k in range(MAX_STEPS + 1)]
    steps = []
    for x in poses[1:]:
        dets = []
        for n, (obj, c) in enumerate(truth):
            d = obj[:2] - x[:2]
            rng, bearing = float(np.linalg.norm(d)), math.atan2(d[1], d[0]) - x[2]
            if rng <= 3.0 and abs(bearing) <= 1.3:
                dets.append(Detection(rng, bearing, _mirror_mean(c, _cos_viewpoint(x, obj)), true_object=n))
        steps.append(Step(np.array([1.0, 0.0, 0.0]), tuple(dets)))
    sc = _scenario([], np.zeros((0, 2)), (0, 0, 0), (1e-6, 1e-6, 1e-7), [], max_range=3.0,
                   true_poses=np.array(poses), true_objects=tuple(truth))
    return sc.replace(steps=tuple(steps))


@pytest.fixture(scope="module")
def discovery_scenario():
    sc = _clean_discovery_scenario()
    assert sc.max_detections == 2 and {d.true_object for s in sc.steps for d in s.detections} == {0, 1, 2, 3}
    return sc


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_unknown_map_creates_each_true_object_once(discovery_scenario, estimator):
    run = _runs(discovery_scenario, estimator)
    assert int(run.belief.num_created) == 4
    pairs = {(d.true_object, o) for s, a in zip(discovery_scenario.steps, run.result.steps[-1].components[0].associations)
             for d, o in zip(s.detections, a)}
    assert len(pairs) == 4 and {t for t, _ in pairs} == {0, 1, 2, 3} and {o for _, o in pairs} == {0, 1, 2, 3}
    classes = run.result.steps[-1].components[0].classes
    by_truth = dict(pairs)
    assert [classes[by_truth[t]] for t in range(4)] == [c for _, c in discovery_scenario.true_objects]
    # The 4 slots are exactly the 4 landmarks: once they exist, a re-detection can no longer be a new
    # object, which is said at every such step and is the only warning.
    before = [0] + [int(i.details.num_created) for i in run.infos[:-1]]
    full = [b == 4 and len(s.detections) > 0 for b, s in zip(before, discovery_scenario.steps)]
    assert any(full) and [bool(i.object_overflow) for i in run.infos] == full
    assert all(": object capacity full" in w for i in run.infos for w in i.warnings())


@pytest.mark.parametrize("estimator", ["ml", "gpda", "max-mixture"])
def test_no_free_slot_leaves_the_new_object_unmapped_and_warns(estimator):
    """A detection of a new landmark with every object slot used is an unmapped object: counted and
    warned, written -1, nothing created, the belief finite."""
    full = [((3.0, 0.5 * i, 0.0), (0.01, 0.01, 0.1)) for i in range(4)]  # capacity 4 reached
    sc = _scenario(full, [[0.5, 0.5]] * 4, (0, 0, 0), (0.01, 0.01, 0.001), [_step((8.0, -1.0, (0.5, 0.5)))])
    run = _runs(sc, estimator)
    info = run.infos[0]
    assert (int(info.unmapped), int(info.skipped), int(info.rejected)) == (1, 0, 0) and int(run.belief.num_created) == 4
    assert "weighed as new objects but not stored" in " ".join(info.warnings()) and not bool(info.inconsistent)
    assert bool(run.infos[0].object_overflow) and "object capacity full" in " ".join(run.infos[0].warnings())
    assert np.isfinite(np.asarray(run.belief.mean)).all()
    # The result file says so: -1, not the detection's nearest object (SCENARIO_FORMAT.md).
    assert run.result.steps[0].components[0].associations == [[-1]]


@pytest.mark.parametrize("estimator", ["ml", "gpda", "max-mixture"])
def test_a_full_map_does_not_force_a_new_landmark_onto_an_old_object(estimator):
    """A detection inside an old object's gate (d² ≈ 11.6 < 13.8) but likelier a new object (its log
    density 1.0 against the object's about -0.7): with a free slot it creates one; with none it is
    unmapped, not named as the old object (before, the null option with no slot counted as a skip,
    ranked below every association)."""
    ahead = [((3.0, 0.0, 0.0), (1e-4, 1e-4, 0.1))]
    others = [((-3.0, 3.0 * i, 0.0), (1e-4, 1e-4, 0.1)) for i in range(3)]  # behind the robot: not candidates
    det = _step((3.0, 0.068, (0.5, 0.5)))  # 0.2 m to the side: bearing d² ≈ (0.068 / 0.02)²
    for objects, created in ((ahead, 2), (ahead + others, 4)):
        sc = _scenario(objects, [[0.5, 0.5]] * len(objects), (0, 0, 0), (1e-6, 1e-6, 1e-7), [det], log_density=1.0)
        run = _runs(sc, estimator)
        assoc = run.result.steps[0].components[0].associations[0]
        if created == 2:  # a free slot: the detection creates object 1
            assert assoc == [1] and int(run.belief.num_created) == 2
        else:
            assert assoc == [-1] and int(run.infos[0].unmapped) == 1 and int(run.belief.num_created) == 4


def test_result_files_and_cli(discovery_scenario, tmp_path, capsys):
    run = _runs(discovery_scenario, "ml")
    save_result(run.result, tmp_path / "ml.json")
    assert load_result(tmp_path / "ml.json").estimator.startswith("hybridslam") and "maximum-likelihood" in run.result.estimator
    path = tmp_path / "scenario.json"
    hs.save_scenario(discovery_scenario, path)
    out = tmp_path / "gpda.json"
    assert cli.main(["run", str(path), "-o", str(out), "--estimator", "gpda", "--smoother", "filter"]) == 0
    result = load_result(out)
    assert "Gaussian PDA" in result.estimator and len(result.steps) == discovery_scenario.num_steps
    assert result.steps[-1].components[0].classes[:4] != [-1] * 4
    assert "gpda" in capsys.readouterr().out
    assert cli.main(["run", str(path), "-o", str(out), "--estimator", "nope"]) == 2


@pytest.mark.parametrize("name", ["hybrid", "ml", "gpda", "max-mixture", "multimodal"])
def test_a_known_map_without_objects_is_refused_by_name(name):
    """A known map with no objects and no discovery section (a KITTI drive past no parked car) has
    nothing to associate: every estimator refuses it at init with the field named, none fails inside
    its compiled step."""
    s = hs.simulate(seed=0, steps=3)
    empty = s.replace(object_prior_means=np.zeros((0, 3)), object_prior_covs=np.zeros((0, 3, 3)),
                      class_prior=np.zeros((0, s.num_classes)), true_object_poses=None, true_classes=None,
                      true_objects=None, discovery=None)
    with pytest.raises(ValueError, match="no objects"):
        hs.make_estimator(name).init(empty)
