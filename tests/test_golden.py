"""Behaviour is unchanged by restructuring: each case of ``tests/data/golden`` reruns to the same
result file, number for number (``timing`` aside; see ``tests/data/golden/README.md``)."""

from __future__ import annotations

import json
import os
import pathlib

import pytest

import hybridslam as hs
from hybridslam.driver import run_estimator
from hybridslam.io.result import result_to_json

GOLDEN = os.path.join(os.path.dirname(__file__), "data", "golden")
CASES = json.loads(pathlib.Path(GOLDEN, "cases.json").read_text(encoding="utf-8"))


@pytest.mark.parametrize("name", sorted(CASES))
def test_result_file_is_unchanged(name):
    case = CASES[name]
    scenario = hs.load_scenario(os.path.join(GOLDEN, case["scenario"] + ".json"))
    run = run_estimator(scenario, case["estimator"], seed=0, **case["settings"])
    got = json.loads(json.dumps(result_to_json(run.result)))
    got.pop("timing", None)
    with open(os.path.join(GOLDEN, name + ".result.json"), encoding="utf-8") as f:
        want = json.load(f)
    assert got["steps"] == want["steps"]
