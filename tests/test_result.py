"""Tests for hybridslam.result: parsing, validation messages, round trips."""

from __future__ import annotations

import copy
import dataclasses
import json

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.io.result import (
    ComponentRecord,
    Result,
    StepRecord,
    load_result,
    parse_result,
    result_to_json,
    save_result,
)
from hybridslam.io.scenario import ScenarioError

COV = [[0.1, 0.01, 0.0], [0.01, 0.1, 0.0], [0.0, 0.0, 0.02]]


def minimal() -> dict:
    """A small valid result: 2 steps, with 2 and 1 components."""
    return {
        "format": "hybridslam-result/1",
        "estimator": "test 0.1",
        "steps": [
            {"k": 1,
             "components": [
                 {"weight": 0.75, "associations": [[0]], "classes": [0, -1],
                  "pose_mean": [1.0, 0.0, 0.0], "pose_cov": COV},
                 {"weight": 0.25, "associations": [[1]], "classes": [-1, 1],
                  "pose_mean": [1.1, 0.0, 0.0], "pose_cov": COV}],
             "metrics": {"entropy": 0.56, "det_cov": 0.0099, "num_components": 2,
                         "err_wmax": 0.1, "err_wavg": 0.12}},
            {"k": 2,
             "components": [
                 {"weight": 1.0, "associations": [[0], []], "classes": [0, -1],
                  "pose_mean": [2.0, 0.1, 0.05], "pose_cov": COV}],
             "metrics": {"entropy": 0.0, "det_cov": 0.0099, "num_components": 1}},
        ],
        "timing": {"compile_s": 3.2, "step_s": [0.012, 0.011]},
    }


def test_parse_and_round_trip() -> None:
    obj = minimal()
    r = parse_result(obj)
    assert r.estimator == "test 0.1" and [s.k for s in r.steps] == [1, 2]
    c = r.steps[0].components[1]
    assert c.weight == 0.25 and c.associations == [[1]] and c.classes == [-1, 1]
    assert c.pose_cov.shape == (3, 3) and c.pose_mean.dtype == np.float64
    assert r.steps[1].metrics == {"entropy": 0.0, "det_cov": 0.0099, "num_components": 1}
    assert r.timing == {"compile_s": 3.2, "step_s": [0.012, 0.011]}
    assert result_to_json(r, version=1) == obj
    assert parse_result(result_to_json(r)) == r and parse_result(result_to_json(r, version=1)) == r
    del obj["timing"]
    assert parse_result(obj).timing is None and "timing" not in result_to_json(parse_result(obj))


def test_save_load(tmp_path) -> None:
    r = parse_result(minimal())
    save_result(r, tmp_path / "r.json")
    assert load_result(tmp_path / "r.json") == r


def test_save_from_numpy_values(tmp_path) -> None:
    """Estimators hand over numpy scalars and arrays; the file holds plain JSON."""
    comp = ComponentRecord(np.float32(1.0), [np.array([0, 1])], list(np.array([0, 1])),
                           np.zeros(3, np.float32), np.eye(3))
    r = Result("np", [StepRecord(1, [comp], {"entropy": np.float64(0.0), "det_cov": 1.0,
                                             "num_components": np.int64(1)})],
               {"compile_s": 0.5, "step_s": np.array([0.01])})
    save_result(r, tmp_path / "r.json")
    back = load_result(tmp_path / "r.json")
    assert back.steps[0].components[0].associations == [[0, 1]]
    assert back.steps[0].metrics["num_components"] == 1


def test_a_negative_zero_metric_is_written_as_zero(tmp_path) -> None:
    """One hypothesis: entropy 0, which jit may compute as -0.0; the file says 0.0 (text-equal to
    other implementations' files)."""
    r = parse_result(minimal())
    r.steps[1].metrics["entropy"] = np.float64(-0.0)
    save_result(r, tmp_path / "r.json")
    assert '"entropy": -0.0' not in (tmp_path / "r.json").read_text()
    assert math.copysign(1.0, load_result(tmp_path / "r.json").steps[1].metrics["entropy"]) == 1.0


def test_save_validates(tmp_path) -> None:
    r = parse_result(minimal())
    r.steps[0].components.reverse()
    with pytest.raises(ScenarioError) as e:
        save_result(r, tmp_path / "r.json")
    assert e.value.path == "steps[0].components[1].weight"
    assert not (tmp_path / "r.json").exists()


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
C0 = ("steps", 0, "components", 0)

