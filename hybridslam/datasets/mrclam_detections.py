"""The window of an MRCLAM log and its detections: which readings a step holds, their motion
compensation and the merging of repeats (used by :mod:`.mrclam`, whose module docstring describes
the conversion: Time, Detections, Motion compensation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .mrclam_calibration import _polar, _rotate, between, wrap
from .mrclam_files import ROBOTS, MRCLAMError, RobotLog, finite

RANGE_STEP, FOV_STEP = 0.5, 0.1  # default max_range and fov round up to these (m, rad)
MERGE_GATE = 9.21  # chi-square (2 dof) 0.99 quantile: two readings this close are one object's (merge_repeats)
SAME_FRAME_S = 1e-3  # readings this close in time are one sensor frame (never merged)


@dataclass(frozen=True)
class Window:
    """The imported stretch of one robot's log. Times in Unix seconds."""

    origin: float  # the robot's first odometry record: ``start`` counts from here
    times: np.ndarray  # (T + 1,) t_0..t_T
    end: float  # the end of the data (odometry and ground truth)

    @property
    def dt(self) -> float:
        return float(self.times[1] - self.times[0])


def data_span(log: RobotLog, delay: float = 0.0) -> tuple[float, float, float]:
    """``(origin, first, last)`` [Unix s]: the robot's first odometry record as logged, and the
    span that both the odometry (its times plus ``delay``) and the ground truth cover."""
    odo, gt = log.odometry.rows[:, 0], log.groundtruth.rows[:, 0]
    return float(odo[0]), max(odo[0] + delay, gt[0]), min(odo[-1] + delay, gt[-1])


def make_window(log: RobotLog, robot: int, start: float, duration: float | None, dt: float,
                delay: float = 0.0) -> Window:
    """Steps every ``dt`` seconds from ``start`` seconds after the first odometry record, for
    ``duration`` seconds (``T = floor(duration / dt)`` steps; default: to the end of the data)."""
    dt = finite(dt, "dt", "seconds")
    start = finite(start, "start", "seconds", positive=False)
    origin, first, last = data_span(log, delay)
    span = (f"robot {robot}'s data cover {first - origin:.3f} to {last - origin:.3f} s after its first "
            f"odometry record (Unix {origin:.3f} s; odometry and ground truth both)")
    if not first <= origin + start < last:
        raise MRCLAMError(f"start {start:g} s: outside the data; {span}")
    t0 = origin + start
    if duration is None:
        steps = math.floor((last - t0) / dt + 1e-9)
    else:
        duration = finite(duration, "duration", "seconds")
        steps = math.floor(duration / dt + 1e-9)
        if t0 + steps * dt > last + 1e-9:
            raise MRCLAMError(f"window {start:g} s + {duration:g} s: ends at {start + duration:.3f} s, "
                              f"after the data; {span}")
    if steps < 1:
        raise MRCLAMError(f"window from {start:g} s: holds no step of dt = {dt:g} s; {span}")
    return Window(origin, t0 + dt * np.arange(steps + 1), last)


@dataclass(frozen=True)
class Measurements:
    """The landmark measurements (n,) that a step can hold, and what was dropped on the way."""

    time: np.ndarray  # (n,) Unix s
    step: np.ndarray  # (n,) int, 1..T
    landmark: np.ndarray  # (n,) int, index into the (sorted) landmark table; -1: a robot or an unknown barcode
    raw: np.ndarray  # (n, 2) range [m], bearing [rad] as measured at `time`
    counts: dict[str, Any]


def landmark_measurements(log: RobotLog, barcodes: dict[int, int], subjects: np.ndarray,
                          window: Window, identity_filter: bool = True) -> Measurements:
    """Every measurement of step k's interval ``(t_k − dt/2, t_k + dt/2]`` (within the data), with
    counts of the robot-robot and unknown-barcode ones. ``subjects`` (L,) sorted.

    ``identity_filter`` (the oracle-assisted conversion): landmark measurements only, the others
    dropped. Otherwise every measurement is kept, those of no landmark with ``landmark = -1``.
    """
    rows = log.measurements.rows.reshape(-1, 4)
    subject = np.array([barcodes.get(int(b), -1) for b in rows[:, 1]], dtype=np.int64)
    index = np.minimum(np.searchsorted(subjects, subject), len(subjects) - 1)
    is_landmark = subjects[index] == subject
    robot = np.isin(subject, ROBOTS)
    t, t0, dt, T = rows[:, 0], window.times[0], window.dt, len(window.times) - 1
    step = np.ceil((t - t0) / dt - 0.5).astype(np.int64)
    inside = (step >= 1) & (step <= T) & (t <= window.end)
    within = (t > t0) & (t <= window.times[-1] + dt / 2)
    keep = inside & is_landmark if identity_filter else inside
    unknown = within & ~robot & ~is_landmark
    counts = {
        "in_window": int(within.sum()),
        "robot_robot": int((within & robot).sum()),
        "unknown_barcode": int(unknown.sum()),
        "unknown_barcodes": sorted({int(b) for b in rows[unknown, 1]}),
        "before_first_step": int((within & is_landmark & ~inside).sum()),
    }
    return Measurements(t[keep], step[keep], np.where(is_landmark, index, -1)[keep], rows[keep, 2:4].copy(), counts)


