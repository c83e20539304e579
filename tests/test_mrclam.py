"""Tests of the MRCLAM importer (``hybridslam.datasets.mrclam``) and ``hybridslam import mrclam``.

Real data: ``tests/data/mrclam`` is a 45 s excerpt of dataset 7, robot 1 (its README). Pure numpy,
no JAX compiles; the whole file runs in a few seconds.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import shutil

import numpy as np
import pytest

import hybridslam as hs
from hybridslam import cli
from hybridslam.datasets import mrclam, mrclam_calibration, mrclam_detections, mrclam_files, mrclam_track
from hybridslam.datasets.mrclam import import_mrclam
from hybridslam.datasets.mrclam_files import MRCLAMError

DATA = os.path.join(os.path.dirname(__file__), "data", "mrclam")
CHI2_3_999 = 16.266  # 99.9% quantile of chi-square with 3 degrees of freedom


@pytest.fixture(scope="module")
def known() -> hs.Scenario:
    return import_mrclam(DATA, 1, identity_filter=True)


@pytest.fixture(scope="module")
def unknown() -> hs.Scenario:
    return import_mrclam(DATA, 1, identity_filter=True, unknown_map=True)


def _import_command(folder, *flags: str) -> tuple[str, str]:
    """``hybridslam import mrclam`` of the excerpt's robot 1 with these flags: the file written and stdout."""
    out, stdout = str(folder / "robot1.json"), io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", out, *flags]) == 0
    return out, stdout.getvalue()


# The command's two conversions that several tests read (each writes and validates a 90-step file).
@pytest.fixture(scope="module")
def command_known(tmp_path_factory) -> tuple[str, str]:
    return _import_command(tmp_path_factory.mktemp("known"), "--identity-filter")


@pytest.fixture(scope="module")
def command_default(tmp_path_factory) -> tuple[str, str]:
    return _import_command(tmp_path_factory.mktemp("default"))


@pytest.fixture
def copy(tmp_path) -> str:
    """A writable copy of the excerpt, for the broken-file cases."""
    path = str(tmp_path / "mrclam")
    shutil.copytree(DATA, path)
    return path


def _one_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message and message
    return message


# --------------------------------------------------------------------------- #
# The excerpt as a file format
# --------------------------------------------------------------------------- #


def test_excerpt_keeps_the_original_format():
    with open(os.path.join(DATA, "Robot1_Odometry.dat"), "rb") as f:
        lines = f.read().split(b"\r\n")
    assert lines[0].startswith(b"# UTIAS Multi-Robot") and sum(x.startswith(b"#") for x in lines) == 4
    assert b"\t" in lines[4]  # tab-and-space separated columns, CRLF line ends
    log = mrclam_files.read_robot(DATA, 1)
    assert log.odometry.rows.shape[1] == 3 and log.measurements.rows.shape[1] == 4
    assert log.odometry.lines[0] == 5  # 1-based file lines, after the 4 comment lines
    assert mrclam_files.read_barcodes(DATA)[5] == 1 and len(mrclam_files.read_landmarks(DATA).rows) == 15


# --------------------------------------------------------------------------- #
# Odometry
# --------------------------------------------------------------------------- #


def _euler(times, v, omega, query, h):
    """Forward Euler with step ``h`` of the held-sample unicycle, poses at ``query`` (on the grid)."""
    n = round((query[-1] - query[0]) / h)
    grid = query[0] + h * np.arange(n)
    active = np.searchsorted(times, grid + 1e-12, side="right") - 1  # the grid's own sample
    heading = np.concatenate([[0.0], np.cumsum(omega[active] * h)])
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(
        (v[active] * h)[:, None] * np.column_stack([np.cos(heading[:-1]), np.sin(heading[:-1])]), axis=0)])
    at = np.round((query - query[0]) / h).astype(int)
    return np.column_stack([xy[at], mrclam_calibration.wrap(heading[at])])


def test_exact_integrator_matches_fine_euler():
    """Irregular samples, a duplicated time (the later counts), ω = 0 and a tiny ω (Taylor branch),
    queries between samples. Euler's global error is ≈ v·ω·h·T/2 ≈ 3e-8 m at h = 1e-6 s."""
    times = np.array([0.0, 0.013, 0.3, 0.3, 0.71, 1.2, 1.2001, 1.6])
    v = np.array([0.086, 0.05, 0.9, 0.07, 0.0, 0.086, 0.03, 0.08])
    omega = np.array([-0.398, 0.0, 5.0, 0.561, 0.4, 1e-7, -0.2, 0.3])
    query = np.array([0.05, 0.2, 0.3, 0.65, 0.9, 1.2, 1.5, 1.9])
    exact = mrclam_calibration.integrate_odometry(times, v, omega, query)
    np.testing.assert_allclose(exact, _euler(times, v, omega, query, 1e-6), atol=1e-6, rtol=0)
    np.testing.assert_array_equal(exact[0], np.zeros(3))


def test_integrator_is_exact_on_one_arc():
    """Constant (v, ω) for 2 s from a query point: the closed-form circle, and composing the steps."""
    v, w = 0.08, 0.5
    query = np.linspace(0.5, 2.5, 9)
    poses = mrclam_calibration.integrate_odometry(np.array([0.0]), np.array([v]), np.array([w]), query)
    t = query - query[0]
    expected = np.column_stack([v / w * np.sin(w * t), v / w * (1 - np.cos(w * t)), w * t])
    np.testing.assert_allclose(poses, expected, atol=1e-14)
    steps = mrclam_calibration.between(poses[:-1], poses[1:])
    composed = poses[0]
    for u in steps:
        composed = mrclam_calibration.compose(composed, u)
    np.testing.assert_allclose(composed, poses[-1], atol=1e-14)


