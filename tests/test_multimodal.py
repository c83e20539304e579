"""The multimodal (sum-mixture) estimator, thesis Ch. 5: modes kept, Monte Carlo association
probabilities against brute force, a late mode recovered, new objects created once.

Every scenario here runs with the same static shapes (capacity 8, 4 object slots, 2 detection
slots, 6 history steps, 2048 samples, the mirror classifier), so the whole file compiles the step
once (``run_estimator`` caches compiled steps by shape). The runs filter (``smoother="filter"``): the
assertions are about the association step (modes, weights, probabilities, created objects), not the
smoother, and the filter's step compiles in a fraction of the full smoother's time.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from hybridslam.driver import run_estimator
from hybridslam.inference import gating
from hybridslam.io.result import parse_result, result_to_json
from hybridslam.io.scenario import parse_scenario

SHAPES = dict(capacity=8, samples=2048, max_detections=2, max_steps=6, smoother="filter")
ALPHA, K_SEM = 0.25, 15.0
GEO_COV = np.diag([0.01, 0.0025])


def _diag(*v) -> list:
    return np.diag(v).tolist()


def _mirror_mean(viewpoint: np.ndarray, c: int) -> np.ndarray:
    """``h_c(viewpoint)`` of the paper's Eq. 18 (numpy), for any array of angles."""
    s = np.sin(viewpoint / 2) ** 2
    h0 = np.stack([ALPHA * s + 1 - ALPHA, ALPHA - ALPHA * s], axis=-1)
    return h0 if c == 0 else h0[..., ::-1]


def _scenario(objects, robot_mean, robot_cov, steps, *, class_prior=None, new_density=-30.0, **extra):
    return parse_scenario({
        "format": "hybridslam-scenario/1", "num_classes": 2,
        "objects": [{"prior_mean": list(p), "prior_cov": _diag(1e-8, 1e-8, 1e-8)} for p in objects],
        **({"class_prior": class_prior} if class_prior is not None else {}),
        "robot": {"prior_mean": list(robot_mean), "prior_cov": robot_cov},
        "motion_cov": _diag(1e-4, 1e-4, 1e-6), "geometric_cov": GEO_COV.tolist(),
        "classifier": {"model": "mirror", "alpha": ALPHA, "K": K_SEM},
        "sensor": {"max_range": 20.0, "fov": 2 * math.pi},
        "discovery": {"max_objects": 4, "new_object_log_density": new_density,
                      "new_object_orientation_var": 9.87},
        "steps": steps,
        **extra,
    })


# --------------------------------------------------------------------------- #
# (a), (c): identical objects A and B, a third object C that only the B-mode can see
# --------------------------------------------------------------------------- #

A, B, C = (-3.0, 0.0, 0.0), (3.0, 0.0, 0.0), (3.0, 4.0, 0.0)
SEEN = _mirror_mean(np.array(-math.pi / 2), 0).tolist()  # scores as class 0 looks from straight in front


def _ambiguity(prior_x: float):
    """Robot at ``(prior_x, -2)`` facing +y (σ = 2 m): step 1 sees A or B 2 m ahead; step 2 sees C 6 m ahead."""
    det = lambda r: {"odometry": [0, 0, 0], "detections": [{"range": r, "bearing": 0.0, "scores": SEEN}]}  # noqa: E731
    return _scenario([A, B, C], (prior_x, -2.0, math.pi / 2), _diag(4.0, 4.0, 1e-4), [det(2.0), det(6.0)])


@pytest.fixture(scope="module")
def symmetric():
    return run_estimator(_ambiguity(0.0), "multimodal", **SHAPES)


@pytest.fixture(scope="module")
def late():
    return run_estimator(_ambiguity(-1.5), "multimodal", **SHAPES)


def test_symmetric_ambiguity_keeps_both_modes(symmetric):
    """One detection of one of two identical objects: the pose marginal has two modes of weight 1/2
    at the two mirror positions (the prior is symmetric about x = 0)."""
    comps = symmetric.result.steps[0].components
    top = sorted(comps[:2], key=lambda c: c.pose_mean[0])
    assert [c.weight for c in top] == pytest.approx([0.5, 0.5], abs=0.02)
    assert top[0].pose_mean[:2] == pytest.approx([-3.0, -2.0], abs=0.05)
    assert top[1].pose_mean[:2] == pytest.approx([3.0, -2.0], abs=0.05)
    assert [c.associations for c in top] == [[[0]], [[1]]]
    assert sum(c.weight for c in comps[2:]) < 0.05  # the C explanation: 3 m further from the prior


def test_unlikely_mode_survives_and_wins(late):
    """The prior favours A (weight ≈ 0.99 with the thesis's double-counted Eq. 5.11 weights); the
    B-mode is kept, and when C is seen it becomes the only likely explanation."""
    first = late.result.steps[0].components
    b_mode = [c for c in first if c.associations == [[1]]]
    assert len(b_mode) == 1 and 1e-4 < b_mode[0].weight < 0.05
    assert first[0].associations == [[0]] and first[0].weight > 0.9
    best = late.result.steps[1].components[0]
    assert best.associations == [[1], [2]] and best.weight > 0.99
    assert best.pose_mean[:2] == pytest.approx([3.0, -2.0], abs=0.05)


