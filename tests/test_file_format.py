"""docs/file_format.md against the readers: the key tables of the documentation are the test's data.

Each key table (a Markdown table after a ``<!-- key-table: NAME -->`` marker) lists every key of the
scenario or result file, with a "required" column: ``yes``, ``no``, or the classifier models for
which the key is required (in backticks). For every required key, deleting it from a valid file
makes the reader raise a ``ScenarioError`` that names the key's field path; every optional key is
accepted when present and when absent; and the tables list every key the writers produce. Pure
numpy and JSON: no JAX compiles.
"""

from __future__ import annotations

import copy
import os
import re
from collections.abc import Iterator

import pytest

from hybridslam.io.result import parse_result
from hybridslam.io.scenario import ScenarioError, parse_scenario, scenario_to_json
from hybridslam.sim.paper import simulate

DOC = os.path.join(os.path.dirname(__file__), os.pardir, "docs", "file_format.md")

# The documented exception to "optional keys may be dropped one at a time" (docs/file_format.md,
# "Unknown maps"): with `discovery`, a detection's `true_object` indexes `true_objects`.
DEPENDENTS = {"scenario": {"true_objects": ["steps[].detections[].true_object"]}, "result": {}, "result-1": {}}


def key_table(name: str) -> dict[str, str]:
    """``{key path: required}`` from the table after ``<!-- key-table: name -->``."""
    with open(DOC, encoding="utf-8") as f:
        text = f.read()
    marker = f"<!-- key-table: {name} -->"
    assert text.count(marker) == 1, f"{marker} must appear exactly once in docs/file_format.md"
    rows = {}
    for line in text.split(marker, 1)[1].lstrip("\n").splitlines():
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        match = re.fullmatch(r"`([^`]+)`", cells[0])
        if match is None:  # the header and the separator row
            continue
        assert match[1] not in rows, f"{match[1]} listed twice"
        rows[match[1]] = cells[1]
    assert rows, f"no rows in the {name} key table"
    return rows


SCENARIO_KEYS = key_table("scenario")
RESULT_KEYS = key_table("result")  # format 2
RESULT_1_KEYS = key_table("result-1")


def models_of(required: str) -> list[str]:
    """The classifier models named in a "required" cell (empty for ``yes`` / ``no``)."""
    return re.findall(r"`([^`]+)`", required)


def kinds(table: dict[str, str]) -> None:
    for key, required in table.items():
        assert required in ("yes", "no", "conditional") or models_of(required), f"{key}: required = {required!r}"


# --------------------------------------------------------------------------- #
# Valid files holding every documented key
# --------------------------------------------------------------------------- #


def full_scenario(model: str = "mirror") -> dict:
    """A simulated 2-step scenario with every optional section (ground truth, discovery, clutter,
    detection probability)."""
    s = simulate(0, steps=2)
    obj = scenario_to_json(s)
    obj["true_objects"] = [{"pose": list(map(float, p)), "class": int(c)}
                           for p, c in zip(s.true_object_poses, s.true_classes)]
    obj["discovery"] = {"max_objects": s.num_objects + 4, "new_object_log_density": -4.0,
                        "new_object_orientation_var": 9.87}
    obj["sensor"]["clutter_log_density"] = -6.0
    obj["sensor"]["detection_probability"] = 0.95
    assert any(step["detections"] for step in obj["steps"])
    classifier = {"mirror": {"model": "mirror", "alpha": 0.25, "K": 15.0},
                  "independent": {"model": "independent", "alpha": 0.25, "K": 15.0},
                  "confusion": {"model": "confusion", "matrix": [[0.9, 0.2], [0.1, 0.8]]},
                  "learned": {"model": "learned", "path": "model.eqx"},  # opened only by models
                  "none": {"model": "none"}}
    obj["classifier"] = classifier[model]
    return obj


def full_result_1() -> dict:
    """A valid 2-step format 1 result with every optional key (timing, errors, smoother output)."""
    cov = [[0.1, 0.01, 0.0], [0.01, 0.1, 0.0], [0.0, 0.0, 0.02]]
    metrics = {"entropy": 0.56, "det_cov": 0.0099, "err_wmax": 0.1, "err_wavg": 0.12}
    return {
        "format": "hybridslam-result/1",
        "estimator": "test",
        "steps": [
            {"k": 1,
             "components": [
                 {"weight": 0.75, "associations": [[0]], "classes": [0, -1],
                  "pose_mean": [1.0, 0.0, 0.0], "pose_cov": cov},
                 {"weight": 0.25, "associations": [[1]], "classes": [-1, 1],
                  "pose_mean": [1.1, 0.0, 0.0], "pose_cov": cov}],
             "metrics": metrics | {"num_components": 2}},
            {"k": 2,
             "components": [
                 {"weight": 1.0, "associations": [[0], []], "classes": [0, -1],
                  "pose_mean": [2.0, 0.1, 0.05], "pose_cov": cov}],
             "metrics": metrics | {"num_components": 1}},
        ],
        "timing": {"compile_s": 3.2, "step_s": [0.012, 0.011]},
        "trajectory": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.1, 0.05]],
        "objects": [[4.0, 3.0, 0.6], [4.0, -3.0, -0.6]],
    }