def _propagate(s: hs.Scenario) -> tuple[np.ndarray, np.ndarray]:
    """Dead reckoning from the prior and its first-order covariance under ``motion_cov``."""
    x, cov = s.robot_prior_mean.copy(), s.robot_prior_cov.copy()
    for step in s.steps:
        u, (c, sn) = step.odometry, (math.cos(x[2]), math.sin(x[2]))
        f = np.array([[1, 0, -sn * u[0] - c * u[1]], [0, 1, c * u[0] - sn * u[1]], [0, 0, 1]])
        x = mrclam_calibration.compose(x, u)
        g = np.eye(3)
        g[:2, :2] = [[math.cos(x[2]), -math.sin(x[2])], [math.sin(x[2]), math.cos(x[2])]]
        cov = f @ cov @ f.T + g @ s.motion_cov @ g.T
    return x, cov


def test_odometry_follows_the_ground_truth(known):
    """The odometry is velocity *commands* (the dataset's own description), so it is checked for what
    commands can promise. Per step: travelled distance within 15% of the ground truth's over the
    window (the full logs of datasets 6-7 overshoot by 4-12%: a speed scale error) and heading
    changes correlated with the true ones (0.78 here, 0.80-0.91 over the full logs; a sign or
    frame error gives ≤ 0). Composed over the window: the final dead-reckoning error inside the
    99.9% chi-square bound of the covariance that the calibrated motion_cov propagates."""
    u = np.array([step.odometry for step in known.steps])
    truth = mrclam_calibration.between(known.true_robot_poses[:-1], known.true_robot_poses[1:])
    ratio = np.hypot(u[:, 0], u[:, 1]).sum() / np.hypot(truth[:, 0], truth[:, 1]).sum()
    assert 0.85 < ratio < 1.15
    assert np.corrcoef(u[:, 2], truth[:, 2])[0, 1] > 0.6
    x, cov = _propagate(known)
    e = x - known.true_robot_poses[-1]
    e[2] = mrclam_calibration.wrap(e[2])
    assert e @ np.linalg.solve(cov, e) < CHI2_3_999
    dr = known.metadata["generator"]["dead_reckoning"]
    assert dr["final_position_error_m"] == pytest.approx(np.hypot(e[0], e[1]), abs=1e-8)


def test_steps_and_true_poses(known):
    g = known.metadata["generator"]
    log = mrclam_files.read_robot(DATA, 1)
    origin = log.odometry.rows[0, 0]
    last = min(log.odometry.rows[-1, 0], log.groundtruth.rows[-1, 0])
    assert g["time_origin_unix_s"] == origin == g["t0_unix_s"]
    assert known.num_steps == math.floor((last - origin) / 0.5) == 90
    times = origin + 0.5 * np.arange(known.num_steps + 1)
    expected = mrclam_calibration.interpolate_groundtruth(log.groundtruth.rows, times)
    np.testing.assert_allclose(known.true_robot_poses, expected)
    np.testing.assert_array_equal(known.robot_prior_mean, known.true_robot_poses[0])
    # Linear in the unwrapped heading: across the ±π seam it stays between its neighbours.
    gt = np.array([[0.0, 0, 0, math.pi - 0.1], [1.0, 0, 0, -math.pi + 0.1]])
    assert mrclam_calibration.interpolate_groundtruth(gt, np.array([0.5]))[0, 2] == pytest.approx(math.pi)
    later = import_mrclam(DATA, 1, identity_filter=True, start=10.25, duration=20, dt=0.25)
    assert later.num_steps == 80
    np.testing.assert_allclose(later.true_robot_poses[0],
                               mrclam_calibration.interpolate_groundtruth(log.groundtruth.rows, [origin + 10.25])[0])


# --------------------------------------------------------------------------- #
# Detections
# --------------------------------------------------------------------------- #


def test_detections_are_the_closest_landmark_measurements_of_each_step():
    """Without motion compensation every detection is a line of the measurement file: a landmark's
    barcode, within dt/2 of its step's time, the closest such line of that landmark."""
    s = import_mrclam(DATA, 1, identity_filter=True, motion_compensation=False)
    rows = mrclam_files.read_robot(DATA, 1).measurements.rows
    barcodes = mrclam_files.read_barcodes(DATA)
    subject = np.array([barcodes[int(b)] for b in rows[:, 1]])
    t0 = s.metadata["generator"]["t0_unix_s"]
    for k, step in enumerate(s.steps, 1):
        tk = t0 + 0.5 * k
        near = (rows[:, 0] > tk - 0.25) & (rows[:, 0] <= tk + 0.25)
        objects = [d.true_object for d in step.detections]
        assert sorted(objects) == sorted({n - 6 for n in subject[near] if n >= 6})
        for d in step.detections:
            same = np.flatnonzero(near & (subject == d.true_object + 6))
            best = same[np.argmin(np.abs(rows[same, 0] - tk))]
            assert (d.range, d.bearing) == tuple(rows[best, 2:4])
            np.testing.assert_array_equal(d.scores, [1.0])
    counts = s.metadata["generator"]["counts"]
    assert counts["kept"] == sum(len(st.detections) for st in s.steps) == 197
    assert counts["robot_robot"] == 12 and counts["unknown_barcode"] == 0