# --------------------------------------------------------------------------- #
# (b): Monte Carlo association probabilities against brute-force quadrature
# --------------------------------------------------------------------------- #

L0, L1 = (2.0, 0.25, 0.3), (2.0, -0.25, -0.4)
TOY_PRIOR = np.array([0.0, 0.0, 0.0])
TOY_SD = np.array([0.15, 0.15, 0.05])
TOY_CLASS_PRIOR = [[0.8, 0.2], [0.3, 0.7]]
TOY_NEW_DENSITY = 1.5
NEW = -1  # "new object" in a brute-force tuple


def _toy_detections() -> list[dict]:
    true_pose = np.array([0.05, -0.03, 0.02])
    out = []
    for obj, c, noise in ((L0, 0, (0.05, 0.02)), (L1, 1, (-0.08, -0.03))):
        d = np.array(obj[:2]) - true_pose[:2]
        rng = np.hypot(*d) + noise[0]
        bearing = math.atan2(d[1], d[0]) - true_pose[2] + noise[1]
        vp = math.atan2(*(-np.array([[math.cos(obj[2]), math.sin(obj[2])], [-math.sin(obj[2]), math.cos(obj[2])]]) @ d)[::-1])
        out.append({"range": rng, "bearing": bearing, "scores": (_mirror_mean(np.array(vp), c) + 0.01).tolist()})
    return out


def _toy():
    return _scenario([L0, L1], TOY_PRIOR, np.diag(TOY_SD**2).tolist(),
                     [{"odometry": [0, 0, 0], "detections": _toy_detections()}],
                     class_prior=TOY_CLASS_PRIOR, new_density=TOY_NEW_DENSITY)


def _log_mirror(z: np.ndarray, viewpoint: np.ndarray, c: int) -> np.ndarray:
    r_sqrt = K_SEM * np.array([[1.0, -0.5], [0.0, 1.0]])
    r = (z - _mirror_mean(viewpoint, c)) @ r_sqrt.T
    return 2 * math.log(K_SEM) - math.log(2 * math.pi) - 0.5 * np.sum(r**2, axis=-1)


def brute_force_probabilities() -> dict[tuple[int, int], float]:
    """``p(d_1, d_2 | Z)`` of every injective joint assignment by quadrature over the robot pose (Eq. 5.9
    with the integral of Eq. 5.10 done on a grid; the objects' priors are points)."""
    axes = [np.linspace(m - 5 * s, m + 5 * s, n) for m, s, n in zip(TOY_PRIOR, TOY_SD, (61, 61, 31))]
    x, y, th = np.meshgrid(*axes, indexing="ij")
    log_prior = -0.5 * sum(((g - m) / s) ** 2 for g, m, s in zip((x, y, th), TOY_PRIOR, TOY_SD))
    dets = _toy_detections()
    w_geo = np.linalg.cholesky(np.linalg.inv(GEO_COV)).T
    geo_norm = -0.5 * np.log(np.linalg.det(2 * math.pi * GEO_COV))
    # A new object's orientation ~ N(0, 9.87): its viewpoint is θ_x + bearing + π − θ_o (grid in θ_o).
    theta_o = np.linspace(-6 * math.sqrt(9.87), 6 * math.sqrt(9.87), 401)
    w_o = np.exp(-0.5 * theta_o**2 / 9.87)
    w_o /= w_o.sum()
    terms = []
    for det in dets:
        z = np.array(det["scores"])
        per = {}
        for n, obj in enumerate((L0, L1)):
            dx, dy = obj[0] - x, obj[1] - y
            pred_b = np.arctan2(-np.sin(th) * dx + np.cos(th) * dy, np.cos(th) * dx + np.sin(th) * dy)
            res = np.stack([det["range"] - np.hypot(dx, dy), np.angle(np.exp(1j * (det["bearing"] - pred_b)))], -1)
            geo = geo_norm - 0.5 * np.sum((res @ w_geo.T) ** 2, axis=-1)
            vp = np.arctan2(-np.sin(obj[2]) * -dx + np.cos(obj[2]) * -dy, np.cos(obj[2]) * -dx + np.sin(obj[2]) * -dy)
            sem = np.logaddexp(*(np.log(TOY_CLASS_PRIOR[n][c]) + _log_mirror(z, vp, c) for c in (0, 1)))
            per[n] = geo + sem
        vp_new = axes[2][:, None] + det["bearing"] + math.pi - theta_o[None, :]
        sem_new = np.log(sum(0.5 * np.exp(_log_mirror(z, vp_new, c)) @ w_o for c in (0, 1)))
        per[NEW] = TOY_NEW_DENSITY + np.broadcast_to(sem_new[None, None, :], x.shape)
        terms.append(per)
    tuples = [(a, b) for a in (0, 1, NEW) for b in (0, 1, NEW) if a == NEW or a != b]
    logs = np.array([np.logaddexp.reduce((log_prior + terms[0][a] + terms[1][b]).ravel()) for a, b in tuples])
    p = np.exp(logs - np.logaddexp.reduce(logs))
    return dict(zip(tuples, p))