def full_result() -> dict:
    """The format 1 file as format 2 with a step more: step 2 linked to its parent, step 3 (the
    last) whole, with its parent."""
    obj = full_result_1()
    obj["format"] = "hybridslam-result/2"
    step2 = obj["steps"][1]["components"][0]
    step2["parent"] = 0
    step2["step_associations"] = step2.pop("associations")[-1]
    step3 = {**step2, "parent": 0, "associations": [[0], [], [1]], "pose_mean": [3.0, 0.1, 0.05]}
    del step3["step_associations"]
    obj["steps"].append({"k": 3, "components": [step3], "metrics": dict(obj["steps"][1]["metrics"])})
    obj["timing"]["step_s"].append(0.01)
    obj["trajectory"].append([3.0, 0.1, 0.05])
    return obj


PARSE = {"scenario": parse_scenario, "result": parse_result, "result-1": parse_result}
TABLES = {"scenario": SCENARIO_KEYS, "result": RESULT_KEYS, "result-1": RESULT_1_KEYS}
KINDS = list(TABLES)


def full(kind: str, model: str = "mirror") -> dict:
    return {"scenario": full_scenario, "result": lambda _: full_result(),
            "result-1": lambda _: full_result_1()}[kind](model)


# --------------------------------------------------------------------------- #
# Paths: "steps[].detections[].scores" -> concrete places in a JSON object
# --------------------------------------------------------------------------- #


def places(obj, pattern: str, prefix: str = "") -> Iterator[tuple[str, dict, str]]:
    """Every ``(concrete path, holding dict, key)`` that ``pattern`` names in ``obj``, in order."""
    head, _, rest = pattern.partition(".")
    name, is_list = (head[:-2], True) if head.endswith("[]") else (head, False)
    if not isinstance(obj, dict) or name not in obj:
        return
    path = f"{prefix}.{name}" if prefix else name
    if not rest and not is_list:
        yield path, obj, name
        return
    if not is_list:
        yield from places(obj[name], rest, path)
        return
    assert rest, f"unsupported key pattern {pattern!r}"  # a list's elements are not deleted alone
    for i, item in enumerate(obj[name]):
        yield from places(item, rest, f"{path}[{i}]")


def pattern_of(path: str) -> str:
    return re.sub(r"\[\d+\]", "[]", path)


def delete(obj: dict, pattern: str, everywhere: bool = False) -> str:
    """Delete the first (or every) occurrence of ``pattern``; return the first concrete path."""
    found = list(places(obj, pattern))
    assert found, f"{pattern} does not occur in the test file"
    for _, parent, key in found if everywhere else found[:1]:
        del parent[key]
    return found[0][0]


def all_paths(obj, prefix: str = "") -> Iterator[str]:
    """Every key path in ``obj`` as a table pattern (lists of numbers are leaves)."""
    if isinstance(obj, dict):
        for key, value in obj.items():
            path = f"{prefix}.{key}" if prefix else key
            yield path
            yield from all_paths(value, path)
    elif isinstance(obj, list):
        for item in obj:
            if isinstance(item, dict):
                yield from all_paths(item, prefix + "[]")


# --------------------------------------------------------------------------- #
# Tests
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("kind", KINDS)
def test_tables_are_well_formed(kind: str) -> None:
    kinds(TABLES[kind])
    for key in TABLES[kind]:  # every nested key's parents are listed too
        parent = key.rsplit(".", 1)[0]
        assert parent == key or parent.removesuffix("[]") in TABLES[kind], f"{key}: parent not listed"


@pytest.mark.parametrize("kind", KINDS)
def test_full_files_parse_and_hold_every_documented_key(kind: str) -> None:
    for model in sorted({m for r in TABLES[kind].values() for m in models_of(r)} | {"mirror"}):
        obj = full(kind, model)
        PARSE[kind](copy.deepcopy(obj))
        present = set(all_paths(obj))
        for key, required in TABLES[kind].items():
            if required in ("yes", "no", "conditional") or model in models_of(required):
                assert key in present, f"{key} is documented but missing from the {model} test file"


