"""scripts/isam2_baseline.py (GTSAM iSAM2 + nearest-neighbour association) writes valid result files.

Skipped without gtsam (a test-only dependency, like evo). The script lives in scripts/, so it is loaded
from its path.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import hybridslam as hs
from hybridslam.sim import hallway

from .scripts import load_script

pytest.importorskip("gtsam")

@pytest.fixture(scope="module")
def baseline():
    return load_script("scripts/isam2_baseline.py", "isam2_baseline")


def _run(baseline, tmp_path, scenario: hs.Scenario, *flags: str) -> tuple[hs.Result, dict]:
    src, out = tmp_path / "scenario.json", tmp_path / "result.json"
    hs.save_scenario(scenario, src)
    assert baseline.main([str(src), "-o", str(out), *flags]) == 0
    return hs.load_result(out), json.loads(out.read_text())


def _first_seen_order(scenario: hs.Scenario) -> list[list[int]]:
    """The associations of a perfect estimator on an unknown map: objects numbered as first detected."""
    index: dict[int, int] = {}
    return [[index.setdefault(d.true_object, len(index)) for d in s.detections] for s in scenario.steps]


def _check_file(result: hs.Result, raw: dict, scenario: hs.Scenario) -> None:
    assert len(result.steps) == scenario.num_steps
    last = result.steps[-1].components[0]
    assert [len(a) for a in last.associations] == [len(s.detections) for s in scenario.steps]
    for record in result.steps:
        (c,) = record.components
        assert c.weight == 1.0 and set(c.classes) <= {-1}
        assert max((o for a in c.associations for o in a), default=-1) < len(c.classes)
        assert np.all(np.linalg.eigvalsh(c.pose_cov) > 0)
        assert record.metrics["entropy"] == 0.0 and record.metrics["num_components"] == 1
        error = np.linalg.norm(c.pose_mean[:2] - scenario.true_robot_poses[record.k, :2])
        assert record.metrics["err_wmax"] == pytest.approx(error)
    assert np.shape(raw["trajectory"]) == (scenario.num_steps + 1, 3)
    assert np.shape(raw["objects"]) == (len(last.classes), 3)
    assert len(result.timing["step_s"]) == scenario.num_steps


def test_paper_setup_known_map(baseline, tmp_path) -> None:
    scenario = hs.simulate(0, steps=3)
    result, raw = _run(baseline, tmp_path, scenario)
    _check_file(result, raw, scenario)
    assert len(result.steps[-1].components[0].classes) == scenario.num_objects  # no new objects
    result, _ = _run(baseline, tmp_path, scenario, "--true-associations")
    truth = [[d.true_object for d in s.detections] for s in scenario.steps]
    assert result.steps[-1].components[0].associations == truth
    # A gate that nothing passes: on a known map every detection is dropped (-1), none is a new object.
    result, raw = _run(baseline, tmp_path, scenario, "--gate", "1e-9")
    _check_file(result, raw, scenario)
    assert result.steps[-1].components[0].associations == [[-1] * len(a) for a in truth]


def test_hallway_unknown_map(baseline, tmp_path) -> None:
    scenario = hallway.hallway(0, hallway.LEVELS[0], steps=6)
    truth = _first_seen_order(scenario)
    result, raw = _run(baseline, tmp_path, scenario, "--true-associations")
    _check_file(result, raw, scenario)
    assert result.steps[-1].components[0].associations == truth
    assert len(result.steps[-1].components[0].classes) == len({o for a in truth for o in a})
    # Six steps at the lowest odometry noise: nearest-neighbour gating finds the same associations.
    result, raw = _run(baseline, tmp_path, scenario, "--batch")
    _check_file(result, raw, scenario)
    assert result.steps[-1].components[0].associations == truth


def test_given_associations_give_the_batch_solution_an_incremental_run_ends_at(baseline, tmp_path) -> None:
    """``--associations-from RESULT --batch``: GTSAM's batch Levenberg-Marquardt of another
    estimator's final graph. ``ml`` under ``incremental:3`` on a 20-step hallway (unknown map: the
    objects the run created are created here where the associations first name them) ends at that
    solution; under ``lag:3`` its old poses stay where they left the window, tenths of a metre away."""
    from hybridslam.estimators.smoothers import Incremental, Lag

    scenario = hallway.hallway(0, 0.05, steps=20)
    src = tmp_path / "scenario.json"
    hs.save_scenario(scenario, src)
    distances = []
    for smoother in (Incremental(3), Lag(3)):
        run = hs.run_estimator(scenario, "ml", smoother=smoother)
        hs.save_result(run.result, tmp_path / "ml.json")
        out = tmp_path / "gtsam.json"
        assert baseline.main([str(src), "-o", str(out), "--associations-from", str(tmp_path / "ml.json"),
                              "--batch"]) == 0
        gtsam = hs.load_result(out)
        assert gtsam.steps[-1].components[0].associations == run.result.steps[-1].components[0].associations
        batch = np.asarray(json.loads(out.read_text())["trajectory"])
        distances.append(np.max(np.linalg.norm(batch[:, :2] - np.asarray(run.result.trajectory)[:, :2], axis=1)))
    assert distances[0] < 1e-3 < 0.1 < distances[1], distances