def test_association_truth_against_the_geometry(known):
    """``true_object`` comes from the barcode. From the true pose, the landmark closest to the
    back-projected detection is that one for 90% of the detections; the others pick a cluster
    neighbour. This excerpt's landmarks stand in clusters (6-8, 9-10, 11-13) 0.18-0.33 m apart,
    while a detection's position error at 5 m is ~0.1 m (range sd 7 cm, bearing 0.011 rad; the
    range bias 6 cm): the data are ambiguous, which is what the library is for. A barcode that
    named a landmark elsewhere (a gross mislabel) would fail the 0.35 m and 0.6 m bounds."""
    landmarks = known.true_object_poses[:, :2]
    pairwise = np.hypot(*(landmarks[:, None] - landmarks[None]).transpose(2, 0, 1))
    matches, total = 0, 0
    for pose, step in zip(known.true_robot_poses[1:], known.steps):
        for d in step.detections:
            direction = pose[2] + d.bearing
            point = pose[:2] + d.range * np.array([math.cos(direction), math.sin(direction)])
            dist = np.hypot(*(landmarks - point).T)
            closest = int(np.argmin(dist))
            total += 1
            matches += closest == d.true_object
            assert pairwise[closest, d.true_object] < 0.35 and dist[d.true_object] < 0.6
    assert matches >= 0.9 * total


def test_motion_compensation_moves_the_point_into_the_step_frame():
    """A robot that turned by +0.1 rad and moved 0.02 m forward between the measurement and t_k sees
    the same point from the step's pose: the compensated detection is the point re-expressed."""
    m = mrclam_detections.Measurements(time=np.array([0.0]), step=np.array([1]), landmark=np.array([0]),
                            raw=np.array([[2.0, 0.3]]), counts={})
    at_steps = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.1]])
    out = mrclam_detections.compensate(m, at_steps, np.zeros((1, 3)))
    point = 2.0 * np.array([math.cos(0.3), math.sin(0.3)])
    expected = mrclam_calibration.range_bearing(at_steps[1:], point[None])
    np.testing.assert_allclose(out, expected, atol=1e-14)
    same = mrclam_detections.compensate(m, at_steps, at_steps[1:])  # measured at t_k: unchanged
    np.testing.assert_allclose(same, m.raw, atol=1e-14)


def test_max_range_and_fov_drop_detections(known):
    s = import_mrclam(DATA, 1, identity_filter=True, max_range=3.0, fov=0.6)
    ranges = np.array([d.range for st in s.steps for d in st.detections])
    bearings = np.array([d.bearing for st in s.steps for d in st.detections])
    assert s.max_range == 3.0 and s.fov == 0.6
    assert ranges.max() <= 3.0 and np.abs(bearings).max() <= 0.3
    assert 0 < len(ranges) < known.metadata["generator"]["counts"]["kept"]
    assert s.metadata["generator"]["counts"]["beyond_sensor"] > 0
    # Defaults: every written detection in view, with a 3-sd margin.
    written = np.array([(d.range, d.bearing) for st in known.steps for d in st.detections])
    sd = np.sqrt(np.diag(known.geometric_cov))
    assert written[:, 0].max() + 3 * sd[0] <= known.max_range
    assert np.abs(written[:, 1]).max() + 3 * sd[1] <= known.fov / 2


# --------------------------------------------------------------------------- #
# Calibration
# --------------------------------------------------------------------------- #


def test_robust_scale_ignores_outliers():
    rng = np.random.default_rng(0)
    r = np.concatenate([0.1 * rng.standard_normal((4000, 2)) + [0.05, 0.0], np.full((200, 2), 10.0)])
    median, scale = mrclam_calibration.robust_location_scale(r)
    np.testing.assert_allclose(scale, 0.1, rtol=0.1)
    np.testing.assert_allclose(median, [0.05, 0.0], atol=0.01)
    np.testing.assert_allclose(mrclam_calibration.robust_variance(r, 1e-3), scale**2 + median**2)
    np.testing.assert_allclose(mrclam_calibration.robust_variance(np.zeros((5, 3)), 1e-3), 1e-6)


def test_noise_is_calibrated_from_the_ground_truth(known):
    cal = known.metadata["generator"]["calibration"]
    log = mrclam_files.read_robot(DATA, 1)
    u = np.array([step.odometry for step in known.steps])
    res = mrclam_calibration.odometry_residuals(u, known.true_robot_poses)
    np.testing.assert_allclose(np.diag(known.motion_cov), mrclam_calibration.robust_variance(res, mrclam_track.MOTION_SD_FLOOR))
    assert cal["odometry_residuals"]["count"] == 90 and cal["measurement_residuals"]["count"] == 197
    median, scale = (np.array(cal["measurement_residuals"][k]) for k in ("median", "scale"))
    np.testing.assert_allclose(np.diag(known.geometric_cov), scale**2 + median**2, rtol=1e-6)
    assert known.motion_cov[0, 1] == known.geometric_cov[0, 1] == 0.0
    # MRCLAM's range bias: reported, not corrected.
    assert cal["range_bias_m"] == median[0] and 0.03 < median[0] < 0.1 and not cal["range_bias_corrected"]
    assert "1.4826*MAD" in cal["method"] and cal["motion_cov"] == "calibrated"
    # The drift check: summed over 5 s the odometry errors grow faster than white noise would.
    drift = cal["odometry_drift_sd_per_step"]
    assert drift["block_steps"][0] == 10 and drift["horizons_s"][0] == 5.0
    assert drift["sd"][2] > math.sqrt(known.motion_cov[2, 2])
    np.testing.assert_allclose(drift["sd"], np.max(drift["sd_by_horizon"], axis=0))
    assert log.odometry.rows.shape[0] > 0