def test_tables_cover_what_the_writers_write() -> None:
    written = set(all_paths(full_scenario())) - {"generator"}  # metadata: kept, not part of the format
    assert written <= set(SCENARIO_KEYS), sorted(written - set(SCENARIO_KEYS))
    assert set(all_paths(full_result())) <= set(RESULT_KEYS)
    assert set(all_paths(full_result_1())) <= set(RESULT_1_KEYS)


def required_cases(kind: str) -> list:
    cases = []
    for key, required in TABLES[kind].items():
        if required == "yes":
            cases.append(pytest.param(kind, key, "mirror", id=f"{kind}:{key}"))
        for model in models_of(required):
            cases.append(pytest.param(kind, key, model, id=f"{kind}:{key}[{model}]"))
    return cases


@pytest.mark.parametrize("kind, key, model", [c for kind in KINDS for c in required_cases(kind)])
def test_missing_required_key_is_named(kind: str, key: str, model: str) -> None:
    obj = full(kind, model)
    path = delete(obj, key)
    with pytest.raises(ScenarioError) as info:
        PARSE[kind](obj)
    assert info.value.path == path, str(info.value)
    assert str(info.value) == f"{path}: missing"


def optional_cases(kind: str) -> list:
    return [pytest.param(kind, key, id=f"{kind}:{key}")
            for key, required in TABLES[kind].items() if required == "no"]


@pytest.mark.parametrize("kind, key", [c for kind in KINDS for c in optional_cases(kind)])
def test_optional_key_present_or_absent(kind: str, key: str) -> None:
    obj = full(kind)
    assert any(places(obj, key)), f"{key} is not in the test file"
    PARSE[kind](copy.deepcopy(obj))  # present
    delete(obj, key, everywhere=True)
    for dependent in DEPENDENTS[kind].get(key, []):
        delete(obj, dependent, everywhere=True)
    PARSE[kind](copy.deepcopy(obj))  # absent
    if key.startswith("steps[].metrics."):
        return  # documented: every value in `metrics` must be a number, null included
    null = full(kind)  # null counts as absent
    for _, parent, name in places(null, key):
        parent[name] = None
    for dependent in DEPENDENTS[kind].get(key, []):
        delete(null, dependent, everywhere=True)
    PARSE[kind](null)


def test_optional_sections_all_absent() -> None:
    """The smallest valid files: every optional key removed at once."""
    for kind in KINDS:
        obj = full(kind)
        for key, required in sorted(TABLES[kind].items(), key=lambda kv: -kv[0].count(".")):
            if required == "no" and any(places(obj, key)):
                delete(obj, key, everywhere=True)
        PARSE[kind](obj)
        assert not any(pattern_of(p) in TABLES[kind] and TABLES[kind][pattern_of(p)] == "no"
                       for p in all_paths(obj))


def test_optional_keys_are_read() -> None:
    """The optional keys the reader keeps come back in the parsed object."""
    s = parse_scenario(full_scenario())
    assert s.true_robot_poses.shape == (3, 3) and s.true_object_poses.shape == (6, 3)
    assert s.discovery.max_objects == 10 and len(s.true_objects) == 6
    r = parse_result(full_result())
    assert r.timing == {"compile_s": 3.2, "step_s": [0.012, 0.011, 0.01]}
    assert set(r.steps[0].metrics) == {"entropy", "det_cov", "num_components", "err_wmax", "err_wavg"}


def test_clutter_association_is_accepted() -> None:
    obj = full_result_1()
    obj["steps"][0]["components"][0]["associations"] = [[-1]]
    parse_result(obj)
    obj = full_result()
    obj["steps"][1]["components"][0]["step_associations"] = [-1]
    obj["steps"][2]["components"][0]["associations"][1] = [-1]
    parse_result(obj)


def test_the_documented_result_example_parses_with_its_histories() -> None:
    """The format 2 example of "The result file": parents followed, step 2's histories are whole."""
    import json

    with open(DOC, encoding="utf-8") as f:
        text = f.read().split("## The result file", 1)[1]
    example = json.loads(text.split("```json", 1)[1].split("```", 1)[0])
    r = parse_result(example)
    assert [list(c.associations) for c in r.steps[1].components] == [[[0, 1], [0]], [[1, 0], [1]]]
    assert [c.parent for c in r.steps[2].components] == [0]
