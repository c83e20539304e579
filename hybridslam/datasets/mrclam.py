"""The UTIAS Multi-Robot Cooperative Localization and Mapping dataset (MRCLAM) as a scenario file.

Leung, Halpern, Barfoot & Liu, "The UTIAS multi-robot cooperative localization and mapping
dataset", IJRR 30(8), 2011. One folder per dataset: ``Barcodes.dat`` (subject, barcode),
``Landmark_Groundtruth.dat`` (subject, x, y, x sd, y sd), and per robot ``N`` in 1-5
``RobotN_Odometry.dat`` (time, v, ω), ``RobotN_Measurement.dat`` (time, barcode, range, bearing)
and ``RobotN_Groundtruth.dat`` (time, x, y, θ). Whitespace-separated columns, ``#`` comment lines
on top, CRLF line ends, times in Unix seconds; subjects 1-5 are robots, the rest landmarks.

:func:`import_mrclam` turns one robot's log into a ``hybridslam-scenario/1`` (SCENARIO_FORMAT.md):

* **Time.** Times are seconds after the robot's *first odometry record* (its log starts there:
  dead reckoning needs velocities). ``x_0`` is the pose at ``t_0 = start``, step ``k = 1..T`` at
  ``t_k = t_0 + k·dt``. The data cover ``[max(first odometry, first ground truth),
  min(last odometry, last ground truth)]``; a window outside that is an error.
* **Odometry.** Each ``(v, ω)`` sample is held until the next one (a later sample with the same
  time replaces it) and integrated exactly, as SE(2) arcs ``Exp([v·τ, 0, ω·τ])`` including the
  partial intervals at step boundaries (:func:`integrate_odometry`). ``u_k = between(P(t_{k-1}),
  P(t_k))`` of the integrated path ``P``.
* **Detections, without identities** (the default). A measurement at time ``t`` belongs to step
  ``k`` when ``t_k − dt/2 < t ≤ t_k + dt/2``. Every measurement of the robot's file in a step's
  window is a detection: those of other robots and of barcodes that name no landmark too (with no
  ``true_object``; counted in ``generator.counts``). The sensor reads an object up to twice per
  0.5 s step (its frames come ~0.24 s apart); every repeat is kept by default (the clutter
  hypothesis below explains the one an object cannot take). ``merge_repeats=True`` merges them
  by geometry alone (:func:`merge_repeats_of`): per step, in order of closeness in time to
  ``t_k``, a reading is dropped when one already kept from another sensor frame lies within the
  0.99 chi-square gate of it (the difference of two readings, twice the calibrated variance).
  Fewer detections (dataset 6, robot 3, 20-120 s: at most 10 per step instead of 16), but it
  drops readings of neighbouring landmarks 0.2 m away (robot 2: 19 of 155 landmark-step pairs
  lost) and keeps repeats that the motion compensation moved apart (e.g. while turning). The file declares a clutter hypothesis, ``sensor.clutter_log_density =
  log(0.5 / (max_range · fov))``: a reading is spurious (another robot, a repeat) with prior
  probability 0.5 (dataset 6, robots 2 and 3, 20-120 s: 29-30% of the readings are other
  robots' and 17-20% repeat a landmark in the same step), uniform over the footprint in ``[range, bearing]``
  (the space of ``new_object_log_density``, below). Barcodes serve only ``true_object``
  (evaluation) and the noise calibration (below: the readings a barcode names a landmark of);
  ``generator.identities`` says so.
* **Detections, oracle-assisted** (``identity_filter=True``, ``--identity-filter``): landmark
  measurements only (robot-robot ones and barcodes that name no landmark are dropped and
  counted), and per step and landmark the one closest in time to ``t_k``: the barcodes select
  and de-duplicate the detections, identities the estimators are meant not to know. No clutter
  field is written (none is left).
* **Motion compensation.** Each detection is *motion-compensated* to ``t_k`` (default): the landmark point it measured from
  ``P(t)`` is re-expressed from ``P(t_k)`` with the integrated odometry, since a detection taken
  0.25 s before ``t_k`` while turning at 0.5 rad/s is otherwise 0.13 rad off in bearing
  (``motion_compensation=False`` writes the raw range and bearing). Barcodes carry no class, so
  ``num_classes`` is 1, the classifier ``none`` and every ``scores`` ``[1.0]``.
* **Ground truth.** ``robot.true_poses`` is the ground truth interpolated at ``t_0..t_T``
  (linear in x, y and the unwrapped heading, then wrapped); ``true_object`` is the landmark's
  index in subject order (the file's order: subject 6 is index 0).
* **Map.** Known (default): every surveyed landmark is an object with ``prior_mean [x, y, 0]``
  and ``prior_cov = diag(x sd², y sd², landmark_heading_var)``. A landmark is a point (a
  cylinder): its heading is not observed by range and bearing, so its variance is π² (about
  uniform on the circle, as ``new_object_orientation_var`` in the hallway); the survey sds
  (40-650 µm) are floored at ``landmark_sd_floor`` (1 cm) so that the 3×3 prior stays well
  conditioned next to π². Unknown (``unknown_map=True``): no objects, a ``discovery`` section and
  the landmarks under ``true_objects``, and ``max_objects`` object slots: by default the most
  detections in one step plus ``discovery_margin`` (10), so that every detection of the busiest
  step could be a new object (with ``identity_filter``: the surveyed landmarks plus the margin).
* **Noise**, calibrated from the ground truth of the same window (override any with the
  arguments: given ``geometric_cov``, no barcode is read for it). The measurement noise uses the
  detections whose barcode names a landmark (the surveyed point they measured), the only use of
  barcodes besides ``true_object``; ``generator.identities.barcodes_used_for`` lists it. Residuals: odometry ``Log(u_k⁻¹ ∘ between(g_{k-1}, g_k))`` per step with ``g`` the
  interpolated ground truth; measurements (``measurement_noise_from="written"``, the default)
  ``[range, bearing]`` of each detection *as written* (motion-compensated to its step time ``t_k``)
  minus the range and bearing of its surveyed landmark from the ground-truth pose at ``t_k``: the
  error an estimator with exact poses sees, the compensation's own error (the odometry commands'
  error over up to ``dt/2``) included. ``"raw"`` uses each kept raw measurement against the
  ground-truth pose at the measurement's own time instead, the sensor alone: on dataset 7 its
  bearing sd is 1.3-2.1× smaller than the written detections' (robots 1, 3, 5) and so
  overconfident for the files written. Per component the robust location ``median`` and scale
  ``1.4826·MAD`` (MAD about the median: the sd of a Gaussian, unmoved by the 1-3% gross outliers
  of mis-read barcodes), and the variance written is ``scale² + median²``, the robust mean
  square about zero: an estimator takes the noise as zero-mean, so an uncorrected bias must be
  covered by the variance. MRCLAM ranges are biased (the median residual is reported as
  ``range_bias``); ``correct_range_bias=True`` subtracts it from the ranges instead.

What the data hold (datasets 6 and 7, all robots), and what the import does about it:

* The odometry is velocity *commands*, not wheel odometry. The ground truth follows them
  ~0.17 s later (``odometry_delay`` shifts them; default 0, the data as logged) and the
  commanded distance is 4-12% longer than the true one over a whole log. The per-step errors are
  therefore correlated in time: summed over 5 s they grow 2.7-5.9× (forward) and 1.7-3.3×
  (heading) faster than the calibrated per-step sd (200 s windows), and dead reckoning drifts
  accordingly. ``generator.calibration.odometry_drift_sd_per_step``
  reports it; ``motion_noise_from="drift"`` writes a ``motion_cov`` that grows as fast (on
  dataset 7's unknown map it halves the duplicate landmarks; on the known map it costs accuracy:
  docs/studies/mrclam.md).
* Odometry records have gaps of up to ~1 s (the last command is held) and duplicated times;
  the ground truth of some robots ends minutes before their odometry (dataset 6, robot 1).
  ``generator.data`` holds the longest gaps in the window.
* Range errors have sd 7-18 cm and a median of −2 to +7 cm depending on the robot; bearings
  0.006-0.018 rad, robot 4's biased by −0.01 to −0.02 rad. Landmarks stand in clusters
  0.18-0.33 m apart: ambiguous associations.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..io.scenario import Classifier, Detection, Discovery, Scenario, Step
from .textfile import read_ascii

ROBOTS = (1, 2, 3, 4, 5)  # MRCLAM subjects 1-5 are robots
NOISE_SOURCES = ("written", "raw")  # what geometric_cov is calibrated from (import_mrclam)
MOTION_NOISE_SOURCES = ("steps", "drift")  # what motion_cov is calibrated from (import_mrclam)
MAD_TO_SD = 1.4826  # 1 / Φ⁻¹(3/4): MAD · this is the sd of a Gaussian
ROBOT_PRIOR_VAR = 1e-4  # x_0 is the ground truth: it anchors the world frame (m², m², rad²)
MOTION_SD_FLOOR = 1e-4  # m, m, rad per step: keeps the calibrated covariance positive definite
GEOMETRIC_SD_FLOOR = 1e-3  # m, rad
RANGE_STEP, FOV_STEP = 0.5, 0.1  # default max_range and fov round up to these (m, rad)
DRIFT_BLOCK_S, MIN_BLOCKS = 5.0, 5  # the drift check sums odometry residuals over 5 s blocks
MERGE_GATE = 9.21  # chi-square (2 dof) 0.99 quantile: two readings this close are one object's (merge_repeats)
SAME_FRAME_S = 1e-3  # readings this close in time are one sensor frame (never merged)
CLUTTER_FRACTION = 0.5  # default prior probability that a reading is spurious (import_mrclam, Clutter)


class MRCLAMError(ValueError):
    """A missing or malformed MRCLAM file, or an import setting the data cannot serve. One line."""


@dataclass(frozen=True)
class Table:
    """The numbers of one ``.dat`` file: ``rows`` (n, columns) and the 1-based line of each row."""

    path: str
    rows: np.ndarray
    lines: np.ndarray


@dataclass(frozen=True)
class RobotLog:
    """One robot's three files; times in Unix seconds."""

    odometry: Table  # time, v [m/s], ω [rad/s]
    measurements: Table  # time, barcode, range [m], bearing [rad]
    groundtruth: Table  # time, x [m], y [m], θ [rad]


