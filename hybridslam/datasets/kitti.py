"""KITTI tracking (training sequences 0000-0020) with PointRCNN detections as a scenario file.

Geiger, Lenz & Urtasun, "Are we ready for autonomous driving?", CVPR 2012 (the tracking
benchmark); detections of PointRCNN (Shi et al., CVPR 2019) as published by AB3DMOT (Weng et
al., IROS 2020). One folder ``DIR`` holds, per sequence ``NN`` (docs/studies/kitti.md says where
each file comes from):

* ``label_02/00NN.txt``: KITTI tracking labels, space-separated ``frame track_id type truncated
  occluded alpha x1 y1 x2 y2 h w l x y z ry`` (3D box in the rectified camera frame: x right,
  y down, z forward; ``(x, y, z)`` the bottom centre; ``ry`` the yaw about the camera y axis);
* ``calib/00NN.txt``: ``P0..P3``, ``R0_rect``, ``Tr_velo_to_cam`` (or ``Tr_velo_cam``),
  ``Tr_imu_to_velo`` (or ``Tr_imu_velo``);
* ``detections/pointrcnn_{Car,Pedestrian,Cyclist}_val/00NN.txt``: comma-separated ``frame, type
  id (1 Pedestrian, 2 Car, 3 Cyclist), x1, y1, x2, y2, score (a logit), h, w, l, x, y, z, ry,
  alpha`` (AB3DMOT's ``docs/KITTI.md``), one detector per class;
* ``egomotion/00NN.txt``: the OXTS ground truth as TUM rows ``t x y z qx qy qz qw``, one per frame,
  the pose of the IMU (x forward, y left, z up) in the IMU frame of frame 0;
* ``orbslam3/00NN/CameraTrajectory.txt``: ORB-SLAM3's camera poses, one 3x4 row-major matrix per
  frame (camera to the frame-0 camera).

:func:`import_kitti` writes one sequence as a ``hybridslam-scenario/1`` (docs/file_format.md):

* **Frames.** The vehicle frame is the IMU's, planar: a pose is ``[x, y, yaw]`` with yaw about the
  IMU z axis (up), so x is forward and y left. Camera-frame points go to it through the
  calibration, ``p_imu = T_imu←velo T_velo←cam R0_rect⁻¹ p_rect``; an ORB-SLAM3 camera pose
  ``T_c0←c`` becomes the IMU pose ``T_i←c T_c0←c T_c←i``. Roll, pitch and height are dropped.
  ``x_0`` is frame ``start``; step ``k`` is frame ``start + k·every``.
* **Odometry.** ``"orbslam3"``: ``u_k = between`` of ORB-SLAM3's planar poses, ``motion_cov``
  calibrated against the ground truth (robust: ``(1.4826·MAD)² + median²`` per component, as the
  MRCLAM importer). ``"noisy-truth"``: the ground-truth increment composed with a draw of
  ``motion_cov`` (default :data:`WHEEL_ODOMETRY_SD` per 0.1 s frame, scaled by ``every``), seeded:
  white noise whose covariance the estimators know exactly.
* **Detections.** The three detectors run separately, so one object may be reported by two of
  them. Per frame, boxes whose bird's-eye centres lie within ``merge_radius`` are merged greedily,
  strongest logit first, into one detection at the strongest box; its ``scores`` are, per class
  ``c``, ``σ(logit_c)`` of class ``c``'s box in the group, or 0 where that detector did not fire
  (:func:`score_vector`). Range and bearing are those of the box's bottom centre in the vehicle
  frame. Groups weaker than ``min_logit``, or outside ``max_range`` / ``fov``, are dropped (counted).
* **Ground truth.** ``robot.true_poses`` are the egomotion poses. A detection is matched to the
  label of its frame with the largest 3D IoU (rotated boxes), at least ``match_iou``, one label per
  detection at most. Label types ``Car``/``Van`` are class 0, ``Pedestrian``/``Person_sitting`` 1,
  ``Cyclist`` 2; other types (``Truck``, ``Tram``, ``Misc``) are not map objects. A track is
  *static* when each of its world positions (ground-truth pose ∘ label centre) lies within
  ``static_tolerance`` of their median, otherwise *moving*. Static tracks of the three classes seen
  in the window are the objects (pose: the median position and the circular mean yaw); a
  detection matched to one gets its index as ``true_object``; detections of moving tracks, of other
  types, or matched to no label have none: to a static map they are clutter, and the
  ``generator.counts`` say how many of each.
* **Map.** Known: every static object with ``prior_mean`` its label pose and ``prior_cov``
  ``diag(prior_sd)²``. Unknown: a ``discovery`` section (object slots: the most detections in one
  step + 20, read off the detections, not the labels) and the objects under ``true_objects``.
* **Clutter.** ``sensor.clutter_log_density`` is ``-log(max_range · fov)``, uniform over the
  sensor's footprint in range and bearing: the moving cars and the unmatched detections are
  clutter to a static map, and without a clutter hypothesis an estimator must make each of them
  some object's.
* **Noise.** ``geometric_cov`` from the range and bearing residuals of the matched detections
  against their labels' boxes (the same robust rule), floored.
* ``classifier`` is ``none``; a study puts its model in (``experiments/kitti.py``).
"""