def compensate(m: Measurements, path_at_steps: np.ndarray, path_at_measurements: np.ndarray) -> np.ndarray:
    """``[range, bearing]`` (n, 2) of each measured point seen from the pose at its step's time
    ``t_k`` instead of from the pose at its own time; ``path_*`` are the integrated odometry."""
    offset = between(path_at_steps[m.step], path_at_measurements)  # P(t) seen from P(t_k)
    point = offset[:, :2] + _rotate(offset[:, 2], _polar(m.raw))
    return np.column_stack([np.hypot(point[:, 0], point[:, 1]), np.arctan2(point[:, 1], point[:, 0])])


def merge_repeats_of(m: Measurements, written: np.ndarray, window: Window, kept: np.ndarray, sd: np.ndarray,
                  gate: float = MERGE_GATE) -> np.ndarray:
    """The readings ``kept`` (indices, time order) without the repeats of one object within a step,
    found by geometry alone (no barcode): per step, readings in order of closeness in time to ``t_k``
    (the first in the file on a tie); one is dropped when a reading already kept in the step, taken
    at another time (another sensor frame: a frame reads each object once), lies within
    ``((Δr / sd_r)² + (Δb / sd_b)²) / 2 <= gate`` of it as written (the difference of two readings of
    one point has twice the variance of one). ``sd`` (2,) the range and bearing noise sds."""
    out = []
    for k in np.unique(m.step[kept]):
        here = kept[m.step[kept] == k]
        lag = np.abs(m.time[here] - window.times[k])
        chosen: list[int] = []
        for i in here[np.lexsort((here, lag))]:
            diff = (written[chosen] - written[i]) / sd
            diff[:, 1] = np.asarray(wrap(diff[:, 1] * sd[1])) / sd[1]
            near = 0.5 * np.sum(diff**2, axis=1) <= gate
            other_frame = np.abs(m.time[chosen] - m.time[i]) > SAME_FRAME_S
            if not np.any(near & other_frame):
                chosen.append(int(i))
        out.extend(chosen)
    return np.sort(np.array(out, dtype=np.int64))


def closest_per_landmark(m: Measurements, window: Window, keep: np.ndarray) -> np.ndarray:
    """Indices of the measurements kept: among ``keep`` (bool (n,)), per step and landmark the one
    closest in time to ``t_k`` (the first in the file on a tie), in time order."""
    candidates = np.flatnonzero(keep)
    lag = np.abs(m.time[candidates] - window.times[m.step[candidates]])
    order = candidates[np.lexsort((candidates, lag, m.landmark[candidates], m.step[candidates]))]
    pairs = np.column_stack([m.step[order], m.landmark[order]])
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(pairs[1:] != pairs[:-1], axis=1)
    return np.sort(order[first])


def default_sensor(log: RobotLog, barcodes: dict[int, int], subjects: np.ndarray, written: np.ndarray,
                   sd: np.ndarray, identity_filter: bool = True) -> tuple[float, float]:
    """``(max_range, fov)`` from the robot's whole log of measurements (``identity_filter``: of
    landmark measurements only) and the written detections (n, 2), with ``sd`` (2,) the range and
    bearing noise sds: the largest range plus 3 sds rounded up to 0.5 m, and twice the largest
    |bearing| plus 3 sds rounded up to 0.1 rad."""
    rows = log.measurements.rows.reshape(-1, 4)
    seen = (np.isin([barcodes.get(int(b), -1) for b in rows[:, 1]], subjects) if identity_filter
            else np.ones(len(rows), dtype=bool))
    rb = np.concatenate([rows[seen][:, 2:4], written])
    max_range = RANGE_STEP * math.ceil((rb[:, 0].max(initial=0.0) + 3 * sd[0]) / RANGE_STEP)
    half = np.abs(rb[:, 1]).max(initial=0.0) + 3 * sd[1]
    return float(max_range), float(min(2 * math.pi, FOV_STEP * math.ceil(2 * half / FOV_STEP)))