def test_measurement_noise_is_what_the_written_detections_show(known):
    """geometric_cov is the robust mean square of the detections as written against the true pose
    at their step (default), or of the raw measurements at their own times ("raw")."""
    landmarks = mrclam_files.read_landmarks(DATA).rows
    rows = [(det.range, det.bearing, *landmarks[det.true_object, 1:3], *pose)
            for pose, step in zip(known.true_robot_poses[1:], known.steps) for det in step.detections]
    a = np.array(rows)
    residuals = mrclam_calibration.measurement_residuals(a[:, :2], a[:, 4:7], a[:, 2:4])
    np.testing.assert_allclose(np.diag(known.geometric_cov),
                               mrclam_calibration.robust_variance(residuals, mrclam_track.GEOMETRIC_SD_FLOOR), rtol=1e-9)
    cal = known.metadata["generator"]["calibration"]
    assert cal["measurement_noise_from"] == "written"
    assert cal["measurement_residuals"] == cal["written_detection_residuals"]
    raw = import_mrclam(DATA, 1, identity_filter=True, measurement_noise_from="raw")
    rcal = raw.metadata["generator"]["calibration"]
    assert rcal["measurement_noise_from"] == "raw"
    assert rcal["measurement_residuals"] == rcal["raw_measurement_residuals"] == cal["raw_measurement_residuals"]
    median, scale = (np.array(rcal["raw_measurement_residuals"][k]) for k in ("median", "scale"))
    np.testing.assert_allclose(np.diag(raw.geometric_cov), scale**2 + median**2, rtol=1e-6)
    assert not np.allclose(raw.geometric_cov, known.geometric_cov)
    # Only the covariance differs: the detections written are the same.
    assert [d.range for st in raw.steps for d in st.detections] == list(a[:, 0])
    with pytest.raises(MRCLAMError, match="measurement_noise_from: expected one of written, raw"):
        import_mrclam(DATA, 1, identity_filter=True, measurement_noise_from="truth")


def test_drift_covers_every_horizon_the_window_holds():
    """The drift sd is per component the largest that the residuals' sums over 5, 10, 20 and 40 s
    imply, over the horizons the window measures (5 blocks of 5 s, 20 of a longer one): white noise
    gives its per-step sd at every horizon; a bias makes the longest horizon win."""
    rng = np.random.default_rng(0)
    white = 0.01 * rng.standard_normal((8000, 3))
    sd, meta = mrclam_calibration.drift_over_horizons(white, 0.5)
    assert meta["horizons_s"] == [5.0, 10.0, 20.0, 40.0] and meta["block_steps"] == [10, 20, 40, 80]
    np.testing.assert_allclose(meta["sd_by_horizon"], 0.01, rtol=0.25)
    np.testing.assert_allclose(sd, np.max(meta["sd_by_horizon"], axis=0))
    biased = white + np.array([0.002, 0.0, 0.0])  # a velocity scale error: correlated in time
    sd_b, meta_b = mrclam_calibration.drift_over_horizons(biased, 0.5)
    assert np.argmax(np.array(meta_b["sd_by_horizon"])[:, 0]) == 3 and sd_b[0] > 1.5 * sd[0]
    # A longer horizon counts with 20 blocks: 400 steps of 0.5 s (200 s) hold 20 of 10 s, 10 of
    # 20 s; 200 steps (a 100 s window) 20 of 5 s only; 49 steps not 5 of 5 s.
    assert mrclam_calibration.drift_over_horizons(white[:400], 0.5)[1]["horizons_s"] == [5.0, 10.0]
    assert mrclam_calibration.drift_over_horizons(white[:399], 0.5)[1]["horizons_s"] == [5.0]
    assert mrclam_calibration.drift_over_horizons(white[:50], 0.5)[1]["horizons_s"] == [5.0]
    assert mrclam_calibration.drift_over_horizons(white[:49], 0.5) is None


def test_motion_noise_from_the_drift_grows_as_fast_as_dead_reckonings_error(known):
    s = import_mrclam(DATA, 1, identity_filter=True, motion_noise_from="drift")
    cal = s.metadata["generator"]["calibration"]
    drift = np.array(cal["odometry_drift_sd_per_step"]["sd"])
    np.testing.assert_allclose(np.diag(s.motion_cov), np.maximum(np.diag(known.motion_cov), drift**2), rtol=1e-6)
    assert np.all(np.diag(s.motion_cov) >= np.diag(known.motion_cov)) and s.motion_cov[2, 2] > known.motion_cov[2, 2]
    assert cal["motion_noise_from"] == "drift" and known.metadata["generator"]["calibration"]["motion_noise_from"] == "steps"
    assert s.steps == known.steps and np.array_equal(s.geometric_cov, known.geometric_cov)
    with pytest.raises(MRCLAMError, match="motion_noise_from drift needs 5 blocks of 5 s"):
        import_mrclam(DATA, 1, identity_filter=True, duration=20.0, motion_noise_from="drift")
    with pytest.raises(MRCLAMError, match="motion_noise_from: expected one of steps, drift"):
        import_mrclam(DATA, 1, identity_filter=True, motion_noise_from="wheel")
    given = import_mrclam(DATA, 1, identity_filter=True, motion_noise_from="drift", motion_cov=[1e-4, 1e-4, 1e-3])
    np.testing.assert_array_equal(given.motion_cov, np.diag([1e-4, 1e-4, 1e-3]))  # a given one wins


