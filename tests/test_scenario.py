"""Tests for hybridslam.scenario: parsing, validation messages, round trips, stacking."""

from __future__ import annotations

import copy
import json
import math
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.io.scenario import (
    Scenario,
    ScenarioError,
    load_scenario,
    parse_scenario,
    save_scenario,
    scenario_to_json,
    stack_steps,
)

I3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.1]]


def minimal() -> dict:
    """A small valid scenario: 2 objects, 2 classes, mirror, 2 steps (1 and 0 detections)."""
    return {
        "format": "hybridslam-scenario/1",
        "generator": {"name": "test", "seed": 3},
        "num_classes": 2,
        "objects": [
            {"prior_mean": [2.0, 1.0, 0.0], "prior_cov": I3, "true_pose": [2.1, 0.9, 0.1],
             "true_class": 0},
            {"prior_mean": [4.0, -1.0, 1.5], "prior_cov": I3, "true_pose": [4.0, -1.2, 1.4],
             "true_class": 1},
        ],
        "class_prior": [[0.5, 0.5], [0.3, 0.7]],
        "robot": {"prior_mean": [0.0, 0.0, 0.0], "prior_cov": I3,
                  "true_poses": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.1, 0.05]]},
        "motion_cov": [[0.01, 0.002, 0.0], [0.002, 0.01, 0.0], [0.0, 0.0, 0.001]],
        "geometric_cov": [[0.04, 0.0], [0.0, 0.01]],
        "classifier": {"model": "mirror", "alpha": 0.25, "K": 15.0},
        "sensor": {"max_range": 10.0, "fov": 2.0944},
        "steps": [
            {"odometry": [1.0, 0.0, 0.0],
             "detections": [{"range": 1.4, "bearing": 0.7, "scores": [0.8, 0.2],
                             "true_object": 0}]},
            {"odometry": [1.0, 0.1, 0.05], "detections": []},
        ],
    }


def test_parse_minimal() -> None:
    s = parse_scenario(minimal())
    assert (s.num_objects, s.num_classes, s.num_steps, s.max_detections) == (2, 2, 2, 1)
    assert s.object_prior_covs.shape == (2, 3, 3) and s.object_prior_covs.dtype == np.float64
    assert s.true_classes.tolist() == [0, 1]
    assert s.true_robot_poses.shape == (3, 3)
    assert s.classifier.model == "mirror" and s.classifier.K == 15.0
    assert s.steps[0].detections[0].true_object == 0
    assert s.metadata == {"generator": {"name": "test", "seed": 3}}
    assert s.discovery is None and s.true_objects is None


def test_round_trip() -> None:
    obj = minimal()
    s = parse_scenario(obj)
    assert scenario_to_json(s) == obj
    assert parse_scenario(scenario_to_json(s)) == s
    assert s != s.replace(fov=1.0)


def test_defaults_and_optional_truth() -> None:
    obj = minimal()
    del obj["class_prior"], obj["objects"][1]["true_pose"], obj["robot"]["true_poses"]
    obj["steps"][0]["detections"][0]["true_object"] = None  # null counts as absent
    s = parse_scenario(obj)
    assert np.array_equal(s.class_prior, np.full((2, 2), 0.5))
    assert s.true_object_poses is None and s.true_robot_poses is None
    assert s.true_classes is not None and s.steps[0].detections[0].true_object is None
    assert parse_scenario(scenario_to_json(s)) == s