from __future__ import annotations

import math
import os
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..models.scenario import Classifier, Detection, Discovery, Scenario, Step
from .clutter import declared_clutter
from .kitti_files import (
    CLASSES,
    Boxes,
    KITTIError,
    between,
    boxes_in_vehicle,
    compose,
    iou_3d,
    planar,
    read_calibration,
    read_detections,
    read_kitti_poses,
    read_labels,
    read_tum,
    score_vector,
    se2_exp,
    viewpoint,
    wrap,
)

LABEL_CLASSES = {"Car": 0, "Van": 0, "Pedestrian": 1, "Person_sitting": 1, "Cyclist": 2}
OTHER_TYPES = ("Truck", "Tram", "Misc")  # labelled, matched, but not map objects
ODOMETRY_SOURCES = ("noisy-truth", "orbslam3")
WHEEL_ODOMETRY_SD = (0.03, 0.01, 0.002)  # m, m, rad per 0.1 s frame: a car's wheel odometry at ~10 m/s
MAD_TO_SD = 1.4826
GEOMETRIC_SD_FLOOR = (0.05, 0.002)  # m, rad
MOTION_SD_FLOOR = 1e-3
ROBOT_PRIOR_VAR = 1e-4


# --------------------------------------------------------------------------- #
# One sequence
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class Sequence:
    """One sequence's files, read and checked. ``truth`` and ``orbslam`` are planar IMU poses per frame."""

    folder: str
    name: str  # "0006"
    imu_from_rect: np.ndarray  # (4, 4)
    truth: np.ndarray  # (F, 3)
    orbslam: np.ndarray | None  # (F, 3)
    labels: Boxes
    detections: Boxes


def sequence_name(sequence: int | str) -> str:
    try:
        n = int(sequence)
    except (TypeError, ValueError):
        raise KITTIError(f"sequence: expected a number 0-9999, got {sequence!r}") from None
    if not 0 <= n <= 9999:
        raise KITTIError(f"sequence: expected a number 0-9999, got {sequence!r}")
    return f"{n:04d}"


def read_sequence(folder: str, sequence: int | str, orbslam: bool = True) -> Sequence:
    """Read and cross-check every file of one sequence (``orbslam=False`` skips ORB-SLAM3's)."""
    name = sequence_name(sequence)
    if not os.path.isdir(folder):
        raise KITTIError(f"{folder}: no such folder")
    imu_from_rect = read_calibration(os.path.join(folder, "calib", f"{name}.txt"))
    ego_path = os.path.join(folder, "egomotion", f"{name}.txt")
    truth = planar(read_tum(ego_path))
    if len(truth) < 2:
        raise KITTIError(f"{ego_path}: {len(truth)} poses; at least 2 needed")
    orb = None
    if orbslam:
        orb_path = os.path.join(folder, "orbslam3", name, "CameraTrajectory.txt")
        cam = read_kitti_poses(orb_path)
        if len(cam) != len(truth):
            raise KITTIError(f"{orb_path}: {len(cam)} poses, but {ego_path} has {len(truth)} (one per frame)")
        rect_from_imu = np.linalg.inv(imu_from_rect)
        orb = planar(imu_from_rect @ cam @ rect_from_imu)
    labels_path = os.path.join(folder, "label_02", f"{name}.txt")
    labels = read_labels(labels_path)
    parts = []
    for cls in CLASSES:
        path = os.path.join(folder, "detections", f"pointrcnn_{cls}_val", f"{name}.txt")
        parts.append(read_detections(path, cls))
        _check_frames(parts[-1].frame, len(truth), path)
    _check_frames(labels.frame, len(truth), labels_path)
    dets = Boxes(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("frame", "cls", "score", "track", "box")))
    return Sequence(folder, name, imu_from_rect, truth, orb, labels, dets)