def test_overrides_and_range_bias_correction(known):
    s = import_mrclam(DATA, 1, identity_filter=True, motion_cov=[1e-4, 2e-4, 3e-4], geometric_cov=np.diag([0.01, 0.002]),
                      robot_prior_cov=[1.0, 1.0, 0.1], correct_range_bias=True)
    np.testing.assert_array_equal(s.motion_cov, np.diag([1e-4, 2e-4, 3e-4]))
    np.testing.assert_array_equal(s.geometric_cov, np.diag([0.01, 0.002]))
    np.testing.assert_array_equal(s.robot_prior_cov, np.diag([1.0, 1.0, 0.1]))
    cal = s.metadata["generator"]["calibration"]
    assert cal["motion_cov"] == cal["geometric_cov"] == "given" and cal["range_bias_corrected"]
    bias = known.metadata["generator"]["calibration"]["range_bias_m"]
    before = [d.range for st in known.steps for d in st.detections]
    after = [d.range for st in s.steps for d in st.detections]
    np.testing.assert_allclose(np.subtract(before, after), bias, atol=1e-12)
    assert abs(cal["measurement_residuals"]["median"][0]) < 1e-9


def test_a_window_without_detections_needs_a_geometric_cov():
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(DATA, 1, identity_filter=True, max_range=0.5)
    assert _one_line(e).startswith("robot 1: no landmark measurement in the window to calibrate")
    s = import_mrclam(DATA, 1, identity_filter=True, max_range=0.5, geometric_cov=[0.01, 0.001])
    assert s.max_detections == 0 and s.metadata["generator"]["counts"]["kept"] == 0
    assert s.metadata["generator"]["calibration"]["measurement_residuals"] == {"count": 0}


# --------------------------------------------------------------------------- #
# Maps and the file
# --------------------------------------------------------------------------- #


def test_known_map(known):
    assert known.num_classes == 1 and known.classifier.model == "none" and known.num_objects == 15
    lm = mrclam_files.read_landmarks(DATA).rows
    np.testing.assert_array_equal(known.object_prior_means[:, :2], lm[:, 1:3])
    np.testing.assert_array_equal(known.object_prior_means[:, 2], 0.0)
    np.testing.assert_array_equal(known.true_object_poses, known.object_prior_means)
    np.testing.assert_array_equal(known.true_classes, 0)
    sd = np.sqrt(np.diagonal(known.object_prior_covs, axis1=1, axis2=2))
    np.testing.assert_allclose(sd[:, :2], np.maximum(lm[:, 3:5], 0.01))  # survey sds are 40-650 µm
    np.testing.assert_allclose(sd[:, 2], math.pi)
    assert known.discovery is None and known.true_objects is None


def test_unknown_map(unknown, known):
    assert unknown.num_objects == 0 and unknown.discovery is not None
    assert unknown.discovery.max_objects == 15 + 10
    density = -math.log(unknown.max_range * unknown.fov)  # uniform in [range, bearing] over the footprint
    assert unknown.discovery.new_object_log_density == pytest.approx(density)
    assert unknown.discovery.new_object_orientation_var == pytest.approx(math.pi**2)
    assert len(unknown.true_objects) == 15
    np.testing.assert_array_equal(np.array([p for p, _ in unknown.true_objects]), known.true_object_poses)
    assert {c for _, c in unknown.true_objects} == {0}
    assert unknown.steps == known.steps and np.array_equal(unknown.motion_cov, known.motion_cov)
    custom = import_mrclam(DATA, 1, identity_filter=True, unknown_map=True, discovery_margin=0, new_object_log_density=-3.0)
    assert custom.discovery.max_objects == 15 and custom.discovery.new_object_log_density == -3.0
    assert import_mrclam(DATA, 1, identity_filter=True, unknown_map=True, max_objects=40).discovery.max_objects == 40
    with pytest.raises(MRCLAMError, match="max_objects: object slots are a setting of an unknown map"):
        import_mrclam(DATA, 1, identity_filter=True, max_objects=40)
    with pytest.raises(MRCLAMError, match="max_objects: expected an integer >= 2, got 1"):
        import_mrclam(DATA, 1, identity_filter=True, unknown_map=True, max_objects=1)


def test_save_load_round_trip(unknown, tmp_path):
    """The known-map file's round trip: test_cli_writes_a_valid_file_and_a_summary (the command saves it)."""
    s = unknown
    path = tmp_path / "mrclam.json"
    hs.save_scenario(s, path)
    loaded = hs.load_scenario(path)
    assert loaded == s
    assert loaded.metadata["generator"]["name"] == "hybridslam.datasets.mrclam"


# --------------------------------------------------------------------------- #
# Errors: one line, naming the file and line, the robot, the window or the setting
# --------------------------------------------------------------------------- #


def test_missing_files(copy, tmp_path):
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(str(tmp_path / "nowhere"), 1)
    assert "nowhere: not a dataset folder" in _one_line(e)
    os.remove(os.path.join(copy, "Robot1_Measurement.dat"))
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(copy, 1)
    assert _one_line(e) == f"{copy}/Robot1_Measurement.dat: no such file (robot 1 has no measurement log)"
    os.remove(os.path.join(copy, "Barcodes.dat"))
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(copy, 1)
    assert _one_line(e) == f"{copy}/Barcodes.dat: no such file"


