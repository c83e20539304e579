"""The benchmark scripts' own scenarios are what their docstrings say (the timings themselves are
printed by the scripts, never asserted)."""

import importlib.util
from pathlib import Path

import numpy as np

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


def _script(name):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_detections_benchmark_keeps_its_map_and_track_and_changes_the_detections_per_step():
    corridor = _script("bench_detections").corridor
    few, many = corridor(2), corridor(16)
    assert [len(s.detections) for s in few.steps] == [2] * 10
    assert [len(s.detections) for s in many.steps] == [16] * 10
    assert few.num_objects == many.num_objects == 32
    np.testing.assert_array_equal(few.true_robot_poses, many.true_robot_poses)