def _check_frames(frames: np.ndarray, num: int, path: str) -> None:
    if frames.size and frames.max() >= num:
        raise KITTIError(f"{path}: frame {frames.max()} beyond the {num} frames of the egomotion file")


@dataclass(frozen=True)
class FrameDetection:
    """A merged detection in one frame: vehicle-frame pose of its box, scores, matched label row."""

    pose: np.ndarray  # (3,) box pose in the vehicle frame
    scores: np.ndarray  # (3,)
    logit: float  # the strongest logit of the group
    label: int  # row of Sequence.labels, or -1


def frame_detections(seq: Sequence, frame: int, merge_radius: float, match_iou: float) -> list[FrameDetection]:
    """Frame ``frame``'s detections, merged across the three detectors and matched to its labels."""
    rows = np.flatnonzero(seq.detections.frame == frame)
    rows = rows[np.argsort(-seq.detections.score[rows], kind="stable")]
    box = seq.detections.box
    used = np.zeros(len(rows), dtype=bool)
    groups: list[tuple[int, dict[int, float]]] = []
    for i, r in enumerate(rows):
        if used[i]:
            continue
        logits = {CLASSES.index(seq.detections.cls[r]): float(seq.detections.score[r])}
        for j in range(i + 1, len(rows)):
            s = rows[j]
            c = CLASSES.index(seq.detections.cls[s])
            if not used[j] and c not in logits and math.hypot(*(box[s, [3, 5]] - box[r, [3, 5]])) <= merge_radius:
                used[j] = True
                logits[c] = float(seq.detections.score[s])
        groups.append((int(r), logits))
    label_rows = np.flatnonzero(seq.labels.frame == frame)
    pairs = sorted(((iou_3d(box[r], seq.labels.box[lr]), g, int(lr)) for g, (r, _) in enumerate(groups)
                    for lr in label_rows), reverse=True)
    match = [-1] * len(groups)
    taken: set[int] = set()
    for iou, g, lr in pairs:
        if iou < match_iou:
            break
        if match[g] < 0 and lr not in taken:
            match[g] = lr
            taken.add(lr)
    poses = boxes_in_vehicle(box[[r for r, _ in groups]].reshape(-1, 7), seq.imu_from_rect)
    return [FrameDetection(poses[g], score_vector(logits), max(logits.values()), match[g])
            for g, (_, logits) in enumerate(groups)]


@dataclass(frozen=True)
class TrackInfo:
    cls: int | None  # class index, None for types that are not map objects
    static: bool
    pose: np.ndarray  # (3,) world pose: median position, circular-mean yaw


def tracks(seq: Sequence, frames: np.ndarray, static_tolerance: float) -> dict[int, TrackInfo]:
    """Every labelled track of ``frames``: class, static or moving, world pose (ground-truth frames)."""
    sel = np.flatnonzero(np.isin(seq.labels.frame, frames))
    world = compose(seq.truth[seq.labels.frame[sel]], boxes_in_vehicle(seq.labels.box[sel], seq.imu_from_rect))
    out = {}
    for t in np.unique(seq.labels.track[sel]):
        mine = seq.labels.track[sel] == t
        p = world[mine]
        centre = np.median(p[:, :2], axis=0)
        static = bool(np.all(np.hypot(*(p[:, :2] - centre).T) <= static_tolerance))
        yaw = math.atan2(np.mean(np.sin(p[:, 2])), np.mean(np.cos(p[:, 2])))
        out[int(t)] = TrackInfo(LABEL_CLASSES.get(seq.labels.cls[sel][mine][0]), static,
                                np.array([centre[0], centre[1], yaw]))
    return out


