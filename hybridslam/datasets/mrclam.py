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
  partial intervals at step boundaries (:func:`~.mrclam_calibration.integrate_odometry`). ``u_k = between(P(t_{k-1}),
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
* **Motion noise with clutter.** A file with a clutter hypothesis gets by default a ``motion_cov``
  calibrated from the odometry's drift (``motion_noise_from="drift"``, below), the per-step one
  otherwise. The clutter density is constant and competes with ``N(z; h, S)``: a reading whose
  innovation lies more than a few sds of ``S`` out is explained as clutter. The per-step
  calibration undercounts the drift of the velocity commands (errors correlated in time), so after
  a stretch without landmarks ``S`` is too small for the pose's real error, the readings of the
  right landmark are explained as clutter, and the estimate is never corrected again (dataset 7,
  robot 1, 20-120 s: no landmark for the first 28 s, heading 0.39 rad off at 4 sds; 120 of 186
  landmark readings then called clutter by the hybrid belief, smoothed APE 0.385 m;
  docs/studies/mrclam_unfiltered.md). Without clutter every reading must be some object's, which
  pulls the estimate back whatever ``S`` says. The drift noise recovers the hybrid belief, ``ml``
  and ``max-mixture`` there (0.116-0.137 m smoothed APE) but not ``gpda`` and ``multimodal``, and it
  costs the single-Gaussian estimators accuracy on dataset 6, robot 2 (the study's table).

What the data hold (datasets 6 and 7, all robots), and what the import does about it:

* The odometry is velocity *commands*, not wheel odometry. The ground truth follows them
  ~0.17 s later (``odometry_delay`` shifts them; default 0, the data as logged) and the
  commanded distance is 4-12% longer than the true one over a whole log. The per-step errors are
  therefore correlated in time: summed over 5 s they grow 2.7-5.9× (forward) and 1.7-3.3×
  (heading) faster than the calibrated per-step sd (200 s windows), and over a whole log the
  largest sd per step over 10-40 s is 1.8-2.1× the 5 s one (forward) and up to 1.5× (heading;
  dataset 7). Dead reckoning drifts
  accordingly. ``generator.calibration.odometry_drift_sd_per_step`` reports it per horizon (5,
  10, 20, 40 s, each where the window measures it); ``motion_noise_from="drift"`` writes a
  ``motion_cov`` that grows as fast at every one of them (on
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
from dataclasses import replace
from typing import Any

import numpy as np

from ..models.scenario import Classifier, Discovery, Scenario
from .mrclam_calibration import MIN_BLOCKS, _drift, _drift_block, _stats, compose, measurement_residuals, wrap
from .mrclam_detections import Window, default_sensor, make_window, merge_repeats_of
from .clutter import declared_clutter
from .mrclam_files import MRCLAMError, RobotLog, covariance, finite, read_barcodes, read_landmarks, read_robot
from .mrclam_track import Noise, Track, assemble_track, calibrate, scenario_steps

NOISE_SOURCES = ("written", "raw")  # what geometric_cov is calibrated from (import_mrclam)
MOTION_NOISE_SOURCES = ("steps", "drift")  # what motion_cov is calibrated from (import_mrclam)
ROBOT_PRIOR_VAR = 1e-4  # x_0 is the ground truth: it anchors the world frame (m², m², rad²)
CLUTTER_FRACTION = 0.5  # default prior probability that a reading is spurious (import_mrclam, Clutter)


def _max_gap(times: np.ndarray, lo: float, hi: float) -> float:
    """The longest time without a record within [lo, hi] (s), its ends counted as records."""
    t = np.concatenate([[lo], times[(times > lo) & (times < hi)], [hi]])
    return float(np.diff(t).max())

def _check_settings(max_range: Any, fov: Any, landmark_sd_floor: Any, landmark_heading_var: Any,
                    discovery_margin: Any, new_object_log_density: Any, odometry_delay: Any,
                    unmapped_objects: Any) -> None:
    if max_range is not None:
        finite(max_range, "max_range", "metres")
    if fov is not None and not 0 < finite(fov, "fov", "radians") <= 2 * math.pi:
        raise MRCLAMError(f"fov: expected radians in (0, 2*pi], got {fov!r}")
    finite(landmark_sd_floor, "landmark_sd_floor", "metres")
    finite(landmark_heading_var, "landmark_heading_var", "rad^2")
    finite(odometry_delay, "odometry_delay", "seconds", positive=False)
    if new_object_log_density is not None:
        finite(new_object_log_density, "new_object_log_density", "nats", positive=False)
    for name, count in (("discovery_margin", discovery_margin), ("unmapped_objects", unmapped_objects)):
        if not isinstance(count, int) or isinstance(count, bool) or count < 0:
            raise MRCLAMError(f"{name}: expected a non-negative integer, got {count!r}")


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
    motion_noise_from: str | None = None,
    landmark_sd_floor: float = 0.01,
    landmark_heading_var: float = math.pi**2,
    discovery_margin: int = 10,
    new_object_log_density: float | None = None,
    max_objects: int | None = None,
    identity_filter: bool = False,
    merge_repeats: bool = False,
    clutter_log_density: float | str | None = None,
    unmapped_objects: int = 0,
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
    * ``unmapped_objects`` (known map; default 0): the surveyed landmarks as the prior map, and a
      ``discovery`` section with room for this many more objects that the survey does not hold
      (another robot standing still is read at every step, which a clutter density, independent
      between steps, does not describe); ``new_object_log_density`` as for an unknown map.
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
    * ``motion_noise_from``: ``"steps"`` calibrates ``motion_cov`` from the per-step odometry
      residuals; ``"drift"`` takes per component the largest of that and the variances per step that
      their sums over 5, 10, 20 and 40 s imply (5 s with 5 blocks in the window, a longer one with 20;
      ``generator.calibration.odometry_drift_sd_per_step``), so that dead reckoning's covariance
      grows as fast as its error does over seconds to tens of seconds (the errors are correlated in
      time: module docstring). Needs a window of at least 25 s. Default (``None``):
      ``"drift"`` when the file declares a clutter hypothesis and the window holds the 25 s,
      ``"steps"`` otherwise (module docstring, Noise: why clutter needs a consistent covariance).

    Everything the import measured (calibration, counts, dead-reckoning error, data gaps) is in
    ``scenario.metadata["generator"]``. Raises :class:`MRCLAMError` (one line naming the file and
    line, the robot, the window or the setting) for anything the data cannot serve.
    """
    folder = os.fspath(dataset_dir)
    if not os.path.isdir(folder):
        raise MRCLAMError(f"{folder}: not a dataset folder (no such directory)")
    _check_settings(max_range, fov, landmark_sd_floor, landmark_heading_var, discovery_margin,
                    new_object_log_density, odometry_delay, unmapped_objects)
    if motion_noise_from is not None and motion_noise_from not in MOTION_NOISE_SOURCES:
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
    if unmapped_objects and unknown_map:
        raise MRCLAMError("unmapped_objects: room for objects beside a known map; an unknown map's slots are "
                          "max_objects (--object-slots)")
    given = {"motion_cov": covariance(motion_cov, 3, "motion_cov"),
             "geometric_cov": covariance(geometric_cov, 2, "geometric_cov"),
             "robot_prior_cov": covariance(robot_prior_cov, 3, "robot_prior_cov")}
    barcodes, landmarks = read_barcodes(folder), read_landmarks(folder).rows
    landmarks = landmarks[np.argsort(landmarks[:, 0])]  # subject order: searchsorted needs it
    log_ = read_robot(folder, robot)
    window = make_window(log_, robot, start, duration, dt, odometry_delay)
    track = assemble_track(log_, barcodes, landmarks, window, odometry_delay, motion_compensation, max_range,
                           fov, identity_filter)
    motion_source = motion_noise_from or default_motion_noise(
        _declares_clutter(clutter_log_density, identity_filter), len(window.times) - 1, window.dt)
    noise = calibrate(track, log_, landmarks, given, robot, correct_range_bias, measurement_noise_from,
                      motion_source, window.dt)
    sd = np.sqrt(np.diag(noise.geometric))
    if merge_repeats and not identity_filter:
        merged = merge_repeats_of(track.measurements, track.written, window, track.kept, sd)
        track.measurements.counts.update(merged=int(len(track.kept) - len(merged)), kept=len(merged))
        track = replace(track, kept=merged)
    default = default_sensor(log_, barcodes, landmarks[:, 0], track.written[track.kept], sd, identity_filter)
    max_range = default[0] if max_range is None else float(max_range)
    fov = default[1] if fov is None else float(fov)
    clutter = _clutter_density(clutter_log_density, identity_filter, max_range, fov)
    steps = scenario_steps(track)
    # The oracle-assisted conversion sizes an unknown map from the surveyed landmarks; otherwise from
    # the data alone: the busiest step's detections could all be new objects, plus the margin.
    slots = max_objects if max_objects is not None else len(landmarks) + discovery_margin if identity_filter \
        else max(2, max((len(st.detections) for st in steps), default=0) + discovery_margin)
    slots_from = ("given" if max_objects is not None else "landmarks + margin (oracle)" if identity_filter
                  else "most detections in a step + margin")

    settings = {"robot": int(robot), "start_s": float(start), "map": "unknown" if unknown_map else "known",
                "motion_compensation": bool(motion_compensation), "odometry_delay_s": float(odometry_delay),
                "range_bias_corrected": bool(correct_range_bias),
                "motion_noise_chosen": "given" if motion_noise_from is not None else
                "default: drift with a clutter hypothesis and 25 s of window, else steps"}
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
    density = -math.log(max_range * fov) if new_object_log_density is None else new_object_log_density
    if unknown_map:
        return Scenario(
            object_prior_means=np.zeros((0, 3)), object_prior_covs=np.zeros((0, 3, 3)),
            class_prior=np.zeros((0, 1)),
            discovery=Discovery(int(slots), float(density),
                                float(landmark_heading_var)),
            true_objects=tuple((p, 0) for p in poses), **common)
    if unmapped_objects:  # a known map the survey may not hold whole (docstring)
        generator["unmapped_objects"] = int(unmapped_objects)
        truth: dict[str, Any] = dict(discovery=Discovery(len(landmarks) + int(unmapped_objects), float(density),
                                                         float(landmark_heading_var)),
                                     true_objects=tuple((p, 0) for p in poses))
    else:
        truth = dict(true_object_poses=poses, true_classes=np.zeros(len(landmarks), dtype=np.int64))
    return Scenario(
        object_prior_means=poses.copy(),
        object_prior_covs=landmark_covariances(landmarks[:, 3:5], landmark_sd_floor, landmark_heading_var),
        class_prior=np.ones((len(landmarks), 1)), **truth, **common)


def _declares_clutter(value: float | str | None, identity_filter: bool) -> bool:
    """Whether the file written will hold ``sensor.clutter_log_density`` (:func:`_clutter_density`)."""
    return value != "none" if value is not None else not identity_filter


def default_motion_noise(clutter: bool, steps: int, dt: float) -> str:
    """``motion_noise_from`` by default: ``"drift"`` for a file with a clutter hypothesis
    (``clutter``) whose ``steps`` of ``dt`` seconds hold :data:`MIN_BLOCKS` drift blocks, else
    ``"steps"``.

    A clutter hypothesis competes with ``N(z; h, S)`` at a constant density, so a reading is
    explained as clutter once its innovation lies a few sds of ``S`` out; with ``S`` built on a
    per-step ``motion_cov`` that undercounts the odometry's time-correlated drift, the readings of
    a landmark seen after a stretch of dead reckoning lie far out, and the estimate stops being
    corrected (module docstring, Noise). Without clutter every reading must be some object's,
    which corrects the drift anyway, and the per-step calibration is the more accurate one.
    """
    return "drift" if clutter and steps // _drift_block(dt) >= MIN_BLOCKS else "steps"


def _clutter_density(value: float | str | None, identity_filter: bool, max_range: float, fov: float) -> float | None:
    """``sensor.clutter_log_density`` to write: ``value`` (a number; ``"none"``: none), or by default
    ``log(CLUTTER_FRACTION / (max_range · fov))`` (none with the identity filter)."""
    default = None if identity_filter else round(math.log(CLUTTER_FRACTION / (max_range * fov)), 9)
    return declared_clutter(value, default, MRCLAMError)


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
            "motion_noise_chosen": settings["motion_noise_chosen"],
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