MALFORMED = [
    ("format", _set(("format",), "hybridslam-scenario/1"),
     "format: expected 'hybridslam-result/1' or 'hybridslam-result/2', got 'hybridslam-scenario/1'"),
    ("missing_estimator", _set(("estimator",), _DELETE), "estimator: missing"),
    ("k_order", _set(("steps", 1, "k"), 3), "steps[1].k: expected 2 (steps in order from 1), got 3"),
    ("weight_range", _set((*C0, "weight"), 1.5),
     "steps[0].components[0].weight: expected a number in (0, 1], got 1.5"),
    ("weight_zero", _set(("steps", 0, "components", 1, "weight"), 0.0),
     "steps[0].components[1].weight: expected a number in (0, 1], got 0.0"),
    ("weight_sum", _set((*C0, "weight"), 0.7), "steps[0].components: weights sum to 0.95, expected 1"),
    ("weight_order", _set(("steps", 0, "components", 1, "weight"), 0.8),
     "steps[0].components[1].weight: 0.8 exceeds the previous weight 0.75 "
     "(components must be sorted by weight, highest first)"),
    ("weight_bool", _set((*C0, "weight"), True),
     "steps[0].components[0].weight: expected a number, got boolean"),
    ("no_components", _set(("steps", 1, "components"), []),
     "steps[1].components: empty (weights must sum to 1)"),
    ("associations_length", _set((*C0, "associations"), [[0], [1]]),
     "steps[0].components[0].associations: expected 1 lists (one per step so far), got 2"),
    ("association_below_clutter", _set((*C0, "associations", 0, 0), -2),
     "steps[0].components[0].associations[0][0]: expected an integer >= -1, got -2"),
    ("class_value", _set((*C0, "classes", 1), -2),
     "steps[0].components[0].classes[1]: expected an integer >= -1, got -2"),
    ("pose_mean_length", _set((*C0, "pose_mean"), [0.0, 0.0]),
     "steps[0].components[0].pose_mean: expected 3 numbers, got 2"),
    ("pose_cov_symmetric", _set((*C0, "pose_cov"), [[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
     "steps[0].components[0].pose_cov: not symmetric"),
    ("pose_cov_shape", _set((*C0, "pose_cov"), [[1.0, 0.0], [0.0, 1.0]]),
     "steps[0].components[0].pose_cov: expected a 3x3 matrix, got 2x2"),
    ("nan", _set((*C0, "pose_mean", 1), float("nan")),
     "steps[0].components[0].pose_mean[1]: not a finite number"),
    ("missing_metric", _set(("steps", 1, "metrics", "entropy"), _DELETE),
     "steps[1].metrics.entropy: missing"),
    ("metric_inf", _set(("steps", 0, "metrics", "err_wavg"), float("inf")),
     "steps[0].metrics.err_wavg: not a finite number"),
    ("num_components", _set(("steps", 0, "metrics", "num_components"), 3),
     "steps[0].metrics.num_components: 3, but the step has 2 components"),
    ("timing_length", _set(("timing", "step_s"), [0.1]), "timing.step_s: expected 2 numbers, got 1"),
    ("timing_type", _set(("timing",), [3.2]), "timing: expected an object, got list"),
]


@pytest.mark.parametrize("mutate, message", [m[1:] for m in MALFORMED], ids=[m[0] for m in MALFORMED])
def test_malformed(mutate, message: str) -> None:
    obj = minimal()
    mutate(obj)
    with pytest.raises(ScenarioError) as e:
        parse_result(obj)
    assert e.value.path == message.split(": ")[0]
    assert str(e.value) == message


def test_file_errors(tmp_path) -> None:
    with pytest.raises(ScenarioError, match=r"^<file>: cannot read"):
        load_result(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("[1, 2")
    with pytest.raises(ScenarioError, match=r"^<file>: .* is not valid JSON: "):
        load_result(tmp_path / "bad.json")


@st.composite
def results(draw) -> dict:
    T = draw(st.integers(0, 4))
    steps = []
    for k in range(1, T + 1):
        raw = draw(st.lists(st.floats(0.01, 1.0), min_size=1, max_size=4))
        weights = sorted((w / sum(raw) for w in raw), reverse=True)
        comps = [{"weight": w,
                  "associations": [draw(st.lists(st.integers(0, 5), max_size=2)) for _ in range(k)],
                  "classes": draw(st.lists(st.integers(-1, 2), max_size=6)),
                  "pose_mean": draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3)),
                  "pose_cov": np.diag(draw(st.lists(st.floats(0.0, 5.0), min_size=3,
                                                    max_size=3))).tolist()}
                 for w in weights]
        metrics = {"entropy": float(-sum(w * np.log(w) for w in weights)),
                   "det_cov": draw(st.floats(0.0, 1.0)), "num_components": len(comps)}
        steps.append({"k": k, "components": comps, "metrics": metrics})
    timing = {"compile_s": draw(st.floats(0.0, 10.0)),
              "step_s": draw(st.lists(st.floats(0.0, 1.0), min_size=T, max_size=T))}
    return {"format": "hybridslam-result/1", "estimator": draw(st.text(max_size=10)),
            "steps": steps, "timing": timing}


@settings(max_examples=20, deadline=None, database=None)
@given(results())
def test_random_round_trip(obj: dict) -> None:
    r = parse_result(copy.deepcopy(obj))
    assert result_to_json(r, version=1) == obj
    for version in (1, 2):
        assert parse_result(json.loads(json.dumps(result_to_json(r, version)))) == r


def test_unassociated_detection_is_minus_one() -> None:
    """An association index of -1 marks a detection the component left unassociated (clutter)."""
    obj = minimal()
    obj["steps"][1]["components"][0]["associations"] = [[-1], []]
    r = parse_result(obj)
    assert r.steps[1].components[0].associations == [[-1], []]
    assert result_to_json(r, version=1) == obj


_scalars = st.none() | st.booleans() | st.integers(-50, 50) | st.floats(-1e3, 1e3) | st.text("ab],[ {\"", max_size=4)
_json_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=5)
                            | st.dictionaries(st.text("kx", max_size=3), inner, max_size=4), max_leaves=30)