# --------------------------------------------------------------------------- #
# Reading
# --------------------------------------------------------------------------- #


def read_table(path: str, columns: int, what: str) -> Table:
    """The numeric rows of a ``.dat`` file; ``#`` lines and blank lines are skipped.

    ``what`` names the columns for messages. Raises :class:`MRCLAMError` naming the file (and the
    line) when it is missing, unreadable or holds a line that is not ``columns`` finite numbers.
    """
    rows, lines = [], []
    for lineno, line in enumerate(read_ascii(path, MRCLAMError).split("\n"), 1):
        text = line.strip()
        if text and not text.startswith("#"):
            rows.append(_numbers(text, columns, what, path, lineno))
            lines.append(lineno)
    return Table(path, np.array(rows, dtype=np.float64).reshape(len(rows), columns), np.array(lines))


def _numbers(text: str, columns: int, what: str, path: str, lineno: int) -> list[float]:
    parts = text.split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(parts) != columns or len(values) != columns or not all(map(math.isfinite, values)):
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise MRCLAMError(f"{path}:{lineno}: expected {columns} numbers ({what}), got {shown!r}")
    return values


def _check_times(table: Table, allow_empty: bool = False) -> None:
    """Times (column 0) must not decrease: the files are logs in time order."""
    t = table.rows[:, 0]
    if not len(t) and not allow_empty:
        raise MRCLAMError(f"{table.path}: no records")
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        i = back[0] + 1
        raise MRCLAMError(f"{table.path}:{table.lines[i]}: time {t[i]:.3f} is before the previous "
                          f"record's {t[i - 1]:.3f} (records must be in time order)")