@pytest.mark.parametrize("name, line, text", [
    ("Robot1_Odometry.dat", 7, "1248446283.4 \t 0.086\r\n"),
    ("Robot1_Groundtruth.dat", 100, "1248446283.4 \t 0.1 \t x \t 0.3\r\n"),
    ("Robot1_Measurement.dat", 5, "1248446283.4 \t 63 \t nan \t 0.1\r\n"),
    ("Landmark_Groundtruth.dat", 6, "7 1 2 3\r\n"),
])
def test_garbled_line(copy, name, line, text):
    path = os.path.join(copy, name)
    with open(path, newline="") as f:
        lines = f.readlines()
    lines[line - 1] = text
    with open(path, "w", newline="") as f:
        f.writelines(lines)
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(copy, 1)
    message = _one_line(e)
    assert message.startswith(f"{path}:{line}: expected ") and repr(text.strip()) in message


def test_records_out_of_time_order(copy):
    path = os.path.join(copy, "Robot1_Odometry.dat")
    with open(path, newline="") as f:
        lines = f.readlines()
    lines[9], lines[10] = lines[10], lines[9]
    with open(path, "w", newline="") as f:
        f.writelines(lines)
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(copy, 1)
    assert _one_line(e).startswith(f"{path}:11: time ") and "time order" in str(e.value)


def test_unknown_robot():
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(DATA, 6)
    assert _one_line(e) == "robot 6: no such robot (MRCLAM robots are 1-5)"
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(DATA, 2)  # the excerpt holds robot 1 only
    assert _one_line(e) == f"{DATA}/Robot2_Odometry.dat: no such file (robot 2 has no odometry log)"


@pytest.mark.parametrize("window, expected", [
    ({"start": -1.0}, "start -1 s: outside the data; robot 1's data cover 0.000 to 45."),
    ({"start": 50.0}, "start 50 s: outside the data; robot 1's data cover 0.000 to 45."),
    ({"start": 10.0, "duration": 40.0}, "window 10 s + 40 s: ends at 50.000 s, after the data; robot 1's"),
    ({"start": 45.3}, "window from 45.3 s: holds no step of dt = 0.5 s; robot 1's data cover"),
    ({"duration": 0.0}, "duration: expected a positive number of seconds, got 0.0"),
    ({"dt": 0.0}, "dt: expected a positive number of seconds, got 0.0"),
    ({"dt": -0.5}, "dt: expected a positive number of seconds, got -0.5"),
    ({"start": math.nan}, "start: expected a finite number of seconds, got nan"),
])
def test_window_outside_the_data(window, expected):
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(DATA, 1, identity_filter=True, **window)
    assert _one_line(e).startswith(expected)


@pytest.mark.parametrize("settings, expected", [
    ({"motion_cov": [1.0, -1.0, 1.0]}, "motion_cov: not symmetric positive definite"),
    ({"geometric_cov": [1.0, 2.0, 3.0]}, "geometric_cov: expected 2 finite variances or a 2x2 matrix"),
    ({"max_range": 0.0}, "max_range: expected a positive number of metres"),
    ({"fov": 7.0}, "fov: expected radians in (0, 2*pi]"),
    ({"discovery_margin": -1}, "discovery_margin: expected a non-negative integer"),
])
def test_bad_settings(settings, expected):
    with pytest.raises(MRCLAMError) as e:
        import_mrclam(DATA, 1, identity_filter=True, **settings)
    assert _one_line(e).startswith(expected)


# --------------------------------------------------------------------------- #
# The command
# --------------------------------------------------------------------------- #


def test_cli_writes_a_valid_file_and_a_summary(tmp_path, capsys, known, command_known):
    out, stdout = command_known
    loaded = hs.load_scenario(out)
    assert loaded == known  # and the round trip of save_scenario and load_scenario
    assert loaded.metadata["generator"]["name"] == "hybridslam.datasets.mrclam"
    assert stdout.startswith(f"wrote {out}: mrclam robot 1, 0-45 s after its first odometry record, 90 steps")
    for text in ("197 of 8 landmarks", "2.19 per step (max 8)", "12 robot-robot",
                 "motion_cov (calibrated): sd", "geometric_cov (calibrated from the detections as written)",
                 "range bias +0.058 m (not corrected", "dead reckoning at the end of the window: 0.438 m"):
        assert text in stdout, text
    out = tmp_path / "unknown.json"
    assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", str(out), "--unknown-map",
                     "--start", "5", "--duration", "20", "--dt", "0.25", "--max-range", "5",
                     "--motion-cov", "1e-4,1e-4,1e-3", "--correct-range-bias", "--no-motion-compensation",
                     "--odometry-delay", "0.17", "--max-objects", "30", "--measurement-noise-from", "raw",
                     "--motion-noise-from", "drift", "--identity-filter"]) == 0
    s = hs.load_scenario(out)
    g = s.metadata["generator"]
    assert s.discovery is not None and s.discovery.max_objects == 30 and s.num_steps == 80 and s.max_range == 5.0
    assert g["odometry_delay_s"] == 0.17 and not g["motion_compensation"]
    assert g["calibration"]["range_bias_corrected"] and g["calibration"]["measurement_noise_from"] == "raw"
    np.testing.assert_array_equal(s.motion_cov, np.diag([1e-4, 1e-4, 1e-3]))  # given: drift ignored
    assert "unknown map of 15 landmarks (30 object slots: --object-slots)" in capsys.readouterr().out
    assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", str(out), "--motion-noise-from", "drift"]) == 0
    assert "motion_cov (calibrated, from the 5 s drift): sd" in capsys.readouterr().out


def _error(capsys) -> str:
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hybridslam: error: ")
    return lines[0]


