"""The new-landmark rule (hybridslam.estimators.novelty): the option's parsing and errors, the rule's
primitives against brute force, and every estimator keeping it on a small hallway; and the recall
of the true loop closure among a result's components (hybridslam.analysis.recall)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.analysis.recall import closure_recall
from hybridslam.driver import run
from hybridslam.estimators import novelty
from hybridslam.estimators.registry import make_estimator
from hybridslam.io.result import ComponentRecord, Result, StepRecord
from hybridslam.sim.hallway import hallway

ESTIMATORS = ("ml", "gpda", "max-mixture", "multimodal", "hybrid")


@pytest.mark.parametrize("value, tau", [("density", None), ("mahalanobis:9.21", 9.21), ("mahalanobis:1e3", 1e3)])
def test_the_option_parses(value, tau):
    assert novelty.parse_new_landmark("X", value) == tau


@pytest.mark.parametrize("value", ["mahalanobis", "mahalanobis:", "mahalanobis:-1", "mahalanobis:0",
                                   "mahalanobis:inf", "mahalanobis:nan", "gate", 3.0, None])
def test_a_bad_option_names_the_setting(value):
    with pytest.raises(ValueError, match=r"X\.new_landmark"):
        novelty.parse_new_landmark("X", value)


@pytest.mark.parametrize("name", ESTIMATORS)
def test_every_estimator_takes_the_option_and_checks_it(name):
    est = make_estimator(name, new_landmark="mahalanobis:9.21")
    assert est.new_landmark == "mahalanobis:9.21" and "new_landmark=mahalanobis:9.21" in est.describe()
    assert make_estimator(name).new_landmark == "density"  # the default is unchanged
    with pytest.raises(ValueError, match="new_landmark"):
        make_estimator(name, new_landmark="mahalanobis:-2")


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 6), st.floats(0.1, 20.0))
def test_the_rules_primitives_against_brute_force(seed, created, tau):
    rng = np.random.default_rng(seed)
    d2 = rng.exponential(5.0, (3, 6))
    within = np.asarray(novelty.known_within(jnp.asarray(d2), jnp.asarray(created), jnp.asarray(tau)))
    np.testing.assert_array_equal(within, [(row[:created] <= tau).any() for row in d2])
    cand = np.argsort(d2, axis=1)[:, :3].astype(np.int32)
    cand[:, 2] = -1  # a rank with no object
    kept, near = (np.asarray(a) for a in novelty.restrict(jnp.asarray(cand), jnp.asarray(d2), jnp.asarray(tau)))
    for j in range(3):
        want = [c if c >= 0 and d2[j, c] <= tau else -1 for c in cand[j]]
        np.testing.assert_array_equal(kept[j], want)
        assert near[j] == any(c >= 0 for c in want)
    # τ = inf is the density rule (novelty.threshold): no candidate dropped, "new" never ruled out.
    density = novelty.threshold("X", "density")
    assert not np.any(np.asarray(novelty.known_within(jnp.asarray(d2), jnp.asarray(created), jnp.asarray(density))))
    kept, near = (np.asarray(a) for a in novelty.restrict(jnp.asarray(cand), jnp.asarray(d2), jnp.asarray(density)))
    np.testing.assert_array_equal(kept, cand)
    assert not near.any() and np.asarray(novelty.allowed(jnp.asarray(d2), density)).all()


@pytest.fixture(scope="module")
def short_hallway():
    return hallway(0, steps=4)  # 12 detections of 8 landmarks, an unknown map


def _objects(record: StepRecord) -> tuple[int, int]:
    """Distinct objects of a step record's top component, and its detections."""
    a = np.concatenate([np.asarray(x) for x in record.components[0].associations])
    return len(set(a[a >= 0].tolist())), len(a)