@settings(max_examples=200, deadline=None, database=None)
@given(_json_values, st.integers(8, 40), st.integers(0, 3))
def test_the_writers_text_is_the_same_json_and_long_lists_one_item_per_line(obj, width: int, indent: int) -> None:
    from hybridslam.io.jsonfields import dumps

    got = dumps(obj, indent, width)
    assert json.loads(got) == json.loads(json.dumps(obj))
    nested = isinstance(obj, list) and any(isinstance(x, (dict, list)) for x in obj)
    if nested and len(json.dumps(obj)) + indent > width:  # one line per item, each item on one line
        assert got.splitlines()[1:-1] == [" " * (indent + 1) + json.dumps(x) + ("," if i < len(obj) - 1 else "")
                                          for i, x in enumerate(obj)]


@pytest.mark.parametrize("bad, path, message", [
    ([[0], [True]], "[1][0]", "expected an integer, got boolean"),
    ([[0], ["1"]], "[1][0]", "expected an integer, got string"),
    ([[0], [1.5]], "[1][0]", "expected an integer, got 1.5"),
    ([[0], [0, -3]], "[1][1]", "expected an integer >= -1, got -3"),
    ([[0], 4], "[1]", "expected a list, got number"),
])
def test_association_errors_name_the_entry(bad, path: str, message: str) -> None:
    obj = minimal()
    obj["steps"][1]["components"][0]["associations"] = bad
    with pytest.raises(ScenarioError) as e:
        parse_result(obj)
    assert str(e.value) == f"steps[1].components[0].associations{path}: {message}"


def test_whole_number_floats_still_count_as_associations_and_bools_not_as_numbers() -> None:
    obj = minimal()
    obj["steps"][1]["components"][0]["associations"] = [[1.0], [0]]
    assert parse_result(obj).steps[1].components[0].associations == [[1], [0]]
    obj["steps"][1]["components"][0]["pose_mean"] = [1.0, True, 0.0]
    with pytest.raises(ScenarioError, match=r"pose_mean\[1\]: expected a number, got boolean"):
        parse_result(obj)


def test_a_huge_integer_is_named_not_a_traceback_and_records_do_not_share_the_callers_lists() -> None:
    obj = minimal()
    obj["steps"][0]["components"][0]["pose_mean"] = [1.0, 10**400, 0.0]
    with pytest.raises(ScenarioError, match=r"components\[0\]\.pose_mean\[1\]: not a finite number"):
        parse_result(obj)
    obj = minimal()
    r = parse_result(obj)
    obj["steps"][1]["components"][0]["associations"][0].append(1)
    obj["steps"][1]["components"][0]["classes"][0] = 1
    assert r == parse_result(minimal())


@pytest.mark.parametrize("version", [1, 2])
def test_the_result_writer_checks_each_step_and_writes_nothing_on_an_error(tmp_path, version: int) -> None:
    from hybridslam.io.result import ResultWriter

    r = parse_result(minimal())
    with ResultWriter(tmp_path / "r.json", version) as writer:
        for step in r.steps:
            writer.add(step)
        assert len(writer) == 2 and not (tmp_path / "r.json").exists()  # nothing at the path before finish
        writer.finish(r)
    assert load_result(tmp_path / "r.json") == r
    assert json.loads((tmp_path / "r.json").read_text()) == result_to_json(r, version)
    save_result(r, tmp_path / "s.json", version)

    with pytest.raises(ScenarioError, match=r"^steps\[0\]\.k: expected 1"):
        with ResultWriter(tmp_path / "bad.json", version) as writer:
            writer.add(r.steps[1])
    with pytest.raises(ScenarioError, match=r"^timing\.step_s: expected 2 numbers, got 1"):
        with ResultWriter(tmp_path / "bad.json", version) as writer:
            for step in r.steps:
                writer.add(step)
            writer.finish(dataclasses.replace(r, timing={"compile_s": 1.0, "step_s": [0.1]}))
    with ResultWriter(tmp_path / "bad.json", version) as writer:  # left without finish: nothing written
        writer.add(r.steps[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json", "s.json"]


def test_tied_weights_may_rise_by_their_last_bits() -> None:
    """Tied components stand in index order (hybridslam.inference.ties), so a tie's weight may
    exceed the previous one in its last bits; a real inversion is still refused."""
    obj = minimal()
    comps = obj["steps"][0]["components"]
    comps[0]["weight"], comps[1]["weight"] = 0.5 - 1e-16, 0.5 + 1e-16
    assert len(parse_result(obj).steps[0].components) == 2
    comps[0]["weight"], comps[1]["weight"] = 0.5 - 1e-6, 0.5 + 1e-6
    with pytest.raises(ScenarioError, match="exceeds the previous weight"):
        parse_result(obj)
