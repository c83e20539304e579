"""One window of an MRCLAM robot log assembled into what a scenario is written from (used by
:mod:`.mrclam`, whose module docstring describes the conversion): the odometry integrated at the
step and measurement times, the detections picked and motion-compensated, the ground truth
interpolated (:class:`Track`, :func:`assemble_track`), the noise calibrated against that ground
truth (:class:`Noise`, :func:`calibrate`; the module docstring of :mod:`.mrclam`, Noise) and the
scenario's steps (:func:`scenario_steps`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..models.scenario import Detection, Step
from .mrclam_calibration import (DRIFT_BLOCK_S, MIN_BLOCKS, between, drift_over_horizons,
                                 integrate_odometry, interpolate_groundtruth, measurement_residuals,
                                 odometry_residuals, robust_variance)
from .mrclam_detections import Measurements, Window, closest_per_landmark, compensate, landmark_measurements
from .mrclam_files import MRCLAMError, RobotLog

MOTION_SD_FLOOR = 1e-4  # m, m, rad per step: keeps the calibrated covariance positive definite
GEOMETRIC_SD_FLOOR = 1e-3  # m, rad


@dataclass(frozen=True)
class Track:
    """The window's integrated odometry, ground truth and detections."""

    path: np.ndarray  # (T + 1, 3) integrated odometry at t_0..t_T, identity at t_0
    odometry: np.ndarray  # (T, 3) u_k
    truth: np.ndarray  # (T + 1, 3) ground truth at t_0..t_T
    measurements: Measurements
    written: np.ndarray  # (n, 2) [range, bearing] as written (compensated or raw) for every measurement
    kept: np.ndarray  # (m,) indices of the measurements written, in time order


def assemble_track(log: RobotLog, barcodes: dict[int, int], landmarks: np.ndarray, window: Window,
                   delay: float, motion_compensation: bool, max_range: float | None, fov: float | None,
                   identity_filter: bool = True) -> Track:
    """Integrate the odometry at the step and measurement times, pick and compensate the detections
    (``identity_filter``: landmark readings only, one per landmark and step; otherwise every reading)."""
    meas = landmark_measurements(log, barcodes, landmarks[:, 0].astype(np.int64), window, identity_filter)
    # One integration serves the step times and the measurement times (motion compensation). Times
    # count from the origin: Unix seconds (~1.2e9) would leave float64 a resolution of only 2e-7 s.
    query = np.concatenate([window.times, meas.time]) - window.origin
    order = np.argsort(query, kind="stable")
    odo = log.odometry.rows
    path = np.empty((len(query), 3))
    path[order] = integrate_odometry(odo[:, 0] - window.origin + delay, odo[:, 1], odo[:, 2], query[order])
    at_steps, at_meas = path[: len(window.times)], path[len(window.times):]
    written = compensate(meas, at_steps, at_meas) if motion_compensation else meas.raw.copy()
    visible = np.ones(len(written), dtype=bool)
    if max_range is not None:
        visible &= written[:, 0] <= max_range
    if fov is not None:
        visible &= np.abs(written[:, 1]) <= fov / 2
    kept = closest_per_landmark(meas, window, visible) if identity_filter else np.flatnonzero(visible)
    meas.counts.update(beyond_sensor=int((~visible).sum()), superseded=int(visible.sum() - len(kept)),
                       kept=len(kept))
    truth = interpolate_groundtruth(log.groundtruth.rows, window.times)
    return Track(at_steps, between(at_steps[:-1], at_steps[1:]), truth, meas, written, kept)


@dataclass(frozen=True)
class Noise:
    """The covariances written and the residuals they came from."""

    motion: np.ndarray  # (3, 3)
    geometric: np.ndarray  # (2, 2)
    odometry_residuals: np.ndarray  # (T, 3)
    sensor_residuals: np.ndarray  # (m, 2) the residuals geometric is calibrated from (``source``)
    raw_residuals: np.ndarray  # (m, 2) raw measurements against the ground truth at their times
    range_bias: float  # m, the median range residual (of ``source``) before any correction
    source: str  # "written" or "raw": which residuals ``sensor_residuals`` are
    motion_source: str  # "steps" or "drift": what ``motion`` is calibrated from


def calibrate(track: Track, log: RobotLog, landmarks: np.ndarray, given: dict[str, np.ndarray | None],
              robot: int, correct_range_bias: bool, source: str = "written", motion_source: str = "steps",
              dt: float = 0.5) -> Noise:
    """The robust covariances (module docstring); corrects ``track.written`` ranges if asked."""
    meas = track.measurements
    kept = track.kept[meas.landmark[track.kept] >= 0]  # the readings a barcode names a landmark of
    if not len(kept) and (given["geometric_cov"] is None or correct_range_bias):
        raise MRCLAMError(f"robot {robot}: no landmark measurement in the window to calibrate the "
                          "measurement noise from; give geometric_cov (--geometric-cov)")
    points = landmarks[meas.landmark[kept], 1:3]
    raw = measurement_residuals(meas.raw[kept], interpolate_groundtruth(log.groundtruth.rows, meas.time[kept]),
                                points)
    sensor = (measurement_residuals(track.written[kept], track.truth[meas.step[kept]], points)
              if source == "written" else raw.copy())
    range_bias = float(np.median(sensor[:, 0])) if len(kept) else 0.0
    if correct_range_bias:
        track.written[:, 0] -= range_bias
        sensor[:, 0] -= range_bias
    odometry = odometry_residuals(track.odometry, track.truth)
    motion, geometric = given["motion_cov"], given["geometric_cov"]
    if motion is None:
        motion = np.diag(robust_variance(odometry, MOTION_SD_FLOOR))
        if motion_source == "drift":
            drift = drift_over_horizons(odometry, dt)
            if drift is None:
                raise MRCLAMError(f"robot {robot}: motion_noise_from drift needs {MIN_BLOCKS} blocks of "
                                  f"{DRIFT_BLOCK_S:g} s of odometry in the window; give a longer window (duration) "
                                  "or motion_noise_from 'steps'")
            motion = np.diag(np.maximum(np.diag(motion), drift[0] ** 2))
    if geometric is None:
        geometric = np.diag(robust_variance(sensor, GEOMETRIC_SD_FLOOR))
    return Noise(motion, geometric, odometry, sensor, raw, range_bias, source, motion_source)


def scenario_steps(track: Track) -> tuple[Step, ...]:
    """The scenario's steps: ``u_k`` and the kept detections of step k, in time order."""
    meas, written = track.measurements, track.written
    per_step: list[list[Detection]] = [[] for _ in range(len(track.odometry))]
    for i in track.kept:
        per_step[meas.step[i] - 1].append(
            Detection(float(written[i, 0]), float(written[i, 1]), np.ones(1),
                      int(meas.landmark[i]) if meas.landmark[i] >= 0 else None))
    return tuple(Step(u.copy(), tuple(d)) for u, d in zip(track.odometry, per_step))