def _robust_var(residuals: np.ndarray, floor) -> np.ndarray:
    """Per column ``(1.4826·MAD)² + median²`` (robust mean square about zero), floored."""
    if len(residuals) < 2:
        return np.asarray(floor, dtype=float) ** 2
    med = np.median(residuals, axis=0)
    scale = MAD_TO_SD * np.median(np.abs(residuals - med), axis=0)
    return np.maximum(scale**2 + med**2, np.asarray(floor, dtype=float) ** 2)


def window_frames(num_frames: int, start: int, end: int | None, every: int) -> np.ndarray:
    """Frames of ``x_0 … x_T``: ``start, start + every, …`` up to ``end`` (inclusive; default the last)."""
    if not (isinstance(every, int) and every >= 1):
        raise KITTIError(f"every: expected a positive integer, got {every!r}")
    end = num_frames - 1 if end is None else end
    if not 0 <= start < end <= num_frames - 1:
        raise KITTIError(f"frames {start}-{end}: the sequence has frames 0-{num_frames - 1} (start < end needed)")
    frames = np.arange(start, end + 1, every)
    if len(frames) < 2:
        raise KITTIError(f"frames {start}-{end} every {every}: fewer than 2 poses")
    return frames


def import_kitti(
    folder: str, sequence: int | str, *, unknown_map: bool = False, start: int = 0, end: int | None = None,
    every: int = 1, odometry: str = "noisy-truth", seed: int = 0, max_range: float = 30.0, fov: float = 1.6,
    min_logit: float | None = None, merge_radius: float = 1.0, match_iou: float = 0.25,
    static_tolerance: float = 1.0, prior_sd: tuple[float, float, float] = (0.3, 0.3, 0.2),
    motion_cov: np.ndarray | None = None, geometric_cov: np.ndarray | None = None,
    max_objects: int | None = None, new_object_orientation_var: float = math.pi**2,
    clutter_log_density: float | str | None = None,
) -> Scenario:
    """One KITTI tracking sequence as a scenario (the module docstring says how).

    ``clutter_log_density``: ``sensor.clutter_log_density`` written (default ``-log(max_range · fov)``,
    uniform over the sensor's footprint in range and bearing; ``"none"``: no clutter hypothesis).
    ``max_objects``: an unknown map's object slots (default: the most detections in one step + 20)."""
    if odometry not in ODOMETRY_SOURCES:
        raise KITTIError(f"odometry: expected one of {', '.join(ODOMETRY_SOURCES)}, got {odometry!r}")
    for name, value in (("max_range", max_range), ("fov", fov), ("merge_radius", merge_radius),
                        ("static_tolerance", static_tolerance)):
        if not (math.isfinite(value) and value > 0):
            raise KITTIError(f"{name}: expected a positive number, got {value!r}")
    footprint = -math.log(max_range * fov)  # log of a density uniform over the sensor's footprint, 1 / (m rad)
    clutter = declared_clutter(clutter_log_density, footprint, KITTIError)
    seq = read_sequence(folder, sequence, orbslam=odometry == "orbslam3")
    frames = window_frames(len(seq.truth), start, end, every)
    truth = seq.truth[frames]
    info = tracks(seq, frames, static_tolerance)
    counts: Counter[str] = Counter()
    per_step: list[list[tuple[np.ndarray, FrameDetection]]] = []
    seen: set[int] = set()
    for f in frames[1:]:
        kept = []
        for d in frame_detections(seq, int(f), merge_radius, match_iou):
            counts["merged"] += 1
            rb = np.array([math.hypot(d.pose[0], d.pose[1]), math.atan2(d.pose[1], d.pose[0])])
            if min_logit is not None and d.logit < min_logit:
                counts["below_min_logit"] += 1
                continue
            if rb[0] > max_range or abs(rb[1]) > fov / 2:
                counts["beyond_sensor"] += 1
                continue
            kept.append((rb, d))
            t = info.get(int(seq.labels.track[d.label])) if d.label >= 0 else None
            if t is None:
                counts["unmatched"] += 1
            elif t.cls is None:
                counts["other_type"] += 1
            elif not t.static:
                counts["moving"] += 1
            else:
                counts["static"] += 1
                seen.add(int(seq.labels.track[d.label]))
        per_step.append(kept)
    counts["raw"] = int(np.isin(seq.detections.frame, frames[1:]).sum())
    # The map: static tracks of the three classes with a label inside the footprint of some x_k.
    sel = np.flatnonzero(np.isin(seq.labels.frame, frames))
    local = boxes_in_vehicle(seq.labels.box[sel], seq.imu_from_rect)
    in_view = (np.hypot(local[:, 0], local[:, 1]) <= max_range) & (np.abs(np.arctan2(local[:, 1], local[:, 0])) <= fov / 2)
    visible = {int(t) for t in seq.labels.track[sel][in_view]}
    ids = sorted(t for t, i in info.items() if i.static and i.cls is not None and (t in visible or t in seen))
    index = {t: n for n, t in enumerate(ids)}
    poses = np.array([info[t].pose for t in ids]).reshape(len(ids), 3)
    classes = np.array([info[t].cls for t in ids], dtype=np.int64)

    residuals = []
    steps_dets: list[tuple[Detection, ...]] = []
    for k, kept in enumerate(per_step, 1):
        out = []
        for rb, d in kept:
            true = None
            if d.label >= 0:
                true = index.get(int(seq.labels.track[d.label]))
                lab = boxes_in_vehicle(seq.labels.box[d.label][None], seq.imu_from_rect)[0]
                residuals.append([rb[0] - math.hypot(lab[0], lab[1]), wrap(rb[1] - math.atan2(lab[1], lab[0]))])
            out.append(Detection(float(rb[0]), float(rb[1]), d.scores, true))
        steps_dets.append(tuple(out))
    geo_source = "given"
    if geometric_cov is None:
        geometric_cov = np.diag(_robust_var(np.array(residuals).reshape(-1, 2), GEOMETRIC_SD_FLOOR))
        geo_source = "calibrated"

    true_u = between(truth[:-1], truth[1:])
    motion_source = "given" if motion_cov is not None else "calibrated"
    if odometry == "orbslam3":
        assert seq.orbslam is not None
        orb = seq.orbslam[frames]
        u = between(orb[:-1], orb[1:])
        if motion_cov is None:
            res = np.array([_log(between(a, b)) for a, b in zip(u, true_u)])
            motion_cov = np.diag(_robust_var(res, (MOTION_SD_FLOOR,) * 3))
    else:
        if motion_cov is None:
            motion_cov = np.diag(np.square(WHEEL_ODOMETRY_SD) * every)
            motion_source = "wheel-odometry level"
        rng = np.random.default_rng(seed)
        noise = rng.multivariate_normal(np.zeros(3), motion_cov, size=len(true_u))
        u = np.array([compose(a, se2_exp(n)) for a, n in zip(true_u, noise)])
    dr = [truth[0]]
    for step in u:
        dr.append(compose(dr[-1], step))
    steps = tuple(Step(np.asarray(a, dtype=float), d) for a, d in zip(u, steps_dets))

    moving = sorted(t for t, i in info.items() if not i.static and i.cls is not None)
    generator: dict[str, Any] = {
        "dataset": "kitti-tracking", "sequence": seq.name, "frames": {"start": int(frames[0]),
        "end": int(frames[-1]), "every": int(every)}, "map": "unknown" if unknown_map else "known",
        "odometry": odometry, "seed": int(seed) if odometry == "noisy-truth" else None,
        "classes": list(CLASSES),
        "scores": "sigmoid of each class detector's logit where it fired, 0 where it did not",
        "settings": {"max_range": max_range, "fov": fov, "min_logit": min_logit, "merge_radius": merge_radius,
                     "match_iou": match_iou, "static_tolerance": static_tolerance},
        "counts": {"raw_detections": counts["raw"], "merged_detections": counts["merged"],
                   "below_min_logit": counts["below_min_logit"], "beyond_sensor": counts["beyond_sensor"],
                   "written": sum(map(len, steps_dets)), "static_object": counts["static"],
                   "moving_object": counts["moving"], "other_type": counts["other_type"],
                   "unmatched": counts["unmatched"], "static_objects": len(ids),
                   "moving_tracks": len(moving),
                   "other_type_tracks": sum(1 for i in info.values() if i.cls is None)},
        "calibration": {"geometric_cov": geo_source, "geometric_sd": np.sqrt(np.diag(geometric_cov)).tolist(),
                        "motion_cov": motion_source, "motion_sd": np.sqrt(np.diag(motion_cov)).tolist()},
        "dead_reckoning": {"final_position_error_m": float(np.hypot(*(dr[-1][:2] - truth[-1, :2]))),
                           "path_length_m": float(np.sum(np.hypot(*np.diff(truth[:, :2], axis=0).T)))},
        "clutter": {"log_density": clutter, "from": "default" if clutter_log_density is None else "given"},
    }
    common: dict[str, Any] = dict(  # noqa: C408 - keyword arguments of Scenario
        num_classes=len(CLASSES), robot_prior_mean=truth[0].copy(), robot_prior_cov=ROBOT_PRIOR_VAR * np.eye(3),
        motion_cov=np.asarray(motion_cov, dtype=float), geometric_cov=np.asarray(geometric_cov, dtype=float),
        classifier=Classifier("none"), max_range=float(max_range), fov=float(fov), steps=steps,
        true_robot_poses=truth.copy(), clutter_log_density=clutter, metadata={"generator": generator})
    if unknown_map:
        # Object slots from the data, not from the labels: the busiest step's detections + 20.
        slots = max(map(len, steps_dets), default=0) + 20 if max_objects is None else int(max_objects)
        return Scenario(
            object_prior_means=np.zeros((0, 3)), object_prior_covs=np.zeros((0, 3, 3)),
            class_prior=np.zeros((0, len(CLASSES))),
            discovery=Discovery(slots, footprint, float(new_object_orientation_var)),
            true_objects=tuple((p, int(c)) for p, c in zip(poses, classes)), **common)
    cov = np.diag(np.square(prior_sd))
    return Scenario(
        object_prior_means=poses.copy(), object_prior_covs=np.repeat(cov[None], len(ids), axis=0),
        class_prior=np.full((len(ids), len(CLASSES)), 1 / len(CLASSES)), true_object_poses=poses.copy(),
        true_classes=classes, **common)


