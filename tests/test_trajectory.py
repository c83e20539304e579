"""APE / RPE against evo on the same TUM files, closed-form cases, TUM round trip."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import metrics as evo_metrics
from evo.tools import file_interface

import hybridslam  # noqa: F401  (float64)
from hybridslam.analysis import trajectory as tj
from hybridslam.io.result import ComponentRecord, Result, StepRecord


def _random_trajectory(rng: np.random.Generator, n: int) -> np.ndarray:
    xy = np.cumsum(rng.normal(0.0, 1.0, (n, 2)), axis=0)
    theta = rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([xy, theta])


def _evo(ref_file, est_file, metric, relation):
    ref = file_interface.read_tum_trajectory_file(str(ref_file))
    est = file_interface.read_tum_trajectory_file(str(est_file))
    m = metric(relation)
    m.process_data((ref, est))
    return m.get_all_statistics()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ape_and_rpe_equal_evo_on_tum_files(tmp_path, seed):
    rng = np.random.default_rng(seed)
    n = 40
    ref = _random_trajectory(rng, n)
    # Estimates near the truth and far from it (rotation errors beyond ±pi/2 included).
    est = ref + rng.normal(0.0, [0.5, 0.5, 1.5], (n, 3))
    est[:, 2] = np.angle(np.exp(1j * est[:, 2]))
    stamps = np.arange(1, n + 1, dtype=float)
    tj.write_tum(tmp_path / "ref.txt", stamps, ref)
    tj.write_tum(tmp_path / "est.txt", stamps, est)
    _, ref_read = tj.read_tum(tmp_path / "ref.txt")
    _, est_read = tj.read_tum(tmp_path / "est.txt")

    ours = {
        ("APE", "t"): tj.ape(ref_read, est_read).statistics()["translation"],
        ("APE", "r"): tj.ape(ref_read, est_read).statistics()["rotation"],
        ("RPE", "t"): tj.rpe(ref_read, est_read).statistics()["translation"],
        ("RPE", "r"): tj.rpe(ref_read, est_read).statistics()["rotation"],
    }
    rel = evo_metrics.PoseRelation
    relations = {"t": rel.translation_part, "r": rel.rotation_angle_rad}
    classes = {"APE": evo_metrics.APE, "RPE": evo_metrics.RPE}
    for (metric, part), stats in ours.items():
        theirs = _evo(tmp_path / "ref.txt", tmp_path / "est.txt", classes[metric], relations[part])
        assert set(theirs) == set(tj.STATISTICS)
        for name in tj.STATISTICS:
            assert stats[name] == pytest.approx(theirs[name], abs=1e-9, rel=0), (metric, part, name)
    # The errors are not trivially small, so the comparison means something.
    assert ours[("APE", "r")]["max"] > 1.5 and ours[("RPE", "t")]["mean"] > 0.3


def test_rpe_with_delta_matches_evo(tmp_path):
    rng = np.random.default_rng(3)
    ref, est = _random_trajectory(rng, 23), _random_trajectory(rng, 23)
    stamps = np.arange(23, dtype=float)
    tj.write_tum(tmp_path / "ref.txt", stamps, ref)
    tj.write_tum(tmp_path / "est.txt", stamps, est)
    for relation, part in ((evo_metrics.PoseRelation.translation_part, "translation"),
                           (evo_metrics.PoseRelation.rotation_angle_rad, "rotation")):
        m = evo_metrics.RPE(relation, delta=3, delta_unit=evo_metrics.Unit.frames)
        m.process_data((file_interface.read_tum_trajectory_file(str(tmp_path / "ref.txt")),
                        file_interface.read_tum_trajectory_file(str(tmp_path / "est.txt"))))
        ours = getattr(tj.rpe(ref, est, delta=3), part)
        np.testing.assert_allclose(ours, m.error, atol=1e-9, rtol=0)


def test_constant_offsets_in_closed_form():
    rng = np.random.default_rng(4)
    ref = _random_trajectory(rng, 10)
    shifted = ref + np.array([0.3, -0.4, 0.0])  # world-frame translation: APE 0.5 everywhere, RPE 0
    s = tj.ape(ref, shifted).statistics()
    for name in ("max", "mean", "median", "min", "rmse"):
        assert s["translation"][name] == pytest.approx(0.5, abs=1e-12)
    assert s["translation"]["sse"] == pytest.approx(10 * 0.25, abs=1e-12)
    assert s["translation"]["std"] == pytest.approx(0.0, abs=1e-12)
    assert s["rotation"]["max"] == pytest.approx(0.0, abs=1e-12)
    assert tj.rpe(ref, shifted).statistics()["translation"]["max"] == pytest.approx(0.0, abs=1e-12)
    turned = ref.copy()
    turned[:, 2] = np.angle(np.exp(1j * (ref[:, 2] - 0.7)))  # heading offset: APE rotation 0.7, RPE 0
    assert tj.ape(ref, turned).rotation == pytest.approx(np.full(10, 0.7), abs=1e-12)
    assert tj.ape(ref, turned).translation == pytest.approx(np.zeros(10), abs=1e-12)
    assert tj.rpe(ref, turned).rotation == pytest.approx(np.zeros(9), abs=1e-12)
    assert tj.rpe(ref, turned).translation.max() > 0.1  # the same steps taken in a turned frame


def test_tum_round_trip_and_errors(tmp_path, unchecked_types):
    rng = np.random.default_rng(5)
    poses = _random_trajectory(rng, 7)
    stamps = np.linspace(0.5, 3.5, 7)
    tj.write_tum(tmp_path / "a.txt", stamps, poses)
    t, p = tj.read_tum(tmp_path / "a.txt")
    np.testing.assert_array_equal(t, stamps)
    np.testing.assert_allclose(p, poses, atol=1e-14, rtol=0)
    (tmp_path / "bad.txt").write_text("0 1 2 0.5 0 0 0 1\n")
    with pytest.raises(ValueError, match="bad.txt:1: not a planar pose"):
        tj.read_tum(tmp_path / "bad.txt")
    with pytest.raises(ValueError, match="estimate: 6 poses, but the reference has 7"):
        tj.ape(poses, poses[:6])


def test_trajectories_from_result_and_scenario():
    scenario = hybridslam.simulate(0, steps=3)
    comp = lambda w, x: ComponentRecord(w, [], [], np.array([x, 0.0, 0.0]), np.eye(3))  # noqa: E731
    steps = [StepRecord(k, [comp(0.7, float(k)), comp(0.3, -9.0)], {}) for k in (1, 2, 3)]
    t, est = tj.trajectory_from_result(Result("test", steps))
    np.testing.assert_array_equal(t, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(est[:, 0], [1.0, 2.0, 3.0])  # the first (highest-weight) component
    t, ref = tj.trajectory_from_scenario(scenario)
    np.testing.assert_array_equal(t, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(ref, scenario.true_robot_poses[1:])
    errs = tj.trajectory_errors(ref, est)
    assert set(errs) == {"ape_translation", "ape_rotation", "rpe_translation", "rpe_rotation"}


def test_error_summary_reports_online_and_smoothed_errors():
    scenario = hybridslam.simulate(0, steps=3)
    truth = np.asarray(scenario.true_robot_poses)
    comp = lambda x: ComponentRecord(1.0, [], [], x, np.eye(3))  # noqa: E731
    online = truth[1:] + np.array([0.3, 0.4, 0.0])  # every online pose 0.5 m off
    steps = [StepRecord(k, [comp(online[k - 1])], {}) for k in (1, 2, 3)]
    filtered = tj.error_summary(Result("test", steps), scenario)
    assert set(filtered) == {"ape_online", "rpe_online", "final"}
    np.testing.assert_allclose([filtered["ape_online"], filtered["final"], filtered["rpe_online"]], [0.5, 0.5, 0.0],
                               atol=1e-12)
    smoothed = truth.copy()
    smoothed[1:, 0] += 0.1  # the smoothed x_1..x_3 0.1 m off; x_0 is not scored
    out = tj.error_summary(Result("test", steps, trajectory=smoothed), scenario)
    np.testing.assert_allclose([out["ape_smoothed"], out["rpe_smoothed"]], [0.1, 0.0], atol=1e-12)
    t, poses = tj.smoothed_trajectory_from_result(Result("test", steps, trajectory=smoothed))
    np.testing.assert_array_equal(t, [1.0, 2.0, 3.0])
    assert tj.smoothed_trajectory_from_result(Result("test", steps)) is None