def test_other_classifiers_and_discovery() -> None:
    obj = minimal()
    obj["num_classes"] = 3
    obj["class_prior"] = [[0.2, 0.3, 0.5]] * 2
    obj["classifier"] = {"model": "confusion",
                         "matrix": [[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]}
    obj["steps"][0]["detections"][0]["scores"] = [0.1, 0.2, 0.7]
    obj["discovery"] = {"max_objects": 5, "new_object_log_density": -4.0,
                        "new_object_orientation_var": 9.87}
    obj["true_objects"] = [{"pose": [1.0, 2.0, 0.0], "class": 2}]
    s = parse_scenario(obj)
    assert s.classifier.matrix.shape == (3, 3) and s.discovery.max_objects == 5
    assert s.true_objects[0][1] == 2
    assert parse_scenario(scenario_to_json(s)) == s
    obj["steps"][0]["detections"][0]["true_object"] = 1  # indexes true_objects now
    with pytest.raises(ScenarioError, match=r"^steps\[0\]\.detections\[0\]\.true_object: "):
        parse_scenario(obj)
    for model in ("none", "independent"):
        obj = minimal()
        obj["classifier"]["model"] = model
        assert parse_scenario(obj).classifier.model == model


def test_save_load(tmp_path) -> None:
    obj = minimal()
    obj["steps"][0]["odometry"][0] = 0.1 + 0.2  # not exactly representable in short form
    s = parse_scenario(obj)
    save_scenario(s, tmp_path / "s.json")
    assert load_scenario(tmp_path / "s.json") == s
    assert json.loads((tmp_path / "s.json").read_text()) == obj


def test_save_validates(tmp_path) -> None:
    s = parse_scenario(minimal())
    with pytest.raises(ScenarioError, match=r"^sensor\.fov: "):
        save_scenario(s.replace(fov=-1.0), tmp_path / "s.json")
    assert not (tmp_path / "s.json").exists()


def test_stack_steps() -> None:
    obj = minimal()
    obj["steps"].append({"odometry": [0.5, 0.0, 0.0], "detections": [
        {"range": 1.0, "bearing": 0.1, "scores": [0.4, 0.6]},
        {"range": 2.0, "bearing": -0.2, "scores": [0.3, 0.7], "true_object": 1}]})
    obj["robot"]["true_poses"].append([2.5, 0.1, 0.05])
    s = parse_scenario(obj)
    st_ = stack_steps(s)
    assert st_.odometry.shape == (3, 3)
    assert st_.geo.shape == (3, 2, 2) and st_.scores.shape == (3, 2, 2)
    assert st_.mask.tolist() == [[True, False], [False, False], [True, True]]
    assert st_.true_object.tolist() == [[0, -1], [-1, -1], [-1, 1]]
    assert st_.geo[2, 1].tolist() == [2.0, -0.2] and st_.scores[0, 0].tolist() == [0.8, 0.2]
    assert not st_.geo[~st_.mask].any() and not st_.scores[~st_.mask].any()
    assert stack_steps(s, max_detections=4).mask.shape == (3, 4)
    with pytest.raises(ScenarioError) as e:
        stack_steps(s, max_detections=1)
    assert e.value.path == "steps[2].detections"


def test_stack_steps_no_detections() -> None:
    obj = minimal()
    obj["steps"][0]["detections"] = []
    st_ = stack_steps(parse_scenario(obj))
    assert st_.geo.shape == (2, 1, 2) and not st_.mask.any()


def _set(path: tuple, value):
    def mutate(obj: dict) -> None:
        target = obj
        for key in path[:-1]:
            target = target[key]
        if value is _DELETE:
            del target[path[-1]]
        else:
            target[path[-1]] = value
    return mutate


_DELETE = object()
_NOT_SYM = [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
_NOT_PD = [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]

MALFORMED = [
    ("missing_key", _set(("objects", 1, "prior_cov"), _DELETE), "objects[1].prior_cov: missing"),
    ("missing_top", _set(("sensor",), _DELETE), "sensor: missing"),
    ("missing_alpha", _set(("classifier", "alpha"), _DELETE), "classifier.alpha: missing"),
    ("format", _set(("format",), "hybridslam-result/1"),
     "format: expected 'hybridslam-scenario/1', got 'hybridslam-result/1'"),
    ("root_type", lambda o: o.clear() or o.update(format=[1]), "format: expected a string, got list"),
    ("vector_length", _set(("robot", "prior_mean"), [0.0, 0.0]),
     "robot.prior_mean: expected 3 numbers, got 2"),
    ("matrix_shape", _set(("motion_cov",), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
     "motion_cov: expected a 3x3 matrix, got 2x3"),
    ("ragged_matrix", _set(("geometric_cov",), [[1.0, 0.0], [0.0]]),
     "geometric_cov[1]: expected 2 numbers, got 1"),
    ("nan", _set(("steps", 0, "odometry", 2), float("nan")),
     "steps[0].odometry[2]: not a finite number"),
    ("inf", _set(("sensor", "max_range"), float("inf")), "sensor.max_range: not a finite number"),
    ("not_symmetric", _set(("objects", 1, "prior_cov"), _NOT_SYM), "objects[1].prior_cov: not symmetric"),
    ("not_pd", _set(("robot", "prior_cov"), _NOT_PD), "robot.prior_cov: not positive definite"),
    ("scores_length", _set(("steps", 0, "detections", 0, "scores"), [0.1, 0.2, 0.7]),
     "steps[0].detections[0].scores: expected 2 numbers, got 3"),
    ("unknown_model", _set(("classifier", "model"), "foo"),
     "classifier.model: unknown model 'foo' (known: confusion, independent, learned, mirror, none)"),
    ("bool_number", _set(("steps", 0, "detections", 0, "range"), True),
     "steps[0].detections[0].range: expected a number, got boolean"),
    ("string_number", _set(("classifier", "K"), "15"), "classifier.K: expected a number, got string"),
    ("list_for_object", _set(("robot",), []), "robot: expected an object, got list"),
    ("negative_K", _set(("classifier", "K"), 0.0), "classifier.K: expected a positive number, got 0.0"),
    ("confusion_column",
     _set(("classifier",), {"model": "confusion", "matrix": [[0.9, 0.2], [0.2, 0.8]]}),
     "classifier.matrix: column 0 sums to 1.1, expected 1"),
    ("confusion_negative",
     _set(("classifier",), {"model": "confusion", "matrix": [[1.1, 0.0], [-0.1, 1.0]]}),
     "classifier.matrix[1][0]: negative probability -0.1"),
    ("true_poses_length", _set(("robot", "true_poses"), [[0.0, 0.0, 0.0]]),
     "robot.true_poses: expected 3 poses (x_0 and one per step), got 1"),
    ("fov_zero", _set(("sensor", "fov"), 0), "sensor.fov: expected a positive number, got 0.0"),
    ("class_prior_sum", _set(("class_prior", 1), [0.3, 0.6]), "class_prior[1]: sums to 0.9, expected 1"),
    ("class_prior_rows", _set(("class_prior",), [[0.5, 0.5]]),
     "class_prior: expected a 2x2 matrix, got 1x2"),
    ("true_class_range", _set(("objects", 0, "true_class"), 2),
     "objects[0].true_class: expected an integer in [0, 2), got 2"),
    ("true_object_float", _set(("steps", 0, "detections", 0, "true_object"), 1.5),
     "steps[0].detections[0].true_object: expected an integer, got 1.5"),
    ("negative_range", _set(("steps", 0, "detections", 0, "range"), -1.0),
     "steps[0].detections[0].range: expected a non-negative number, got -1.0"),
    ("num_classes", _set(("num_classes",), 0), "num_classes: expected an integer >= 1, got 0"),
    ("mirror_classes", lambda o: o.update(num_classes=3, class_prior=None),
     "classifier.model: 'mirror' needs num_classes == 2, got 3"),
    ("detections_type", _set(("steps", 1, "detections"), {}),
     "steps[1].detections: expected a list, got object"),
    ("max_objects", _set(("discovery",), {"max_objects": 1, "new_object_log_density": -4.0,
                                          "new_object_orientation_var": 1.0}),
     "discovery.max_objects: expected an integer >= 2, got 1"),
]


@pytest.mark.parametrize("mutate, message", [m[1:] for m in MALFORMED], ids=[m[0] for m in MALFORMED])
def test_malformed(mutate, message: str) -> None:
    obj = minimal()
    mutate(obj)
    with pytest.raises(ScenarioError) as e:
        parse_scenario(obj)
    path = message.split(": ")[0]
    assert e.value.path == path
    assert str(e.value) == message
    assert "\n" not in str(e.value)


def test_malformed_root() -> None:
    with pytest.raises(ScenarioError, match=r"^<root>: expected an object, got list$"):
        parse_scenario([])


def test_file_errors(tmp_path) -> None:
    with pytest.raises(ScenarioError, match=r"^<file>: cannot read") as e:
        load_scenario(tmp_path / "missing.json")
    assert e.value.path == "<file>"
    (tmp_path / "bad.json").write_text('{"format": ')
    with pytest.raises(ScenarioError, match=r"^<file>: .* is not valid JSON: "):
        load_scenario(tmp_path / "bad.json")
    # Python's json reads NaN literals; validation still names the field.
    text = json.dumps(minimal()).replace('"max_range": 10.0', '"max_range": NaN')
    (tmp_path / "nan.json").write_text(text)
    with pytest.raises(ScenarioError, match=r"^sensor\.max_range: not a finite number$"):
        load_scenario(tmp_path / "nan.json")


def test_error_pickles() -> None:
    e = pickle.loads(pickle.dumps(ScenarioError("a.b", "bad")))
    assert (e.path, str(e)) == ("a.b", "a.b: bad") and isinstance(e, ValueError)


# --------------------------------------------------------------------------- #
# Property test: random valid scenarios round-trip through JSON text.
# --------------------------------------------------------------------------- #

_finite = st.floats(-1e3, 1e3, allow_nan=False)


@st.composite
def _spd(draw, n: int) -> list:
    a = np.array(draw(st.lists(_finite, min_size=n * n, max_size=n * n))).reshape(n, n) / 1e3
    m = a @ a.T + np.diag(draw(st.lists(st.floats(0.1, 10.0), min_size=n, max_size=n)))
    return ((m + m.T) / 2).tolist()


@st.composite
def scenarios(draw) -> dict:
    M, N, T = draw(st.integers(1, 4)), draw(st.integers(0, 3)), draw(st.integers(0, 3))
    vec = lambda n: st.lists(_finite, min_size=n, max_size=n)  # noqa: E731
    prob = lambda: (lambda p: (p / p.sum()).tolist())(  # noqa: E731
        np.array(draw(st.lists(st.floats(0.01, 1.0), min_size=M, max_size=M))))
    obj = {
        "format": "hybridslam-scenario/1",
        "num_classes": M,
        "objects": [{"prior_mean": draw(vec(3)), "prior_cov": draw(_spd(3)),
                     "true_class": draw(st.integers(0, M - 1))} for _ in range(N)],
        "class_prior": [prob() for _ in range(N)],
        "robot": {"prior_mean": draw(vec(3)), "prior_cov": draw(_spd(3)),
                  "true_poses": [draw(vec(3)) for _ in range(T + 1)]},
        "motion_cov": draw(_spd(3)),
        "geometric_cov": draw(_spd(2)),
        "classifier": draw(st.sampled_from([
            {"model": "none"}, {"model": "confusion", "matrix": np.eye(M).tolist()}])),
        "sensor": {"max_range": draw(st.floats(0.1, 100.0)),
                   "fov": draw(st.floats(0.01, 2 * math.pi))},
        "steps": [{"odometry": draw(vec(3)), "detections": [
            {"range": draw(st.floats(0.0, 50.0)), "bearing": draw(st.floats(-3.0, 3.0)),
             "scores": draw(vec(M))} for _ in range(draw(st.integers(0, 3)))]}
            for _ in range(T)],
    }
    if draw(st.booleans()):
        obj["discovery"] = {"max_objects": N + draw(st.integers(0, 5)),
                            "new_object_log_density": draw(_finite),
                            "new_object_orientation_var": draw(st.floats(0.01, 10.0))}
    return obj


@settings(max_examples=20, deadline=None, database=None)
@given(scenarios())
def test_random_round_trip(obj: dict) -> None:
    s = parse_scenario(copy.deepcopy(obj))
    assert scenario_to_json(s) == obj
    again = parse_scenario(json.loads(json.dumps(scenario_to_json(s))))
    assert again == s and isinstance(again, Scenario)
    packed = stack_steps(s)
    assert packed.mask.sum() == sum(len(st_.detections) for st_ in s.steps)


def test_legal_corners_that_other_writers_produce() -> None:
    """Whole numbers written as floats in integer fields (2.0), and a field of view of 2π or more
    (every bearing in view): valid files, read as meant."""
    obj = minimal()
    obj["num_classes"] = 2.0
    obj["objects"][0]["true_class"] = 0.0
    obj["steps"][0]["detections"][0]["true_object"] = 0.0
    obj["sensor"]["fov"] = 7.0
    s = parse_scenario(obj)
    assert s.num_classes == 2 and isinstance(s.num_classes, int)
    assert s.steps[0].detections[0].true_object == 0 and s.fov == 7.0


def test_a_true_object_without_a_list_of_true_objects_says_what_is_missing() -> None:
    obj = minimal()
    obj["discovery"] = {"max_objects": 4, "new_object_log_density": -4.0, "new_object_orientation_var": 1.0}
    with pytest.raises(ScenarioError, match=r"^steps\[0\]\.detections\[0\]\.true_object: names a true object, "
                                            r"but the scenario lists none \(with discovery, the top-level "
                                            r"true_objects list holds them\)$"):
        parse_scenario(obj)