def read_barcodes(dataset_dir: str) -> dict[int, int]:
    """``Barcodes.dat`` as ``{barcode: subject}``."""
    table = read_table(os.path.join(dataset_dir, "Barcodes.dat"), 2, "subject, barcode")
    return {int(b): int(s) for s, b in table.rows}


def read_landmarks(dataset_dir: str) -> Table:
    """``Landmark_Groundtruth.dat``: rows (subject, x, y, x sd, y sd) [m], subjects unique and > 5."""
    table = read_table(os.path.join(dataset_dir, "Landmark_Groundtruth.dat"), 5, "subject, x, y, x sd, y sd")
    seen: set[int] = set()
    for (subject, *_), line in zip(table.rows, table.lines):
        if subject in seen or subject in ROBOTS or subject != int(subject):
            raise MRCLAMError(f"{table.path}:{line}: subject {subject:g} is a robot, not an integer, "
                              "or listed twice")
        seen.add(subject)
    if not seen:
        raise MRCLAMError(f"{table.path}: no landmarks")
    return table


def read_robot(dataset_dir: str, robot: int) -> RobotLog:
    """Robot ``robot``'s odometry, measurements and ground truth, each checked to be in time order."""
    if robot not in ROBOTS:
        raise MRCLAMError(f"robot {robot}: no such robot (MRCLAM robots are 1-5)")
    name = os.path.join(dataset_dir, f"Robot{robot}_")
    tables = []
    for suffix, columns, what in (("Odometry", 3, "time, v, omega"),
                                  ("Measurement", 4, "time, barcode, range, bearing"),
                                  ("Groundtruth", 4, "time, x, y, theta")):
        path = f"{name}{suffix}.dat"
        if not os.path.exists(path):
            raise MRCLAMError(f"{path}: no such file (robot {robot} has no {suffix.lower()} log)")
        table = read_table(path, columns, what)
        _check_times(table, allow_empty=suffix == "Measurement")  # a robot may see nothing
        tables.append(table)
    return RobotLog(*tables)


# --------------------------------------------------------------------------- #
# SE(2) on arrays of poses (N, 3): numpy, no JAX compiles (conventions of se2.py)
# --------------------------------------------------------------------------- #


def wrap(angle: np.ndarray | float) -> np.ndarray | float:
    """Angles (rad) wrapped to (-π, π]."""
    return np.pi - np.mod(np.pi - np.asarray(angle, dtype=np.float64), 2.0 * np.pi)