def _estimated_probabilities(info) -> dict[tuple[int, int], float]:
    objects = np.asarray(info.details.assoc_objects)
    log_p = np.asarray(info.details.assoc_log_probs)
    out = {}
    for obj, lp in zip(objects, log_p):
        if lp > -np.inf:
            out[tuple(int(o) if o < 2 else NEW for o in obj)] = float(np.exp(lp))
    return out


@pytest.fixture(scope="module")
def toy_runs():
    return [run_estimator(_toy(), "multimodal", seed=s, **SHAPES) for s in range(6)]


def test_association_probabilities_converge_to_brute_force(toy_runs):
    """Eq. 5.9-5.10 by Monte Carlo (2048 joint samples per child) against quadrature on a 61×61×31
    pose grid: every seed within 0.015, and the mean of 6 seeds (12288 samples) within 0.006
    (measured: at most 0.0044 per seed; the literal prior-sampling proposal: at most 0.0049)."""
    exact = brute_force_probabilities()
    assert sum(exact.values()) == pytest.approx(1.0)
    assert exact[(0, 1)] > 0.5 and exact[(1, 0)] < 1e-3  # joint compatibility rules out the swap
    assert max(exact[(0, NEW)], exact[(NEW, 1)]) > 0.02  # the null hypothesis carries real mass
    estimates = [_estimated_probabilities(run.infos[0]) for run in toy_runs]
    for est in estimates:
        assert set(est) == set(exact)
        assert max(abs(est[t] - exact[t]) for t in exact) < 0.015
    mean = {t: np.mean([est[t] for est in estimates]) for t in exact}
    assert max(abs(mean[t] - exact[t]) for t in exact) < 0.006


def test_joint_assignments_enumerate_every_choice():
    choices = gating.joint_options(2, 2)
    assert choices.shape == (9, 2) and len({tuple(c) for c in choices}) == 9


# --------------------------------------------------------------------------- #
# (d), (e): an unknown map, a clean sequence
# --------------------------------------------------------------------------- #

TRUE_OBJECTS = [((2.0, 1.0, 0.5), 0), ((3.5, -1.0, -1.0), 1), ((5.0, 1.0, 2.0), 0)]


def _clean_sequence(prior_objects=()):
    """Three objects, none mapped (``prior_objects``: mapped ones, not seen); the robot drives +x 1 m
    a step and sees what is within 3 m, ±60°."""
    poses = [np.array([float(k), 0.0, 0.0]) for k in range(6)]
    steps = []
    for pose in poses[1:]:
        dets = []
        for i, (obj, c) in enumerate(TRUE_OBJECTS):
            d = np.array(obj[:2]) - pose[:2]
            bearing = math.atan2(d[1], d[0]) - pose[2]
            if np.hypot(*d) <= 3.0 and abs(bearing) <= math.pi / 3:
                vp = math.atan2(*(-np.array([[math.cos(obj[2]), math.sin(obj[2])], [-math.sin(obj[2]), math.cos(obj[2])]]) @ d)[::-1])
                dets.append({"range": float(np.hypot(*d)), "bearing": bearing,
                             "scores": _mirror_mean(np.array(vp), c).tolist(), "true_object": i})
        steps.append({"odometry": [1.0, 0.0, 0.0], "detections": dets[:2]})
    return _scenario(list(prior_objects), (0.0, 0.0, 0.0), _diag(1e-4, 1e-4, 1e-6), steps, new_density=-4.0,
                     true_objects=[{"pose": list(p), "class": c} for p, c in TRUE_OBJECTS],
                     )


@pytest.fixture(scope="module")
def discovery_run():
    scenario = _clean_sequence()
    return scenario, run_estimator(scenario, "multimodal", **SHAPES)


def test_unknown_map_creates_each_object_once(discovery_run):
    scenario, run = discovery_run
    best = run.result.steps[-1].components[0]
    assert best.weight > 0.9
    truth_to_estimate: dict[int, set[int]] = {}
    for step, assoc in zip(scenario.steps, best.associations):
        for det, obj in zip(step.detections, assoc):
            truth_to_estimate.setdefault(det.true_object, set()).add(obj)
    assert set(truth_to_estimate) == {0, 1, 2}  # the sequence sees every object
    assert all(len(v) == 1 for v in truth_to_estimate.values())  # each true object is one estimate
    assert len({next(iter(v)) for v in truth_to_estimate.values()}) == 3  # ... and no two share one
    assert sorted(c for c in best.classes if c >= 0) == [0, 0, 1]
    assert best.classes.count(-1) == 1  # the fourth slot is never created