@pytest.mark.parametrize("args, expected", [
    (["--robot", "7"], "robot 7: no such robot"),
    (["--robot", "1", "--start", "60"], "start 60 s: outside the data"),
    (["--robot", "1", "--dt", "0"], "dt: expected a positive number of seconds"),
    (["--robot", "1", "--motion-cov", "1,2"], "--motion-cov: expected 3 positive comma-separated variances"),
    (["--robot", "x"], "argument --robot: invalid int value: 'x'"),
])
def test_cli_errors_are_one_line(tmp_path, capsys, args, expected):
    assert cli.main(["import", "mrclam", DATA, "-o", str(tmp_path / "x.json"), *args]) == 2
    assert expected in _error(capsys)
    assert not (tmp_path / "x.json").exists()


def test_cli_garbled_file_names_file_and_line(copy, tmp_path, capsys):
    path = os.path.join(copy, "Robot1_Odometry.dat")
    with open(path, newline="") as f:
        lines = f.readlines()
    lines[20] = "garbage\r\n"
    with open(path, "w", newline="") as f:
        f.writelines(lines)
    assert cli.main(["import", "mrclam", copy, "--robot", "1", "-o", str(tmp_path / "x.json")]) == 2
    assert f"{path}:21: expected 3 numbers (time, v, omega), got 'garbage'" in _error(capsys)


# --------------------------------------------------------------------------- #
# Without identities (the default)
# --------------------------------------------------------------------------- #


def test_the_default_import_writes_every_reading_and_no_identity_it_lacks(known):
    """Without the identity filter every reading in a step's window is a detection (repeats kept
    here): the other robot's readings too, with no ``true_object``, counted in the metadata; the
    file declares the clutter density ``log(0.5 / (max_range · fov))``. The oracle-assisted
    conversion (``identity_filter``) declares none."""
    s = import_mrclam(DATA, 1, merge_repeats=False, motion_compensation=False)
    rows = mrclam_files.read_robot(DATA, 1).measurements.rows
    t0 = s.metadata["generator"]["t0_unix_s"]
    for k, step in enumerate(s.steps, 1):
        tk = t0 + 0.5 * k
        near = (rows[:, 0] > tk - 0.25) & (rows[:, 0] <= tk + 0.25)
        np.testing.assert_allclose(sorted(d.range for d in step.detections), sorted(rows[near, 2]))
    g = s.metadata["generator"]
    unnamed = sum(d.true_object is None for st in s.steps for d in st.detections)
    assert unnamed == g["counts"]["robot_robot"] == 12 and g["counts"]["unknown_barcode"] == 0
    assert not g["identities"]["identity_filter"] and "selecting detections" not in g["identities"]["barcodes_used_for"]
    assert s.clutter_log_density == pytest.approx(math.log(0.5 / (s.max_range * s.fov)))
    assert hs.load_scenario(_saved(s)).clutter_log_density == pytest.approx(s.clutter_log_density)
    assert known.clutter_log_density is None
    assert import_mrclam(DATA, 1, clutter_log_density="none").clutter_log_density is None
    assert import_mrclam(DATA, 1, clutter_log_density=-6.0).clutter_log_density == -6.0
    with pytest.raises(MRCLAMError, match="clutter_log_density"):
        import_mrclam(DATA, 1, clutter_log_density="lots")


def _saved(s: hs.Scenario) -> str:
    import tempfile
    path = os.path.join(tempfile.mkdtemp(), "s.json")
    hs.save_scenario(s, path)
    return path


def test_merging_repeats_reads_no_barcode(tmp_path):
    """The merge of repeated readings (``merge_repeats``) is by geometry alone: with the barcodes of the
    landmarks permuted (and the noise given, so that no calibration reads them) the detections
    written are the same; only their ``true_object`` (evaluation) moves. Merging drops readings,
    never adds any, and keeps at most one per landmark more often than keeping every repeat."""
    copy = tmp_path / "permuted"
    shutil.copytree(DATA, copy)
    path = copy / "Barcodes.dat"
    lines = path.read_bytes().decode("ascii").splitlines(keepends=True)
    rows = [i for i, line in enumerate(lines) if not line.startswith("#") and line.strip()]
    pairs = [lines[i].split() for i in rows]
    landmark = [j for j, (subject, _) in enumerate(pairs) if int(subject) > 5]
    shifted = landmark[1:] + landmark[:1]
    for j, k in zip(landmark, shifted):
        lines[rows[j]] = f"{pairs[j][0]}\t{pairs[k][1]}\r\n"
    path.write_bytes("".join(lines).encode("ascii"))
    cov = dict(geometric_cov=[0.01, 0.001], motion_cov=[1e-4, 1e-4, 1e-4])
    a, b = import_mrclam(DATA, 1, merge_repeats=True, **cov), import_mrclam(copy, 1, merge_repeats=True, **cov)
    geometry = lambda s: [[(d.range, d.bearing) for d in st.detections] for st in s.steps]  # noqa: E731
    assert geometry(a) == geometry(b)
    assert [d.true_object for st in a.steps for d in st.detections] != \
        [d.true_object for st in b.steps for d in st.detections]
    every = import_mrclam(DATA, 1, **cov)
    assert a.metadata["generator"]["counts"]["merged"] > 0
    assert sum(map(len, geometry(a))) + a.metadata["generator"]["counts"]["merged"] == sum(map(len, geometry(every)))