def _rotate(theta: np.ndarray, xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ∘ b`` for poses (..., 3)."""
    t = a[..., :2] + _rotate(a[..., 2], b[..., :2])
    return np.concatenate([t, wrap(a[..., 2:] + b[..., 2:])], axis=-1)


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ∘ b`` for poses (..., 3): ``b`` seen from ``a``."""
    t = _rotate(-a[..., 2], b[..., :2] - a[..., :2])
    return np.concatenate([t, wrap(b[..., 2:] - a[..., 2:])], axis=-1)


def _arc_coeffs(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sin(t)/t`` and ``(1 − cos t)/t``, with Taylor series below 1e-4 rad (no 0/0)."""
    small = np.abs(theta) < 1e-4
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, theta / 2.0 - theta**3 / 24.0, (1.0 - np.cos(safe)) / safe)
    return a, b


def log(p: np.ndarray) -> np.ndarray:
    """SE(2) logarithm of poses (..., 3): the tangent ``[v_x, v_y, ω]`` with ``Exp`` of it ``p``."""
    theta = np.asarray(wrap(p[..., 2]))
    a, b = _arc_coeffs(theta)
    det = a * a + b * b
    x, y = p[..., 0], p[..., 1]
    return np.stack([(a * x + b * y) / det, (-b * x + a * y) / det, theta], axis=-1)


# --------------------------------------------------------------------------- #
# Odometry and ground truth
# --------------------------------------------------------------------------- #


def integrate_odometry(times: np.ndarray, v: np.ndarray, omega: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses (Q, 3) at the sorted times ``query`` (Q,) of the path the velocity samples drive,
    relative to the pose at ``query[0]`` (the identity there).

    ``times`` (n,) [s] non-decreasing, ``v`` (n,) [m/s], ``omega`` (n,) [rad/s]. Sample ``i`` is
    held on ``[times[i], times[i+1])`` (the last one from then on; of samples with equal times the
    last counts); before ``times[0]`` nothing is known, so ``query[0] >= times[0]``. On each piece
    of constant ``(v, ω)`` between consecutive breakpoints (sample times and query times) the
    motion is the exact arc ``Exp([v·τ, 0, ω·τ])``; headings accumulate unwrapped, then wrap.
    """
    times, query = np.asarray(times, np.float64), np.asarray(query, np.float64)
    if query[0] < times[0]:
        raise ValueError(f"query starts at {query[0]}, before the first sample at {times[0]}")
    inner = times[(times > query[0]) & (times < query[-1])]
    breaks = np.sort(np.concatenate([query, inner]))
    active = np.searchsorted(times, breaks[:-1], side="right") - 1
    tau = np.diff(breaks)
    dist, turn = np.asarray(v)[active] * tau, np.asarray(omega)[active] * tau
    a, b = _arc_coeffs(turn)
    heading = np.concatenate([[0.0], np.cumsum(turn)])
    step = _rotate(heading[:-1], np.stack([a * dist, b * dist], axis=-1))
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    at = np.searchsorted(breaks, query, side="left")  # equal breakpoints hold the same pose
    return np.column_stack([xy[at], wrap(heading[at])])


def interpolate_groundtruth(groundtruth: np.ndarray, times: ArrayLike) -> np.ndarray:
    """Poses (Q, 3) at ``times`` (Q,) [s], linear in x, y and the unwrapped heading, then wrapped.

    ``groundtruth`` (n, 4): time, x, y, θ, times non-decreasing; ``times`` within its span.
    """
    t, q = groundtruth[:, 0], np.asarray(times, dtype=float)
    heading = np.unwrap(groundtruth[:, 3])
    cols = [np.interp(q, t, groundtruth[:, i]) for i in (1, 2)]
    return np.column_stack([*cols, np.asarray(wrap(np.interp(q, t, heading)))])


def range_bearing(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``[range, bearing]`` (N, 2) of points (N, 2) seen from poses (N, 3) (SCENARIO_FORMAT.md)."""
    q = _rotate(-poses[:, 2], points - poses[:, :2])
    return np.column_stack([np.hypot(q[:, 0], q[:, 1]), np.arctan2(q[:, 1], q[:, 0])])


def _polar(rb: np.ndarray) -> np.ndarray:
    return rb[:, :1] * np.column_stack([np.cos(rb[:, 1]), np.sin(rb[:, 1])])


# --------------------------------------------------------------------------- #
# The window and the detections
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class Window:
    """The imported stretch of one robot's log. Times in Unix seconds."""

    origin: float  # the robot's first odometry record: ``start`` counts from here
    times: np.ndarray  # (T + 1,) t_0..t_T
    end: float  # the end of the data (odometry and ground truth)

    @property
    def dt(self) -> float:
        return float(self.times[1] - self.times[0])


def _finite(value: Any, name: str, unit: str, positive: bool = True) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0):
        raise MRCLAMError(f"{name}: expected a {'positive' if positive else 'finite'} number of {unit}, "
                          f"got {value!r}")
    return float(value)


def data_span(log: RobotLog, delay: float = 0.0) -> tuple[float, float, float]:
    """``(origin, first, last)`` [Unix s]: the robot's first odometry record as logged, and the
    span that both the odometry (its times plus ``delay``) and the ground truth cover."""
    odo, gt = log.odometry.rows[:, 0], log.groundtruth.rows[:, 0]
    return float(odo[0]), max(odo[0] + delay, gt[0]), min(odo[-1] + delay, gt[-1])


def make_window(log: RobotLog, robot: int, start: float, duration: float | None, dt: float,
                delay: float = 0.0) -> Window:
    """Steps every ``dt`` seconds from ``start`` seconds after the first odometry record, for
    ``duration`` seconds (``T = floor(duration / dt)`` steps; default: to the end of the data)."""
    dt = _finite(dt, "dt", "seconds")
    start = _finite(start, "start", "seconds", positive=False)
    origin, first, last = data_span(log, delay)
    span = (f"robot {robot}'s data cover {first - origin:.3f} to {last - origin:.3f} s after its first "
            f"odometry record (Unix {origin:.3f} s; odometry and ground truth both)")
    if not first <= origin + start < last:
        raise MRCLAMError(f"start {start:g} s: outside the data; {span}")
    t0 = origin + start
    if duration is None:
        steps = math.floor((last - t0) / dt + 1e-9)
    else:
        duration = _finite(duration, "duration", "seconds")
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


# --------------------------------------------------------------------------- #
# Calibration
# --------------------------------------------------------------------------- #


def robust_location_scale(residuals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column of ``residuals`` (n, d): the median and ``1.4826 · median |r − median|``."""
    median = np.median(residuals, axis=0)
    return median, MAD_TO_SD * np.median(np.abs(residuals - median), axis=0)


def robust_variance(residuals: np.ndarray, floor: float) -> np.ndarray:
    """Per column (d,): ``scale² + median²``, the robust mean square about zero, at least ``floor²``."""
    median, scale = robust_location_scale(residuals)
    return np.maximum(scale**2 + median**2, floor**2)


def drift_per_step(residuals: np.ndarray, block: int) -> np.ndarray | None:
    """The per-step sd (d,) that the sums of ``residuals`` (T, d) over blocks of ``block`` steps
    imply, ``sqrt(mean(block sum²) / block)``; None with fewer than ``MIN_BLOCKS`` blocks.

    For white noise it equals the per-step RMS; larger, the errors are correlated in time (a
    velocity scale error, command latency) and dead reckoning drifts faster than the per-step
    covariance says.
    """
    n = len(residuals) // block
    if n < MIN_BLOCKS:
        return None
    sums = residuals[: n * block].reshape(n, block, -1).sum(axis=1)
    return np.sqrt(np.mean(sums**2, axis=0) / block)


def odometry_residuals(odometry: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``Log(u_k⁻¹ ∘ between(g_{k-1}, g_k))`` (T, 3) for odometry (T, 3) and true poses (T + 1, 3)."""
    return log(between(odometry, between(truth[:-1], truth[1:])))


def measurement_residuals(measured: np.ndarray, poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``z − h(pose, point)`` (n, 2), the bearing wrapped; ``measured`` (n, 2) [range, bearing]."""
    r = measured - range_bearing(poses, points)
    return np.column_stack([r[:, 0], wrap(r[:, 1])])


def _covariance(value: Any, n: int, name: str) -> np.ndarray | None:
    """A user's covariance: ``None``, ``n`` variances (diagonal) or an n×n SPD matrix."""
    if value is None:
        return None
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise MRCLAMError(f"{name}: expected {n} variances or a {n}x{n} matrix, got {value!r}") from None
    m = np.diag(m) if m.shape == (n,) else m
    if m.shape != (n, n) or not np.all(np.isfinite(m)):
        raise MRCLAMError(f"{name}: expected {n} finite variances or a {n}x{n} matrix, got shape {m.shape}")
    try:
        if not np.allclose(m, m.T):
            raise np.linalg.LinAlgError
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        raise MRCLAMError(f"{name}: not symmetric positive definite") from None
    return m


def _stats(residuals: np.ndarray) -> dict[str, Any]:
    """Median and robust scale per component, for the ``generator`` metadata."""
    if not len(residuals):
        return {"count": 0}
    median, scale = robust_location_scale(residuals)
    return {"count": len(residuals), "median": _floats(median), "scale": _floats(scale)}


def _drift_block(dt: float) -> int:
    """Steps of ``dt`` seconds in one drift block of :data:`DRIFT_BLOCK_S`."""
    return max(1, round(DRIFT_BLOCK_S / dt))


def _drift(residuals: np.ndarray, dt: float) -> dict[str, Any] | None:
    block = _drift_block(dt)
    sd = drift_per_step(residuals, block)
    return None if sd is None else {"block_steps": block, "sd": _floats(sd)}


def _floats(a: Any) -> Any:
    return np.round(np.asarray(a, dtype=np.float64), 9).tolist()


# --------------------------------------------------------------------------- #
# The importer
# --------------------------------------------------------------------------- #


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


def _max_gap(times: np.ndarray, lo: float, hi: float) -> float:
    """The longest time without a record within [lo, hi] (s), its ends counted as records."""
    t = np.concatenate([[lo], times[(times > lo) & (times < hi)], [hi]])
    return float(np.diff(t).max())


def _check_settings(max_range: Any, fov: Any, landmark_sd_floor: Any, landmark_heading_var: Any,
                    discovery_margin: Any, new_object_log_density: Any, odometry_delay: Any) -> None:
    if max_range is not None:
        _finite(max_range, "max_range", "metres")
    if fov is not None and not 0 < _finite(fov, "fov", "radians") <= 2 * math.pi:
        raise MRCLAMError(f"fov: expected radians in (0, 2*pi], got {fov!r}")
    _finite(landmark_sd_floor, "landmark_sd_floor", "metres")
    _finite(landmark_heading_var, "landmark_heading_var", "rad^2")
    _finite(odometry_delay, "odometry_delay", "seconds", positive=False)
    if new_object_log_density is not None:
        _finite(new_object_log_density, "new_object_log_density", "nats", positive=False)
    if not isinstance(discovery_margin, int) or isinstance(discovery_margin, bool) or discovery_margin < 0:
        raise MRCLAMError(f"discovery_margin: expected a non-negative integer, got {discovery_margin!r}")


def import_mrclam(
    dataset_dir: str | os.PathLike,
    robot: int,
    *,
    start: float = 0.0,
    duration: float | None = None,
    dt: float = 0.5,
    unknown_map: bool = False,
    max_range: float | None = None,
    fov: float | None = None,
    motion_cov: Any = None,
    geometric_cov: Any = None,
    robot_prior_cov: Any = None,
    correct_range_bias: bool = False,
    motion_compensation: bool = True,
    odometry_delay: float = 0.0,
    measurement_noise_from: str = "written",
    motion_noise_from: str = "steps",
    landmark_sd_floor: float = 0.01,
    landmark_heading_var: float = math.pi**2,
    discovery_margin: int = 10,
    new_object_log_density: float | None = None,
    max_objects: int | None = None,
    identity_filter: bool = False,
    merge_repeats: bool = False,
    clutter_log_density: float | str | None = None,
) -> Scenario:
    """Robot ``robot``'s log in the MRCLAM dataset folder ``dataset_dir`` as a ``hybridslam-scenario/1``.

    See the module docstring for what is written and how. Arguments:

    * ``start`` [s] after the robot's first odometry record, ``duration`` [s] (default: to the end
      of the data), one step every ``dt`` [s]: ``T = floor(duration / dt)`` steps.
    * ``identity_filter``: the oracle-assisted conversion (module docstring); default ``False``:
      every reading. ``merge_repeats`` (default ``False``, without the filter): merge the repeats
      of an object within a step by geometry (:func:`merge_repeats_of`). ``clutter_log_density``:
      ``sensor.clutter_log_density`` written (default ``log(0.5 / (max_range · fov))``, none with
      the filter; ``"none"``: none).
    * ``unknown_map``: no prior objects, a ``discovery`` section with ``max_objects`` = the most
      detections in a step (the number of surveyed landmarks with ``identity_filter``) +
      ``discovery_margin`` (or ``max_objects``, when given: every duplicate of a
      landmark takes a slot too, and once they are full a new landmark is not stored: every
      estimator weighs its detections as unmapped objects, and warns) and ``new_object_log_density`` (default
      ``−log(max_range · fov)``: a new object's detection uniform over the sensor footprint in
      ``[range, bearing]`` coordinates, the space of the Gaussian ``N(z; h, Σ_v)`` it competes
      with, as in the hallway; ``−log(max_range² · fov / 2)`` would be a density per square
      metre, off by the Jacobian ``r``), ``new_object_orientation_var = landmark_heading_var``.
    * ``max_range`` [m], ``fov`` [rad]: the sensor written; a detection beyond them (as written)
      is dropped. Default from the data (:func:`default_sensor`), nothing dropped.
    * ``motion_cov`` (3 variances [m², m², rad²] or 3×3), ``geometric_cov`` (2 [m², rad²] or 2×2),
      ``robot_prior_cov`` (3 or 3×3; default ``1e-4·I``): replace the calibrated / default ones.
    * ``correct_range_bias``: subtract the median range residual from the written ranges.
    * ``motion_compensation``: re-express each detection from ``x_k`` (default) or write it raw.
    * ``odometry_delay`` [s]: added to the odometry times. The velocities are *commands*: the
      ground truth follows them ~0.17 s later, and a delay of that size shrinks the heading
      residuals by a quarter to a third. Default 0 (the data as logged); the time origin stays
      the logged first odometry record.
    * ``measurement_noise_from``: ``"written"`` (default) calibrates ``geometric_cov`` from the
      detections as written, at their step times; ``"raw"`` from the raw measurements at their
      own times (module docstring, Noise).
    * ``motion_noise_from``: ``"steps"`` (default) calibrates ``motion_cov`` from the per-step
      odometry residuals; ``"drift"`` takes per component the larger of that and the variance per
      step that their sums over 5 s imply (``generator.calibration.odometry_drift_sd_per_step``), so
      that dead reckoning's covariance grows as fast as its error does over seconds (the errors
      are correlated in time: module docstring). Needs a window of at least 25 s.

    Everything the import measured (calibration, counts, dead-reckoning error, data gaps) is in
    ``scenario.metadata["generator"]``. Raises :class:`MRCLAMError` (one line naming the file and
    line, the robot, the window or the setting) for anything the data cannot serve.
    """
    folder = os.fspath(dataset_dir)
    if not os.path.isdir(folder):
        raise MRCLAMError(f"{folder}: not a dataset folder (no such directory)")
    _check_settings(max_range, fov, landmark_sd_floor, landmark_heading_var, discovery_margin,
                    new_object_log_density, odometry_delay)
    if motion_noise_from not in MOTION_NOISE_SOURCES:
        raise MRCLAMError(f"motion_noise_from: expected one of {', '.join(MOTION_NOISE_SOURCES)}, "
                          f"got {motion_noise_from!r}")
    if measurement_noise_from not in NOISE_SOURCES:
        raise MRCLAMError(f"measurement_noise_from: expected one of {', '.join(NOISE_SOURCES)}, "
                          f"got {measurement_noise_from!r}")
    if max_objects is not None:
        if not unknown_map:
            raise MRCLAMError("max_objects: object slots are a setting of an unknown map "
                              "(unknown_map=True, --unknown-map)")
        if not isinstance(max_objects, int) or isinstance(max_objects, bool) or max_objects < 2:
            raise MRCLAMError(f"max_objects: expected an integer >= 2, got {max_objects!r}")
    given = {"motion_cov": _covariance(motion_cov, 3, "motion_cov"),
             "geometric_cov": _covariance(geometric_cov, 2, "geometric_cov"),
             "robot_prior_cov": _covariance(robot_prior_cov, 3, "robot_prior_cov")}
    barcodes, landmarks = read_barcodes(folder), read_landmarks(folder).rows
    landmarks = landmarks[np.argsort(landmarks[:, 0])]  # subject order: searchsorted needs it
    log_ = read_robot(folder, robot)
    window = make_window(log_, robot, start, duration, dt, odometry_delay)
    track = _track(log_, barcodes, landmarks, window, odometry_delay, motion_compensation, max_range, fov,
                   identity_filter)
    noise = _calibrate(track, log_, landmarks, given, robot, correct_range_bias, measurement_noise_from,
                       motion_noise_from, window.dt)
    sd = np.sqrt(np.diag(noise.geometric))
    if merge_repeats and not identity_filter:
        merged = merge_repeats_of(track.measurements, track.written, window, track.kept, sd)
        track.measurements.counts.update(merged=int(len(track.kept) - len(merged)), kept=len(merged))
        track = replace(track, kept=merged)
    default = default_sensor(log_, barcodes, landmarks[:, 0], track.written[track.kept], sd, identity_filter)
    max_range = default[0] if max_range is None else float(max_range)
    fov = default[1] if fov is None else float(fov)
    clutter = _clutter_density(clutter_log_density, identity_filter, max_range, fov)
    steps = _steps(track)
    # The oracle-assisted conversion sizes an unknown map from the surveyed landmarks; otherwise from
    # the data alone: the busiest step's detections could all be new objects, plus the margin.
    slots = max_objects if max_objects is not None else len(landmarks) + discovery_margin if identity_filter \
        else max(2, max((len(st.detections) for st in steps), default=0) + discovery_margin)
    slots_from = ("given" if max_objects is not None else "landmarks + margin (oracle)" if identity_filter
                  else "most detections in a step + margin")

    settings = {"robot": int(robot), "start_s": float(start), "map": "unknown" if unknown_map else "known",
                "motion_compensation": bool(motion_compensation), "odometry_delay_s": float(odometry_delay),
                "range_bias_corrected": bool(correct_range_bias)}
    generator = _generator(folder, settings, window, track, noise, given, landmarks, log_)
    generator["identities"] = {
        "identity_filter": bool(identity_filter),
        "detections": ("landmark readings only, one per landmark and step (barcodes: oracle-assisted)"
                       if identity_filter else "every reading in the step window"
                       + (", repeats merged by geometry (merge_repeats)" if merge_repeats else ", repeats kept")),
        "barcodes_used_for": ["true_object"] + (["selecting detections", "object slots"] if identity_filter else [])
                             + ([] if given["geometric_cov"] is not None and not correct_range_bias
                                else ["measurement noise calibration"]),
    }
    if unknown_map:
        generator["object_slots"] = {"value": int(slots), "from": slots_from}
    if clutter is not None:
        generator["clutter"] = {"log_density": clutter, "from": "given" if clutter_log_density is not None
                                else f"log({CLUTTER_FRACTION:g} / (max_range * fov))"}
    prior_cov = given["robot_prior_cov"]
    common = dict(
        num_classes=1, robot_prior_mean=track.truth[0].copy(),
        robot_prior_cov=ROBOT_PRIOR_VAR * np.eye(3) if prior_cov is None else prior_cov,
        motion_cov=noise.motion, geometric_cov=noise.geometric, classifier=Classifier("none"),
        max_range=max_range, fov=fov, steps=steps, true_robot_poses=track.truth,
        clutter_log_density=clutter, metadata={"generator": generator},
    )
    poses = np.column_stack([landmarks[:, 1:3], np.zeros(len(landmarks))])
    if unknown_map:
        density = -math.log(max_range * fov) if new_object_log_density is None else new_object_log_density
        return Scenario(
            object_prior_means=np.zeros((0, 3)), object_prior_covs=np.zeros((0, 3, 3)),
            class_prior=np.zeros((0, 1)),
            discovery=Discovery(int(slots), float(density),
                                float(landmark_heading_var)),
            true_objects=tuple((p, 0) for p in poses), **common)
    return Scenario(
        object_prior_means=poses.copy(),
        object_prior_covs=landmark_covariances(landmarks[:, 3:5], landmark_sd_floor, landmark_heading_var),
        class_prior=np.ones((len(landmarks), 1)), true_object_poses=poses,
        true_classes=np.zeros(len(landmarks), dtype=np.int64), **common)


def _clutter_density(value: float | str | None, identity_filter: bool, max_range: float, fov: float) -> float | None:
    """``sensor.clutter_log_density`` to write: ``value`` (a number; ``"none"``: none), or by default
    ``log(CLUTTER_FRACTION / (max_range · fov))`` (none with the identity filter)."""
    if isinstance(value, str):
        if value != "none":
            raise MRCLAMError(f"clutter_log_density: expected a finite number or 'none', got {value!r}")
        return None
    if value is not None:
        return _finite(value, "clutter_log_density", "nats", positive=False)
    return None if identity_filter else round(math.log(CLUTTER_FRACTION / (max_range * fov)), 9)


@dataclass(frozen=True)
class Track:
    """The window's integrated odometry, ground truth and detections."""

    path: np.ndarray  # (T + 1, 3) integrated odometry at t_0..t_T, identity at t_0
    odometry: np.ndarray  # (T, 3) u_k
    truth: np.ndarray  # (T + 1, 3) ground truth at t_0..t_T
    measurements: Measurements
    written: np.ndarray  # (n, 2) [range, bearing] as written (compensated or raw) for every measurement
    kept: np.ndarray  # (m,) indices of the measurements written, in time order


def _track(log: RobotLog, barcodes: dict[int, int], landmarks: np.ndarray, window: Window, delay: float,
           motion_compensation: bool, max_range: float | None, fov: float | None,
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


def _calibrate(track: Track, log: RobotLog, landmarks: np.ndarray, given: dict[str, np.ndarray | None],
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
            drift = drift_per_step(odometry, _drift_block(dt))
            if drift is None:
                raise MRCLAMError(f"robot {robot}: motion_noise_from drift needs {MIN_BLOCKS} blocks of "
                                  f"{DRIFT_BLOCK_S:g} s of odometry in the window; give a longer window (duration) "
                                  "or motion_noise_from 'steps'")
            motion = np.diag(np.maximum(np.diag(motion), drift**2))
    if geometric is None:
        geometric = np.diag(robust_variance(sensor, GEOMETRIC_SD_FLOOR))
    return Noise(motion, geometric, odometry, sensor, raw, range_bias, source, motion_source)


def _generator(folder: str, settings: dict[str, Any], window: Window, track: Track, noise: Noise,
               given: dict[str, np.ndarray | None], landmarks: np.ndarray, log: RobotLog) -> dict[str, Any]:
    """The ``generator`` metadata: settings, calibration, counts, dead reckoning, data gaps.

    ``written_detection_residuals`` are the detections as written against the true pose at their
    step (what an estimator with perfect poses would see, timing and compensation included).
    """
    truth, meas = track.truth, track.measurements
    kept = track.kept[meas.landmark[track.kept] >= 0]
    points = landmarks[meas.landmark[kept], 1:3]
    written = measurement_residuals(track.written[kept], truth[meas.step[kept]], points)
    dead_reckoning = compose(np.broadcast_to(truth[0], track.path.shape), track.path)
    error = dead_reckoning[-1] - truth[-1]
    lo, hi = window.times[0], window.times[-1]
    delay = settings["odometry_delay_s"]
    return {
        "name": "hybridslam.datasets.mrclam",
        "dataset": os.path.basename(os.path.normpath(os.path.abspath(folder))),
        "robot": settings["robot"], "start_s": settings["start_s"], "dt_s": window.dt,
        "duration_s": round(float(hi - lo), 9), "time_origin_unix_s": window.origin, "t0_unix_s": float(lo),
        "map": settings["map"], "motion_compensation": settings["motion_compensation"],
        "odometry_delay_s": delay,
        "calibration": {
            "method": "per component: median and 1.4826*MAD about the median; variance = scale^2 + "
                      "median^2 (robust mean square about zero), diagonal; residuals against the "
                      "ground truth of the imported window (odometry: per step; measurements: "
                      + ("the detections as written, against the ground-truth pose at their step "
                         "time" if noise.source == "written" else "raw, against the ground-truth pose "
                         "at the measurement time") + ", and the surveyed landmark)",
            "measurement_noise_from": noise.source,
            "motion_noise_from": noise.motion_source,
            "motion_cov": "calibrated" if given["motion_cov"] is None else "given",
            "geometric_cov": "calibrated" if given["geometric_cov"] is None else "given",
            "odometry_residuals": _stats(noise.odometry_residuals),
            "odometry_drift_sd_per_step": _drift(noise.odometry_residuals, window.dt),
            "measurement_residuals": _stats(noise.sensor_residuals),
            "raw_measurement_residuals": _stats(noise.raw_residuals),
            "range_bias_m": round(noise.range_bias, 9),
            "range_bias_corrected": settings["range_bias_corrected"],
            "written_detection_residuals": _stats(written),
        },
        "counts": track.measurements.counts,
        "dead_reckoning": {
            "final_position_error_m": round(float(np.hypot(error[0], error[1])), 9),
            "final_heading_error_rad": round(float(wrap(error[2])), 9),
            "path_length_m": round(float(np.sum(np.hypot(*np.diff(truth[:, :2], axis=0).T))), 9),
        },
        "data": {
            "odometry_max_gap_s": round(_max_gap(log.odometry.rows[:, 0] + delay, lo, hi), 6),
            "groundtruth_max_gap_s": round(_max_gap(log.groundtruth.rows[:, 0], lo, hi), 6),
        },
    }


def landmark_covariances(sd: np.ndarray, floor: float, heading_var: float) -> np.ndarray:
    """``diag(max(x sd, floor)², max(y sd, floor)², heading_var)`` (L, 3, 3) for survey sds (L, 2) [m]."""
    var = np.maximum(sd, floor) ** 2
    out = np.zeros((len(sd), 3, 3))
    out[:, 0, 0], out[:, 1, 1], out[:, 2, 2] = var[:, 0], var[:, 1], heading_var
    return out


def _steps(track: Track) -> tuple[Step, ...]:
    """The scenario's steps: ``u_k`` and the kept detections of step k, in time order."""
    meas, written = track.measurements, track.written
    per_step: list[list[Detection]] = [[] for _ in range(len(track.odometry))]
    for i in track.kept:
        per_step[meas.step[i] - 1].append(
            Detection(float(written[i, 0]), float(written[i, 1]), np.ones(1),
                      int(meas.landmark[i]) if meas.landmark[i] >= 0 else None))
    return tuple(Step(u.copy(), tuple(d)) for u, d in zip(track.odometry, per_step))