def test_an_object_beyond_the_slots_is_unmapped_never_an_old_one():
    """Two mapped objects out of range leave 2 of the 4 slots for the 3 objects seen: the last one's
    detections are unmapped (weighed as new objects, not stored: object -1), not named as an old
    object, counted (``StepInfo.unmapped``) and warned. (The file's shapes: no new compile.)"""
    scenario = _clean_sequence(prior_objects=[(-40.0, 0.0, 0.0), (-40.0, 6.0, 0.0)])
    run = run_estimator(scenario, "multimodal", **SHAPES)
    best = run.result.steps[-1].components[0]
    pairs = [(d.true_object, o) for step, assoc in zip(scenario.steps, best.associations)
             for d, o in zip(step.detections, assoc)]
    unmapped = {t for t, o in pairs if o == -1}
    assert len(unmapped) == 1  # one true object has no slot, and only its detections are unmapped
    stored = {t: {o for tt, o in pairs if tt == t} for t in {t for t, _ in pairs} - unmapped}
    assert sorted(o for v in stored.values() for o in v) == [2, 3]  # one new slot each, after the mapped two
    assert sum(int(i.unmapped) for i in run.infos) == sum(1 for _, o in pairs if o == -1) > 0
    assert any("weighed as new objects but not stored" in w for i in run.infos for w in i.warnings())
    assert int(run.belief.num_created[0]) == 4


def test_result_file_validates(discovery_run):
    _, run = discovery_run
    parsed = parse_result(result_to_json(run.result))
    assert "multimodal" in parsed.estimator
    assert len(parsed.steps) == 5 and parsed.steps[-1].metrics["num_components"] >= 1


# --------------------------------------------------------------------------- #
# The beam's sequential screening against the exhaustive joint screening
# --------------------------------------------------------------------------- #


def _crowded(objects=None, max_objects=6, fov=2 * math.pi):
    """Four correlated, uncertain objects in a row, a broad robot prior, three detections: the pose
    and map correlations make each detection's conditional density depend on the earlier ones.
    A ``fov`` of about 0.7 rad puts the outer objects near the footprint's edges."""
    objects = objects or [(2.0, -0.6, 0.0), (2.2, 0.0, 0.0), (2.0, 0.6, 0.0), (3.0, 0.2, 0.0)]
    dets = [{"range": 2.05, "bearing": -0.28, "scores": SEEN}, {"range": 2.18, "bearing": 0.02, "scores": SEEN},
            {"range": 2.1, "bearing": 0.3, "scores": SEEN}]
    return parse_scenario({
        "format": "hybridslam-scenario/1", "num_classes": 2,
        "objects": [{"prior_mean": list(p), "prior_cov": _diag(0.02, 0.02, 0.1)} for p in objects],
        "robot": {"prior_mean": [0.0, 0.0, 0.0], "prior_cov": _diag(0.05, 0.05, 0.01)},
        "motion_cov": _diag(1e-4, 1e-4, 1e-6), "geometric_cov": GEO_COV.tolist(),
        "classifier": {"model": "mirror", "alpha": ALPHA, "K": K_SEM},
        "sensor": {"max_range": 20.0, "fov": fov},
        "discovery": {"max_objects": max_objects, "new_object_log_density": -3.0, "new_object_orientation_var": 9.87},
        "steps": [{"odometry": [0, 0, 0], "detections": dets}],
    })


@pytest.mark.parametrize("fov", [2 * math.pi, 0.7])
def test_sequential_beam_screening_equals_the_exhaustive_joint_screening(fov):
    """The beam scores a partial assignment one detection at a time (a rank-2 downdate of the
    covariance per detection, :class:`Conditioned`); with room for every joint assignment
    (4³ = 64 rows) its children, screening scores and weights equal the exhaustive enumeration's,
    which scores each row by the joint innovation density of all its detections at once. With a
    narrow footprint the in-view probabilities enter both screens alike."""
    import jax

    from hybridslam.driver import inputs_from_scenario
    from hybridslam.estimators.multimodal import Multimodal, association_log_probabilities
    from hybridslam.estimators.smoothers import Filter

    scenario = _crowded(fov=fov)
    detections = jax.tree.map(lambda a: a[0], inputs_from_scenario(scenario, 3).detections)
    out = {}
    for name, width in (("beam", 64), ("exhaustive", None)):
        est = Multimodal(capacity=2, samples=32, max_detections=3, max_steps=2, smoother=Filter(), max_assignments=width)
        state = est.init(scenario)
        ch = association_log_probabilities(state, detections, jax.random.key(0))
        rows = {tuple(int(o) for o in obj): (float(lw), float(lp))
                for obj, lw, lp in zip(np.asarray(ch.objects), np.asarray(ch.log_weight), np.asarray(ch.log_prob))
                if lw > -np.inf}
        out[name] = rows
    assert len(out["beam"]) == 4 and out["beam"].keys() == out["exhaustive"].keys()
    for key, (lw, lp) in out["exhaustive"].items():
        assert out["beam"][key][0] == pytest.approx(lw, abs=1e-9)
        assert out["beam"][key][1] == pytest.approx(lp, abs=1e-9)


