"""The hallway simulator (thesis Sec. 5.4.1), its CLI subcommand and the trajectory plot."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import hybridslam  # noqa: F401  (float64)
from hybridslam import cli
from hybridslam.analysis.plot import plot_trajectory
from hybridslam.io.result import ComponentRecord, Result, StepRecord
from hybridslam.io.scenario import load_scenario, save_scenario
from hybridslam.models import geometry, se2
from hybridslam.sim.hallway import LEVELS, HallwaySetup, hallway, odometry_cov

TRACE = 0.03


@pytest.fixture(scope="module")
def long_run():
    """Twenty loops (1200 steps): enough odometry draws and detections for the statistics."""
    return hallway(7, TRACE, steps=20 * HallwaySetup().loop_steps)


def test_files_round_trip_for_both_maps(tmp_path):
    for known in (False, True):
        s = hallway(1, LEVELS[2], known_map=known)
        save_scenario(s, tmp_path / "s.json")
        assert load_scenario(tmp_path / "s.json") == s
    unknown, known = hallway(1, LEVELS[2]), hallway(1, LEVELS[2], known_map=True)
    n = len(unknown.true_objects)
    assert unknown.num_objects == 0 and unknown.discovery.max_objects == n + 10
    assert unknown.discovery.new_object_log_density == pytest.approx(-np.log(3.5 * 2 * np.pi / 3))
    assert known.num_objects == n and known.discovery is None
    np.testing.assert_allclose(known.object_prior_means[:, :2], known.true_object_poses[:, :2], atol=1.5)
    assert unknown.classifier.model == "confusion"
    np.testing.assert_allclose(unknown.classifier.matrix, [[0.9, 0.1], [0.1, 0.9]])
    assert (unknown.max_range, unknown.fov) == (3.5, pytest.approx(2.0944, abs=1e-4))
    np.testing.assert_allclose(unknown.geometric_cov, np.diag([0.01, 0.01]))
    assert set(c for _, c in unknown.true_objects) == {0, 1}


def test_odometry_noise_has_covariance_lambda(long_run):
    lam = odometry_cov(TRACE)
    assert np.trace(lam) == pytest.approx(TRACE) and lam[2, 2] == pytest.approx(0.1 * lam[0, 0])
    np.testing.assert_allclose(odometry_cov(0.021), np.diag([0.01, 0.01, 0.001]))  # the thesis's example
    poses = long_run.true_robot_poses
    u = np.stack([s.odometry for s in long_run.steps])
    true_rel = jax.vmap(se2.between)(poses[:-1], poses[1:])
    w = np.asarray(jax.vmap(lambda a, b: se2.log(se2.between(a, b)))(true_rel, u))  # Exp(w) = b⁻¹ u
    assert np.all(np.abs(np.mean(w, axis=0)) < 4 * np.sqrt(np.diag(lam) / len(w)))  # unbiased
    cov = np.cov(w.T)
    np.testing.assert_allclose(np.diag(cov), np.diag(lam), rtol=0.15)
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.max(np.abs(corr - np.eye(3))) < 0.15


def test_detections_are_exactly_the_landmarks_in_view(long_run):
    truth = np.stack([p for p, _ in long_run.true_objects])
    poses = long_run.true_robot_poses[1:]
    rb = np.asarray(jax.vmap(jax.vmap(geometry.range_bearing, (None, 0)), (0, None))(poses, truth))
    in_view = (rb[..., 0] <= 3.5) & (np.abs(rb[..., 1]) <= np.pi / 3)
    errors = []
    for k, step in enumerate(long_run.steps):
        seen = [d.true_object for d in step.detections]
        assert sorted(seen) == list(np.flatnonzero(in_view[k]))  # every landmark in view, and only those
        errors += [(d.range - rb[k, d.true_object, 0], se2.wrap(d.bearing - rb[k, d.true_object, 1]))
                   for d in step.detections]
    errors = np.asarray(errors, dtype=float)
    assert len(errors) > 2000
    np.testing.assert_allclose(np.var(errors, axis=0), [0.01, 0.01], rtol=0.1)


def test_labels_follow_the_90_percent_confusion_matrix(long_run):
    classes = np.array([c for _, c in long_run.true_objects])
    dets = [d for s in long_run.steps for d in s.detections]
    assert all(np.sum(d.scores) == 1.0 and set(d.scores) <= {0.0, 1.0} for d in dets)  # one-hot
    right = np.mean([np.argmax(d.scores) == classes[d.true_object] for d in dets])
    assert abs(right - 0.9) < 0.02  # ~3600 detections: sd 0.005


def test_the_track_closes_the_loop_and_seeds_reproduce():
    s = hallway(0, LEVELS[0])
    poses = s.true_robot_poses
    assert s.num_steps == 60
    np.testing.assert_allclose(poses[-1], poses[0], atol=1e-12)
    assert np.ptp(poses[:, 0]) == pytest.approx(20.0) and np.ptp(poses[:, 1]) == pytest.approx(10.0)
    # The start is seen again at the end: a loop closure.
    first = {d.true_object for d in s.steps[0].detections}
    last = {d.true_object for d in s.steps[-1].detections}
    assert last and last <= first
    assert hallway(0, LEVELS[0]) == s and hallway(1, LEVELS[0]) != s
    # Levels of one seed share their detections and scale the same odometry errors.
    t = hallway(0, LEVELS[4])
    assert all(a.detections == b.detections for a, b in zip(s.steps, t.steps))
    rel = jax.vmap(se2.between)(poses[:-1], poses[1:])
    noise = lambda sc: np.asarray(jax.vmap(lambda a, b: se2.log(se2.between(a, b)))(  # noqa: E731
        rel, np.stack([st.odometry for st in sc.steps])))
    np.testing.assert_allclose(noise(t), noise(s) * np.sqrt(LEVELS[4] / LEVELS[0]), rtol=1e-6, atol=1e-12)


def test_cli_writes_one_file_per_level_and_seed(tmp_path, capsys):
    out = tmp_path / "hw"
    args = ["hallway", "-o", str(out), "--levels", "0.005,0.05", "--seeds", "2", "--steps", "8"]
    assert cli.main(args) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"hallway_tr{v}_seed{s}.json" for v in ("0.0050", "0.0500") for s in (0, 1)]
    s = load_scenario(out / "hallway_tr0.0500_seed1.json")
    assert s.num_steps == 8 and np.trace(s.motion_cov) == pytest.approx(0.05)
    assert cli.main(["hallway", "-o", str(out), "--levels", "0,1"]) == 2
    assert "--levels: expected positive" in capsys.readouterr().err


def test_plot_trajectory_writes_a_png(tmp_path):
    s = hallway(0, LEVELS[1], steps=12)
    drift = s.true_robot_poses[1:] + np.array([0.1, -0.2, 0.0])
    steps = [StepRecord(k + 1, [ComponentRecord(1.0, [], [], drift[k], np.eye(3))], {}) for k in range(12)]
    path = tmp_path / "traj.png"
    estimated = (np.stack([p[:2] for p, _ in s.true_objects[:5]]) + 0.2, np.array([0, 1, -1, 0, 1]))
    plot_trajectory(path, s, Result("test", steps), "hallway", landmarks=estimated)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
