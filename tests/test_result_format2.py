"""Result format 2 (``hybridslam-result/2``): parents and each step's own associations, the last
step whole. Written and read back, every step's whole histories are those of format 1."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.io.result import (
    History,
    HistoryLinker,
    Result,
    ResultWriter,
    load_result,
    parse_result,
    result_to_json,
    save_result,
)
from hybridslam.io.scenario import ScenarioError

COV = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.02]]


def _component(weight: float, associations: list, parent=None) -> dict:
    return {"weight": weight, "associations": associations, "classes": [0, -1],
            "pose_mean": [1.0, 0.0, 0.0], "pose_cov": COV}


def _format1(histories: list[list[list[list[int]]]]) -> dict:
    """A format 1 result with ``histories[k-1]``, the whole histories of step k's components."""
    steps = []
    for k, step in enumerate(histories, start=1):
        n = len(step)
        weights = [1.0 / n] * n
        steps.append({"k": k, "components": [_component(w, h) for w, h in zip(weights, step)],
                      "metrics": {"entropy": float(np.log(n)), "det_cov": 0.01, "num_components": n}})
    return {"format": "hybridslam-result/1", "estimator": "test", "steps": steps}


@st.composite
def parent_trees(draw) -> list[list[list[list[int]]]]:
    """Histories of T steps: each component extends one of the previous step's (any of them, the
    same one for several, some not at all), or, now and then, has a past of its own (a loop closure
    rewrote it: no parent)."""
    lists = st.lists(st.integers(-1, 6), max_size=3)
    steps: list[list[list[list[int]]]] = []
    for k in range(1, draw(st.integers(1, 7)) + 1):
        step = []
        for _ in range(draw(st.integers(1, 4))):
            if k == 1 or draw(st.integers(0, 5)) == 0:
                step.append([draw(lists) for _ in range(k)])
            else:
                parent = steps[-1][draw(st.integers(0, len(steps[-1]) - 1))]
                step.append([list(a) for a in parent] + [draw(lists)])
        steps.append(step)
    return steps


@settings(max_examples=60, deadline=None, database=None)
@given(parent_trees())
def test_format_2_keeps_every_steps_whole_histories(tmp_path_factory, histories) -> None:
    """Random parent trees: written in format 2 and read back, every step's histories (and the rest
    of every record) are format 1's; and written in format 1 again, the file is the original."""
    folder = tmp_path_factory.mktemp("format2")
    original = _format1(histories)
    r = parse_result(copy.deepcopy(original))
    save_result(r, folder / "r2.json")
    text = json.loads((folder / "r2.json").read_text())
    assert text["format"] == "hybridslam-result/2"
    back = load_result(folder / "r2.json")
    assert back == r
    assert [[list(map(list, c.associations)) for c in s.components] for s in back.steps] == histories
    assert result_to_json(back, version=1) == original
    last = text["steps"][-1]["components"]
    assert all(len(c["associations"]) == len(histories) and "step_associations" not in c for c in last)
    for k, step in enumerate(text["steps"][1:-1], start=2):  # linked where a parent exists
        for c, h in zip(step["components"], histories[k - 1]):
            assert ("parent" in c) == (h[:-1] in histories[k - 2])
            assert ("step_associations" in c) == ("parent" in c)
    save_result(back, folder / "r1.json", version=1)
    assert json.loads((folder / "r1.json").read_text()) == original


def test_a_format_2_file_is_linear_in_the_run(tmp_path) -> None:
    """4 components, one detection a step: twice the steps, format 2's file about twice the size
    (format 1's nearly four times); the loaded histories share their parents' links."""
    histories = [[[[0]]] * 4]
    for k in range(2, 101):
        histories.append([histories[-1][i % 2] + [[k % 7]] for i in range(4)])
    sizes = {}
    for version in (1, 2):
        for steps in (50, 100):
            path = tmp_path / f"r{version}-{steps}.json"
            save_result(parse_result(_format1(histories[:steps])), path, version)
            sizes[version, steps] = path.stat().st_size
    assert sizes[2, 100] < 2.1 * sizes[2, 50] and sizes[1, 100] > 2.5 * sizes[1, 50], sizes
    back = load_result(tmp_path / "r2-100.json")
    step = back.steps[69].components[2]
    assert isinstance(step.associations, History) and step.parent == 0
    assert step.associations.parent is back.steps[68].components[0].associations
    assert back == parse_result(_format1(histories))