def test_the_screen_weighs_each_named_object_by_its_in_view_probability():
    """``screen_log_likelihood`` under a narrow footprint is the all-round sensor's screen plus
    ``log P(in view)`` (``log_visibility_probability`` of the linearized predictive) of every
    created object the assignment names; new objects and empty slots add nothing."""
    import jax
    import jax.numpy as jnp

    from hybridslam.driver import inputs_from_scenario
    from hybridslam.estimators import multimodal as mm
    from hybridslam.estimators.smoothers import Filter
    from hybridslam.models.geometry import range_bearing
    from hybridslam.models.measurement import log_visibility_probability

    screens = {}
    for fov in (2 * math.pi, 0.7):
        scenario = _crowded(fov=fov)
        detections = jax.tree.map(lambda a: a[0], inputs_from_scenario(scenario, 3).detections)
        est = mm.Multimodal(capacity=2, samples=8, max_detections=3, max_steps=2, smoother=Filter())
        state = est.init(scenario)
        m, c, sensor = state.mean[0], state.cov[0], state.model.sensor
        pred = jax.jit(gating.innovations)(sensor, m, c, detections)
        objects, new = jnp.asarray([0, 3, -1]), jnp.asarray([False, False, True])
        screens[fov] = float(jax.jit(mm.screen_log_likelihood)(sensor, state.params, pred, m, c,
                                                              state.class_log_probs[0], objects, new, detections))
    in_view = 0.0
    for n in (0, 3):
        idx = np.r_[0:3, 3 + 3 * n:6 + 3 * n]
        jac = np.concatenate(jax.jacfwd(range_bearing, argnums=(0, 1))(m[:3], m[3 + 3 * n:6 + 3 * n]), axis=1)
        var = np.diagonal(jac @ np.asarray(c)[np.ix_(idx, idx)] @ jac.T)
        in_view += float(log_visibility_probability(sensor, range_bearing(m[:3], m[3 + 3 * n:6 + 3 * n]), jnp.asarray(var)))
    assert in_view < -0.1  # object 0 sits near the edge: the term matters
    assert screens[0.7] == pytest.approx(screens[2 * math.pi] + in_view, abs=1e-9)


def test_merge_keeps_the_mass_of_a_child_too_light_to_be_a_centre():
    """A child more than ``RELEVANT_NATS`` below the best (here 46 nats) becomes no centre, even with
    room for it (``K`` = 4), and is not smoothed; its mass joins the nearest centre, so the merged
    weights still sum to the children's. A dead child (-inf) is nobody's member."""
    import equinox as eqx
    import jax.numpy as jnp

    from hybridslam.estimators.base import RELEVANT_NATS, relevant_children
    from hybridslam.estimators.multimodal import cluster

    cluster = eqx.filter_jit(cluster)  # one program per call (op by op, each of its ops compiled alone)

    log_w = jnp.log(jnp.array([0.6, 0.4, 1e-20, 0.0]))
    mean = jnp.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [9.0, 0.0, 0.0], [5.0, 5.0, 0.0]])
    cov = jnp.broadcast_to(jnp.eye(3) * 0.01, (4, 3, 3))
    created = jnp.zeros(4, jnp.int32)
    ok = relevant_children(log_w)
    assert ok.tolist() == [True, True, False, False] and float(log_w[0] - log_w[2]) > RELEVANT_NATS
    centres, merged, wn = cluster(log_w, mean, cov, created, jnp.asarray(4.0), 4, ok)
    assert sorted(int(c) for c in centres[merged > -jnp.inf]) == [0, 1]
    owner = int(np.flatnonzero(np.asarray(centres) == 1)[0])
    assert float(wn[owner, 2]) > 0.0 and float(wn[1 - owner, 2]) == 0.0  # child 2 joined its nearest, child 1
    assert float(jnp.exp(jnp.logaddexp(merged[0], merged[1]))) == pytest.approx(1.0, rel=1e-12)
    assert np.all(np.asarray(wn)[:, 3] == 0.0)
    centres_all, merged_all, _ = cluster(log_w, mean, cov, created, jnp.asarray(4.0), 4)  # every live child may centre
    assert sorted(int(c) for c in centres_all[merged_all > -jnp.inf]) == [0, 1, 2]