def test_an_unknown_maps_object_slots_come_from_the_data_not_the_landmark_count():
    """Default object slots without identities: the busiest step's detections plus the margin (the
    oracle-assisted conversion: the surveyed landmarks plus the margin); ``max_objects`` sets them."""
    s = import_mrclam(DATA, 1, unknown_map=True)
    assert s.discovery.max_objects == s.max_detections + 10
    assert s.metadata["generator"]["object_slots"]["from"] == "most detections in a step + margin"
    assert import_mrclam(DATA, 1, unknown_map=True, discovery_margin=3).discovery.max_objects == s.max_detections + 3
    assert import_mrclam(DATA, 1, unknown_map=True, identity_filter=True).discovery.max_objects == 15 + 10
    assert import_mrclam(DATA, 1, unknown_map=True, max_objects=12).discovery.max_objects == 12


def test_cli_default_import_says_what_it_kept(tmp_path, capsys, command_default):
    stdout = command_default[1]
    out = tmp_path / "robot1.json"
    for text in ("every reading: 12 of no landmark (other robots: 12 readings", "0 repeats merged",
                 "clutter log density -"):
        assert text in stdout, text
    assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", str(out), "--clutter-log-density", "none"]) == 0
    assert hs.load_scenario(out).clutter_log_density is None
    assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", str(out), "--clutter-log-density", "x"]) == 2


def test_a_file_with_clutter_gets_the_drift_calibrated_motion_noise_by_default(known):
    """With a clutter hypothesis (the default conversion) ``motion_cov`` is calibrated from the
    odometry's 5-40 s drift (5 s on this excerpt), so that ``S`` covers dead reckoning's real error and a landmark seen after
    a stretch without any is not explained as clutter; without clutter (the identity filter,
    ``clutter_log_density="none"``) or with a window too short for 5 drift blocks it stays per step.
    A given ``motion_noise_from`` is kept."""
    s = import_mrclam(DATA, 1)
    cal = s.metadata["generator"]["calibration"]
    assert s.clutter_log_density is not None and cal["motion_noise_from"] == "drift"
    assert cal["motion_noise_chosen"].startswith("default")
    np.testing.assert_array_equal(s.motion_cov, import_mrclam(DATA, 1, motion_noise_from="drift").motion_cov)
    steps = import_mrclam(DATA, 1, motion_noise_from="steps")
    assert steps.metadata["generator"]["calibration"]["motion_noise_chosen"] == "given"
    assert np.all(np.diag(s.motion_cov) >= np.diag(steps.motion_cov))
    assert np.any(np.diag(s.motion_cov) > 2 * np.diag(steps.motion_cov))  # the excerpt's heading drifts
    for kwargs in ({"identity_filter": True}, {"clutter_log_density": "none"}, {"duration": 20.0}):
        other = known if kwargs == {"identity_filter": True} else import_mrclam(DATA, 1, **kwargs)
        assert other.metadata["generator"]["calibration"]["motion_noise_from"] == "steps", kwargs
    assert import_mrclam(DATA, 1, identity_filter=True, clutter_log_density=-4.0) \
        .metadata["generator"]["calibration"]["motion_noise_from"] == "drift"


@pytest.mark.parametrize("clutter, steps, dt, expected", [
    (True, 50, 0.5, "drift"), (True, 49, 0.5, "steps"), (False, 1000, 0.5, "steps"),
    (True, 25, 1.0, "drift"), (True, 24, 1.0, "steps"),
])
def test_default_motion_noise_rule(clutter, steps, dt, expected):
    """Drift needs :data:`mrclam_calibration.MIN_BLOCKS` blocks of 5 s; only a file with clutter gets it by default."""
    assert mrclam.default_motion_noise(clutter, steps, dt) == expected


def test_cli_default_import_calibrates_the_motion_noise_from_the_drift(command_default, command_known):
    assert "motion_cov (calibrated, from the 5 s drift)" in command_default[1]
    assert "motion_cov (calibrated): sd" in command_known[1]


def test_unmapped_objects_keep_the_map_and_add_room_beside_it(tmp_path):
    """``--unmapped-objects N``: the surveyed landmarks stay the prior map, a discovery section adds
    room for N objects they do not hold (the new-object density of an unknown map), the ground
    truth moves to ``true_objects`` (detections then index it) and the file round-trips."""
    plain = import_mrclam(DATA, 1)
    s = import_mrclam(DATA, 1, unmapped_objects=4)
    assert s.num_objects == plain.num_objects == 15 and s.discovery.max_objects == 19
    np.testing.assert_array_equal(s.object_prior_means, plain.object_prior_means)
    assert s.discovery.new_object_log_density == pytest.approx(-math.log(s.max_range * s.fov))
    np.testing.assert_array_equal(np.array([p for p, _ in s.true_objects]), plain.true_object_poses)
    assert s.steps == plain.steps and s.metadata["generator"]["unmapped_objects"] == 4
    out = tmp_path / "r1.json"
    assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", str(out), "--unmapped-objects", "4"]) == 0
    assert hs.load_scenario(out).discovery.max_objects == 19
    # --new-object-log-density writes the density those objects' detections get (a rarer source
    # than the footprint's uniform density), and a bad value names the field.
    assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", str(out), "--unmapped-objects", "4",
                     "--new-object-log-density", "-6"]) == 0
    assert hs.load_scenario(out).discovery.new_object_log_density == -6.0
    assert cli.main(["import", "mrclam", DATA, "--robot", "1", "-o", str(out), "--unmapped-objects", "4",
                     "--new-object-log-density", "inf"]) == 2
    with pytest.raises(MRCLAMError, match="unmapped_objects: room for objects beside a known map"):
        import_mrclam(DATA, 1, unknown_map=True, unmapped_objects=4)
    with pytest.raises(MRCLAMError, match="unmapped_objects: expected a non-negative integer"):
        import_mrclam(DATA, 1, unmapped_objects=-1)