def test_history_reads_like_a_list() -> None:
    base = [[0], [1, 2]]
    h = History(History(base, [3]), [])
    plain = [[0], [1, 2], [3], []]
    assert len(h) == 4 and list(h) == plain and h == plain and plain == h
    assert [h[i] for i in range(-4, 4)] == plain + plain
    assert h[1:3] == plain[1:3] and h[::-1] == plain[::-1]
    assert h != [[0], [1, 2], [3], [4]] and h != plain[:3] and h != "abcd"
    with pytest.raises(IndexError):
        h[4]
    assert tuple(tuple(a) for a in h) == ((0,), (1, 2), (3,), ())  # a history as a dict key
    assert repr(h) == "History([[0], [1, 2], [3], []])"


def test_the_linker_keeps_links_and_finds_parents_by_content() -> None:
    r = parse_result(_format1([[[[0]], [[1]]], [[[1], [2]], [[0], [2]], [[5], [5]]], [[[0], [2], []]]]))
    link = HistoryLinker()
    linked = [link(s) for s in r.steps]
    assert [[c.parent for c in s.components] for s in linked] == [[None, None], [1, 0, None], [1]]
    again = HistoryLinker()
    relinked = [again(s) for s in linked]  # links kept: the same objects
    assert all(a.associations is b.associations for s, t in zip(linked, relinked)
               for a, b in zip(s.components, t.components))
    assert relinked == r.steps


def _format2() -> dict:
    """Three steps in format 2: step 2 linked, step 3 (the last) whole with its parent."""
    return {"format": "hybridslam-result/2", "estimator": "test", "steps": [
        {"k": 1, "components": [_component(0.5, [[0]]), _component(0.5, [[1]])],
         "metrics": {"entropy": 0.69, "det_cov": 0.01, "num_components": 2}},
        {"k": 2, "components": [{**_component(1.0, None), "parent": 1, "step_associations": [2]}],
         "metrics": {"entropy": 0.0, "det_cov": 0.01, "num_components": 1}},
        {"k": 3, "components": [{**_component(1.0, [[1], [2], []]), "parent": 0}],
         "metrics": {"entropy": 0.0, "det_cov": 0.01, "num_components": 1}},
    ]}


def _drop_none(obj: dict) -> dict:
    for s in obj["steps"]:
        for c in s["components"]:
            if c.get("associations", 0) is None:
                del c["associations"]
    return obj


def test_a_format_2_file_reads_as_format_1() -> None:
    r = parse_result(_drop_none(_format2()))
    assert [list(c.associations) for s in r.steps for c in s.components] == [[[0]], [[1]], [[1], [2]],
                                                                            [[1], [2], []]]
    assert [c.parent for s in r.steps for c in s.components] == [None, None, 1, 0]


def _c(k: int) -> tuple:
    return ("steps", k, "components", 0)


MALFORMED_2 = [
    ("parent_range", (*_c(1), "parent"), 2, "steps[1].components[0].parent: expected an integer in [0, 2), got 2"),
    ("parent_at_step_1", (*_c(0), "parent"), 0, "steps[0].components[0].parent: step 1 has no previous step"),
    ("no_parent", (*_c(1), "parent"), None,
     "steps[1].components[0].parent: missing (step_associations extends the parent's history)"),
    ("no_associations", (*_c(1), "step_associations"), None,
     "steps[1].components[0].associations: missing (or step_associations with parent)"),
    ("both", (*_c(1), "associations"), [[1], [2]],
     "steps[1].components[0].step_associations: given with associations (expected one of the two)"),
    ("step_association_value", (*_c(1), "step_associations"), [-2],
     "steps[1].components[0].step_associations[0]: expected an integer >= -1, got -2"),
    ("last_not_whole", (*_c(2), "associations"), None,
     "steps[2].components[0].associations: missing (the last step lists every component's whole history)"),
    ("last_not_its_parents", (*_c(2), "associations"), [[0], [2], []],
     ("steps[2].components[0].associations: its first 2 lists are not the history of its parent, "
      "steps[1].components[0]")),
    ("whole_length", (*_c(2), "associations"), [[1], [2]],
     "steps[2].components[0].associations: expected 3 lists (one per step so far), got 2"),
]


@pytest.mark.parametrize("path, value, message", [m[1:] for m in MALFORMED_2], ids=[m[0] for m in MALFORMED_2])
def test_malformed_format_2(path: tuple, value, message: str) -> None:
    obj = _format2()
    target = obj
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    with pytest.raises(ScenarioError) as e:
        parse_result(_drop_none(obj))
    assert str(e.value) == message


def test_unknown_version_is_refused(tmp_path) -> None:
    r = Result("x", [])
    with pytest.raises(ValueError, match="result format version 3"):
        save_result(r, tmp_path / "r.json", version=3)
    with pytest.raises(ValueError, match="result format version 3"):
        ResultWriter(tmp_path / "r.json", version=3)
    assert list(tmp_path.iterdir()) == []
    save_result(r, tmp_path / "r.json")
    assert load_result(tmp_path / "r.json") == r