def test_screening_over_the_candidates_rows_equals_screening_over_the_whole_map():
    """``localized_terms``: the beam's sequential screening (densities and rank-2 conditioning) on
    the pose and candidate rows only gives every partial assignment the same score as on the whole
    state, for every joint choice of 3 detections × (2 candidates + new) on a 10-object map."""
    import itertools

    import jax
    import jax.numpy as jnp

    from hybridslam.driver import inputs_from_scenario
    from hybridslam.estimators import multimodal as mm
    from hybridslam.estimators.smoothers import Filter
    from hybridslam.inference import gating, sequential

    rng = np.random.default_rng(5)
    scenario = _crowded([(2.0 + 0.1 * i, -0.9 + 0.2 * i, 0.0) for i in range(10)], max_objects=12)
    detections = jax.tree.map(lambda a: a[0], inputs_from_scenario(scenario, 3).detections)
    est = mm.Multimodal(capacity=2, samples=8, candidates=2, max_detections=3, max_steps=2, smoother=Filter())
    state = est.init(scenario)
    m, c = state.mean[0], state.cov[0]
    root = jnp.asarray(rng.normal(size=c.shape)) * 0.02
    c = c + root @ root.T  # correlate the pose and the objects
    # Jitted: one program for the terms and one per state layout for the scores (op by op, the 27
    # assignments' calls compiled some 450 small programs).
    @jax.jit
    def slot_terms(m, c):
        pred = gating.innovations(state.model.sensor, m, c, detections)
        cand = mm.gate(pred.d2, state.num_created[0], 2)
        terms = mm.slot_terms(state.model.sensor, state.params, pred, m, c, state.class_log_probs[0], cand, detections)
        return cand, terms, mm.localized_terms(terms)

    @jax.jit
    def score(t, cand, opts):
        objs, new, _ = mm.assignment_objects(opts[None], cand, detections.mask, state.num_created[0],
                                             state.config.max_objects, True)
        row = jax.tree.map(lambda a: a[0], sequential.start(1, t.cov.shape[0], 3, m.dtype))
        total = jnp.zeros((), m.dtype)
        for j in range(3):
            total += mm.slot_log_likelihood(t, row, jnp.asarray(j), opts[j], objs[0, j], new[0, j])
            row = mm.condition(t, detections.mask, row, opts, jnp.asarray(j))
        return total

    cand, terms, local = slot_terms(m, c)
    assert local.cov.shape[0] == 3 + 3 * cand.size < c.shape[0]
    for options in itertools.product(range(3), repeat=3):
        opts = jnp.asarray(options)
        scores = [float(score(t, cand, opts)) for t in (terms, local)]
        assert scores[1] == pytest.approx(scores[0], rel=1e-10, abs=1e-10), options


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(-math.pi, math.pi))
@example(0, math.pi - 0.05)
def test_spread_is_the_moment_match_about_the_anchor(seed, heading):
    """``spread``: ``anchor + shift`` is the members' weighted mean and ``scatter`` their weighted
    covariance about it (numpy, two passes), with headings averaged on the circle — members on both
    sides of ±π (around ``heading``) average near it, not near 0."""
    import jax.numpy as jnp

    from hybridslam.estimators.multimodal import spread

    rng = np.random.default_rng(seed)
    c, d = 5, 6
    mean = rng.normal(size=(c, d)) * 0.3
    mean[:, 2::3] += heading
    mean[:, 2::3] = (mean[:, 2::3] + math.pi) % (2 * math.pi) - math.pi
    wn = rng.dirichlet(np.ones(c), size=2)  # (K=2, C)
    anchor = mean[[0, 3]]
    shift, scatter = spread(jnp.asarray(wn), jnp.asarray(anchor), jnp.asarray(mean))
    for k in range(2):
        delta = mean - anchor[k]
        delta[:, 2::3] = (delta[:, 2::3] + math.pi) % (2 * math.pi) - math.pi  # offsets on the circle
        mu = wn[k] @ delta
        np.testing.assert_allclose(np.asarray(shift[k]), mu, atol=1e-12)
        dev = delta - mu
        np.testing.assert_allclose(np.asarray(scatter[k]), (wn[k][:, None] * dev).T @ dev, atol=1e-12)


def test_downdate_block_is_the_block_of_the_whole_downdate():
    """``update.downdate`` with ``idx`` (the weights' proposal, the clustering's pose blocks) is the
    ``[idx, idx]`` block of the child's whole covariance ``Σ − K (JΣ)``, symmetric."""
    import jax.numpy as jnp

    from hybridslam.inference.update import downdate

    rng = np.random.default_rng(0)
    a = rng.normal(size=(9, 9))
    parent = jnp.asarray(a @ a.T + 9 * np.eye(9))
    k, js = jnp.asarray(rng.normal(size=(9, 4)) * 0.1), jnp.asarray(rng.normal(size=(4, 9)) * 0.1)
    whole = np.asarray(downdate(parent, k, js))
    np.testing.assert_allclose(whole, 0.5 * ((parent - k @ js) + (parent - k @ js).T), atol=1e-12)
    idx = jnp.asarray([0, 1, 2, 6, 7, 8])
    np.testing.assert_allclose(np.asarray(downdate(parent, k, js, idx)), whole[np.ix_(idx, idx)], atol=1e-12)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.integers(-1, 3), st.integers(-1, 3)), min_size=1, max_size=12),
       st.lists(st.floats(-30.0, 5.0), min_size=12, max_size=12), st.integers(0, 11))
def test_tuple_shares_are_each_tuples_part_of_the_mass(rows, masses, dead):
    """Eq. 5.9: ``p_j`` is the mass of the children naming child j's object tuple over the total
    (brute force over the distinct tuples); zero-mass children get ``-inf``."""
    import jax
    import jax.numpy as jnp

    from hybridslam.estimators.multimodal import tuple_log_probs

    objects = np.asarray(rows, np.int32)
    log_mass = np.asarray(masses[: len(rows)])
    log_mass[dead % len(rows)] = -np.inf
    # Jitted: one program per number of rows (op by op, about 15 small ones each).
    got = np.asarray(jax.jit(tuple_log_probs)(jnp.asarray(objects), jnp.asarray(log_mass)))
    total = np.sum(np.exp(log_mass))
    for j, row in enumerate(rows):
        if log_mass[j] == -np.inf:
            assert got[j] == -np.inf
            continue
        same = np.sum([np.exp(m) for r, m in zip(rows, log_mass) if r == row])
        np.testing.assert_allclose(got[j], np.log(same / total), rtol=1e-12, atol=1e-12)