def _log(p: np.ndarray) -> np.ndarray:
    """SE(2) logarithm of a planar pose (3,) into ``[v_x, v_y, ω]``."""
    x, y, w = p
    if abs(w) < 1e-9:
        a, b = 1.0, w / 2
    else:
        a, b = math.sin(w) / w, (1 - math.cos(w)) / w
    det = a * a + b * b
    return np.array([(a * x + b * y) / det, (-b * x + a * y) / det, w])


def classifier_samples(
    folder: str, sequences, *, every: int = 1, max_range: float = 30.0, merge_radius: float = 1.0,
    match_iou: float = 0.25,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training samples of a classifier model (Eq. 2) from labelled detections.

    Every merged detection within ``max_range`` matched to a label of the three classes (static or
    moving): its label's class, the viewpoint of the label's box from the vehicle (docs/file_format.md),
    its scores. Returns ``classes`` (N,), ``viewpoints`` (N,) radians, ``scores`` (N, 3).
    """
    classes, views, scores = [], [], []
    for s in sequences:
        seq = read_sequence(folder, s, orbslam=False)
        for f in range(0, len(seq.truth), every):
            for d in frame_detections(seq, f, merge_radius, match_iou):
                if d.label < 0 or math.hypot(d.pose[0], d.pose[1]) > max_range:
                    continue
                c = LABEL_CLASSES.get(seq.labels.cls[d.label])
                if c is None:
                    continue
                lab = boxes_in_vehicle(seq.labels.box[d.label][None], seq.imu_from_rect)[0]
                classes.append(c)
                views.append(viewpoint(np.zeros(3), lab))
                scores.append(d.scores)
    return (np.array(classes, dtype=np.int64), np.array(views, dtype=float),
            np.array(scores, dtype=float).reshape(-1, len(CLASSES)))