@pytest.mark.parametrize("name", [pytest.param(n, marks=() if n == "ml" else pytest.mark.slow) for n in ESTIMATORS])
def test_the_rule_decides_which_detections_are_new(name, short_hallway):
    """A tiny τ leaves no known object inside: ml, gpda, max-mixture and multimodal make every
    detection new (their candidates beyond τ are dropped); the hybrid belief, which keeps its
    candidates, may make fewer but never more than under "density". A huge τ puts every created object
    inside: no estimator makes more objects than under "density", and the hybrid belief makes only the
    first step's (every later detection is of a known object). Every rule and τ run one compiled step
    (τ is traced, inf under "density": ``AbstractEstimator.init_settings``)."""
    # The filter: the rule acts in the association step, the same code under every smoother, and the
    # filter's step compiles in a fraction of the full smoother's time.
    options = dict(capacity=8, gate=3, weights="linearized") if name == "hybrid" else (
        {"capacity": 4} if name == "multimodal" else {})
    options["smoother"] = "filter"
    count, compiles = {}, []
    for rule in ("density", "mahalanobis:1e-9", "mahalanobis:1e9"):
        result = run(make_estimator(name, new_landmark=rule, **options), short_hallway).result
        count[rule] = _objects(result.steps[-1])
        compiles.append(result.timing["compile_s"])
    assert compiles[1] == compiles[2] == 0.0, compiles  # the density rule's program, for every τ
    detections = count["density"][1]
    if name == "hybrid":
        assert count["mahalanobis:1e-9"][0] == count["density"][0]  # nothing inside τ: the density rule
        assert count["mahalanobis:1e9"][0] == len(short_hallway.steps[0].detections)
    else:
        assert count["mahalanobis:1e-9"][0] == detections
    assert count["mahalanobis:1e9"][0] <= count["density"][0]


def _truth_history(scenario, fresh_redetections: bool, gap: int = 20) -> list[list[int]]:
    """Associations from the truth (each landmark one object, numbered by first detection); with
    ``fresh_redetections`` a landmark re-detected more than ``gap`` steps later gets a new object."""
    slot: dict[int, int] = {}
    first: dict[int, int] = {}
    late: dict[int, int] = {}
    history = []
    for k, step in enumerate(scenario.steps, start=1):
        row = []
        for d in step.detections:
            t = d.true_object
            first.setdefault(t, k)
            if fresh_redetections and k - first[t] > gap:
                row.append(late.setdefault(t, 1000 + t))
            else:
                row.append(slot.setdefault(t, len(slot)))
        history.append(row)
    return history


def test_recall_finds_the_true_closure_below_the_top():
    scenario = hallway(3, steps=60)
    truth = np.asarray(scenario.true_robot_poses)[-1]
    right = ComponentRecord(0.3, _truth_history(scenario, False), [], truth + [0.3, 0.4, 0.0], np.eye(3))
    wrong = ComponentRecord(0.7, _truth_history(scenario, True), [], truth + [3.0, 4.0, 0.0], np.eye(3))
    steps = [StepRecord(k, [wrong, right], {}) for k in range(1, scenario.num_steps + 1)]
    rec = closure_recall(scenario, Result("test", steps))
    assert rec.redetections > 0 and rec.components == 2 and rec.top_closed == 0
    assert rec.holding == (1,) and rec.kept and not rec.top_right
    assert rec.top_error == pytest.approx(5.0) and rec.kept_error == pytest.approx(0.5) and rec.kept_weight == 0.3
    only_wrong = closure_recall(scenario, Result("test", [dataclasses.replace(s, components=[wrong]) for s in steps]))
    assert not only_wrong.kept and only_wrong.kept_error is None
    top = closure_recall(scenario, Result("test", [dataclasses.replace(s, components=[right, wrong]) for s in steps]))
    assert top.top_right and top.top_closed == top.redetections and top.kept_error == top.top_error


def test_recall_needs_ground_truth():
    scenario = hallway(3, steps=30)
    comp = ComponentRecord(1.0, _truth_history(scenario, False), [], np.zeros(3), np.eye(3))
    result = Result("test", [StepRecord(k, [comp], {}) for k in range(1, 31)])
    with pytest.raises(ValueError, match="robot.true_poses"):
        closure_recall(scenario.replace(true_robot_poses=None), result)
    with pytest.raises(ValueError, match="29 steps"):
        closure_recall(scenario, Result("test", result.steps[:-1]))


def test_the_command_line_takes_the_rule_and_names_a_bad_one(tmp_path, capsys):
    from hybridslam.cli import main
    from hybridslam.io.scenario import save_scenario

    save_scenario(hallway(0, steps=2), tmp_path / "s.json")
    argv = ["run", str(tmp_path / "s.json"), "-o", str(tmp_path / "r.json"), "--estimator", "ml"]
    assert main([*argv, "--new-landmark", "mahalanobis:-1"]) != 0
    assert "new_landmark" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()