def test_many_detection_slots_over_many_objects_are_accepted():
    """No integer code of the association tuples bounds the slots: 16 slots over 32 objects
    ((N+1)^D ≈ 2e24, beyond int64) builds a state."""
    import hybridslam as hs

    objects = tuple((float(x), side * 2.5, 0.0) for x in range(2, 34, 2) for side in (1.0, -1.0))
    scenario = hs.simulate(0, steps=2, setup=hs.PaperSetup(object_poses=objects, max_detections=16, max_range=25.0))
    state = hs.make_estimator("multimodal", max_detections=16, smoother="filter").init(scenario)
    assert state.history.shape[-1] == 16


# A known map of two objects, three detection slots: one program for the runs of the step (the skip,
# clutter-free, and pose-belief tests; the clutter run is a structure of its own).
KNOWN = {"capacity": 2, "samples": 32, "max_detections": 3, "max_steps": 2, "smoother": "filter"}


def test_a_known_map_step_with_more_detections_than_objects_skips_the_fewest():
    """Three detections, two mapped objects, no discovery: no injective assignment names all three.
    The beam (the step's children in a run, ``Details``) and the exhaustive enumeration both keep only
    the assignments that leave exactly one detection unassociated (-1, counted in ``skipped``), the
    likeliest first, instead of losing the step."""
    import jax

    from hybridslam.driver import inputs_from_scenario
    from hybridslam.estimators.multimodal import Multimodal, association_log_probabilities
    from hybridslam.estimators.smoothers import Filter

    two = _two_objects_three_detections()
    run = run_estimator(two, "multimodal", **KNOWN)  # the beam (max_assignments 64), the pose-belief test's program
    assert int(run.infos[0].skipped) == 1
    details = run.infos[0].details
    detections = jax.tree.map(lambda a: a[0], inputs_from_scenario(two, 3).detections)
    est = Multimodal(capacity=2, samples=32, max_detections=3, max_steps=2, smoother=Filter(), max_assignments=None)
    ch = association_log_probabilities(est.init(two), detections, jax.random.key(0))
    for name, objects, score in (("beam", details.assoc_objects, details.assoc_log_probs),
                                 ("exhaustive", ch.objects, ch.log_weight)):
        live = np.asarray(score) > -np.inf
        objects = np.asarray(objects)[live]
        assert live.any() and np.all((objects < 0).sum(axis=1) == 1), (name, objects)
        assert np.all(np.sort(objects, axis=1)[:, 1:] >= 0)  # the other two name distinct objects
        assert objects[np.argmax(np.asarray(score)[live])].tolist() == [0, 1, -1], name


def _two_objects_three_detections():
    obj = _crowded().replace(discovery=None)
    return obj.replace(object_prior_means=obj.object_prior_means[:2], object_prior_covs=obj.object_prior_covs[:2],
                       class_prior=obj.class_prior[:2])


def test_a_known_maps_clutter_hypothesis_scores_the_null_choice_the_same_in_the_beam_and_the_enumeration():
    """With a clutter density the null choice of a known map is a scored hypothesis, not a skip: the
    beam (room for all 3³ rows) and the exhaustive enumeration keep the same children with the same
    Monte Carlo weights (common random numbers), and the likeliest names both objects and calls the
    third detection clutter."""
    import jax

    from hybridslam.driver import inputs_from_scenario
    from hybridslam.estimators.multimodal import Multimodal, association_log_probabilities
    from hybridslam.estimators.smoothers import Filter

    two = _two_objects_three_detections()
    detections = jax.tree.map(lambda a: a[0], inputs_from_scenario(two, 3).detections)
    got = {}
    for width in (64, None):
        est = Multimodal(capacity=2, samples=32, max_detections=3, max_steps=2, smoother=Filter(),
                         max_assignments=width, clutter=-4.0)
        ch = association_log_probabilities(est.init(two), detections, jax.random.key(0))
        live = np.asarray(ch.log_weight) > -np.inf
        got[width] = {tuple(o): w for o, w in zip(np.asarray(ch.objects)[live].tolist(), np.asarray(ch.log_weight)[live])}
    assert got[64].keys() == got[None].keys() and len(got[64]) > 1
    for objects, w in got[64].items():
        np.testing.assert_allclose(got[None][objects], w, rtol=1e-9)
    assert max(got[64], key=got[64].get) == (0, 1, -1)
    # Each clutter slot contributes the density once to the Monte Carlo likelihood: raising it by
    # 2 nats raises a child's log L_ij by 2 per detection it calls clutter.
    lik = {}
    for density in (-4.0, -2.0):
        est = Multimodal(capacity=2, samples=32, max_detections=3, max_steps=2, smoother=Filter(), clutter=density)
        ch = association_log_probabilities(est.init(two), detections, jax.random.key(0))
        live = np.asarray(ch.log_lik) > -np.inf
        lik[density] = {tuple(o): v for o, v in zip(np.asarray(ch.objects)[live].tolist(), np.asarray(ch.log_lik)[live])}
    common = lik[-4.0].keys() & lik[-2.0].keys()
    assert common
    for objects in common:
        np.testing.assert_allclose(lik[-2.0][objects] - lik[-4.0][objects], 2.0 * objects.count(-1), atol=1e-9)


def test_clutter_is_refused_on_an_unknown_map_and_counted_as_rejected_on_a_known_one():
    """A run of the three-detections step with ``clutter``: one detection explained as clutter
    (``rejected``, warned, ``-1`` in the result), none skipped; on an unknown map the option is
    refused with the reason."""
    import hybridslam as hs

    with pytest.raises(ValueError, match="--clutter is for a known map"):
        hs.make_estimator("multimodal", clutter=-4.0).init(_crowded())
    with pytest.raises(ValueError, match="Multimodal.clutter: expected a finite log density"):
        hs.make_estimator("multimodal", clutter=float("nan"))
    run = run_estimator(_two_objects_three_detections(), "multimodal", capacity=2, samples=32, max_detections=3,
                        max_steps=2, smoother="filter", clutter=-4.0)
    info = run.infos[0]
    assert int(info.rejected) == 1 and int(info.skipped) == 0
    assert any("clutter" in w for w in info.warnings())
    best = max(run.result.steps[0].components, key=lambda c: c.weight)
    assert sorted(best.associations[0]) == [-1, 0, 1]
    assert "clutter=-4" in hs.make_estimator("multimodal", clutter=-4.0).describe()


def test_a_pose_belief_that_contradicts_every_association_is_flagged():
    """A robot believed 1.5 m from where it is, with a tight prior (a kidnap): the best component
    can explain no detection (a known map without clutter: each is skipped or named far outside
    its prediction), and the step says so (``inconsistent``, warned); the true start is not
    flagged. The same for ``ml``."""
    import jax

    from hybridslam.estimators.base import summarize

    two = _two_objects_three_detections()
    tight = np.diag([1e-4, 1e-4, 1e-6])
    flags = {}
    for shift in (0.0, 1.5):
        scenario = two.replace(robot_prior_mean=np.asarray(two.robot_prior_mean) + [0.0, shift, 0.0],
                               robot_prior_cov=tight)
        run = run_estimator(scenario, "multimodal", **KNOWN)
        flags[shift] = bool(run.infos[0].inconsistent)
        if shift:
            assert any("contradicts the detections" in w for w in run.infos[0].warnings())
            assert "at 1 step(s)" in " ".join(summarize(jax.tree.map(lambda *a: np.stack(a), *run.infos)))
        # ml's associations pass its gate: there the detections it skips are the unexplained ones.
        flags[("ml", shift)] = bool(run_estimator(scenario, "ml", max_detections=3, max_steps=2,
                                                  smoother="filter").infos[0].inconsistent)
    assert flags == {0.0: False, 1.5: True, ("ml", 0.0): False, ("ml", 1.5): True}


def test_contradicted_counts_skipped_and_far_detections_against_half_the_step():
    """``gating.contradicted`` against ``d²`` computed here: a step is contradicted when more than
    half of its detections are skipped or named beyond the 1e-6 bound."""
    import jax
    import jax.numpy as jnp

    import hybridslam as hs
    from hybridslam.driver import inputs_from_scenario

    two = _two_objects_three_detections()
    state = hs.make_estimator("multimodal", smoother="filter", max_detections=3).init(two)
    det = _first(inputs_from_scenario(two, 3).detections)
    mean, cov, sensor = state.mean[0], state.cov[0], state.model.sensor
    # Jitted: one program each (op by op, every call's ops compiled one by one).
    mahalanobis, contradicted = jax.jit(gating.mahalanobis), jax.jit(gating.contradicted)
    for m in (mean, mean.at[1].add(3.0)):  # as believed, and 3 m to the side (every association far)
        c = cov if m is mean else cov * 1e-3
        d2 = np.asarray(mahalanobis(sensor, m, c, det))
        for objects in ([0, 1, -1], [1, 0, -1], [-1, -1, -1], [0, -1, 1], [1, -1, -1]):
            for skipped in (False, True):
                unassociated = np.array([o < 0 and skipped for o in objects])
                bad = sum((o >= 0 and d2[j, o] > gating.CONTRADICTION_D2) or unassociated[j] for j, o in enumerate(objects))
                got = contradicted(sensor, m, c, det, jnp.asarray(objects), jnp.asarray(unassociated))
                assert bool(got) == (2 * bad > 3), (objects, skipped)
    assert bool(contradicted(sensor, mean.at[1].add(3.0), cov * 1e-3, det, jnp.asarray([0, 1, -1]),
                             jnp.zeros(3, bool)))


def _first(tree):
    import jax

    return jax.tree.map(lambda a: a[0], tree)
