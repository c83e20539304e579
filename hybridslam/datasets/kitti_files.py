"""The files of a KITTI tracking folder (labels, calibration, AB3DMOT's PointRCNN detections, TUM
and KITTI pose files) and the box geometry the importer needs (:mod:`hybridslam.datasets.kitti`).

Frames: KITTI's rectified camera has x right, y down, z forward; the vehicle (IMU) frame x
forward, y left, z up. A planar pose is ``[x, y, yaw]`` with yaw about the vehicle's up axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .textfile import read_ascii

CLASSES = ("Car", "Pedestrian", "Cyclist")  # class 0, 1, 2
DETECTOR_TYPE_IDS = {1: "Pedestrian", 2: "Car", 3: "Cyclist"}  # AB3DMOT's det_id2str

class KITTIError(ValueError):
    """A missing or malformed KITTI file, or a setting the data cannot serve. One line."""


# --------------------------------------------------------------------------- #
# Reading
# --------------------------------------------------------------------------- #


def _lines(path: str):
    for lineno, line in enumerate(read_ascii(path, KITTIError).splitlines(), 1):
        if line.strip():
            yield lineno, line.strip()


def _bad(path: str, lineno: int, what: str, text: str) -> KITTIError:
    shown = text if len(text) <= 60 else text[:57] + "..."
    return KITTIError(f"{path}:{lineno}: expected {what}, got {shown!r}")


def _floats(parts: list[str], path: str, lineno: int, what: str, text: str) -> list[float]:
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise _bad(path, lineno, what, text) from None
    if not all(map(math.isfinite, values)):
        raise _bad(path, lineno, what, text)
    return values


def _frame(value: float, path: str, lineno: int, what: str, text: str) -> int:
    if value != int(value) or value < 0:
        raise _bad(path, lineno, what, text)
    return int(value)


@dataclass(frozen=True)
class Boxes:
    """3D boxes of one file: ``frame`` (n,), ``cls`` (n,) names, ``score`` (n,), ``track`` (n,),
    ``box`` (n, 7) ``h w l x y z ry`` in the rectified camera frame."""

    frame: np.ndarray
    cls: np.ndarray
    score: np.ndarray
    track: np.ndarray
    box: np.ndarray


def read_detections(path: str, expected: str) -> Boxes:
    """One AB3DMOT PointRCNN file; every row's type id must name ``expected``."""
    what = "15 comma-separated numbers (frame, type, x1, y1, x2, y2, score, h, w, l, x, y, z, ry, alpha)"
    rows: list[list[float]] = []
    for lineno, text in _lines(path):
        parts = text.split(",")
        if len(parts) != 15:
            raise _bad(path, lineno, what, text)
        v = _floats(parts, path, lineno, what, text)
        _frame(v[0], path, lineno, what, text)
        if DETECTOR_TYPE_IDS.get(int(v[1])) != expected or v[1] != int(v[1]):
            raise KITTIError(f"{path}:{lineno}: type id {v[1]:g} is not {expected} "
                             f"(AB3DMOT ids: 1 Pedestrian, 2 Car, 3 Cyclist)")
        rows.append(v)
    a = np.array(rows, dtype=np.float64).reshape(len(rows), 15)
    return Boxes(a[:, 0].astype(np.int64), np.full(len(a), expected, dtype=object), a[:, 6],
                 np.full(len(a), -1), a[:, 7:14])


def read_labels(path: str) -> Boxes:
    """KITTI tracking labels (``DontCare`` rows skipped)."""
    what = "17 or 18 fields (frame track_id type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry)"
    frames, tracks, types, boxes = [], [], [], []
    for lineno, text in _lines(path):
        parts = text.split()
        if len(parts) not in (17, 18):
            raise _bad(path, lineno, what, text)
        v = _floats(parts[:2] + parts[3:], path, lineno, what, text)
        frame = _frame(v[0], path, lineno, what, text)
        if parts[2] == "DontCare":
            continue
        if v[1] != int(v[1]) or v[1] < 0:
            raise _bad(path, lineno, what, text)
        frames.append(frame)
        tracks.append(int(v[1]))
        types.append(parts[2])
        boxes.append(v[9:16])
    n = len(frames)
    return Boxes(np.array(frames, dtype=np.int64), np.array(types, dtype=object), np.zeros(n),
                 np.array(tracks, dtype=np.int64), np.array(boxes, dtype=np.float64).reshape(n, 7))


def read_calibration(path: str) -> np.ndarray:
    """``T_imu←rect`` (4, 4): rectified camera coordinates to the IMU frame."""
    found: dict[str, np.ndarray] = {}
    sizes = {"R0_rect": 9, "Tr_velo_to_cam": 12, "Tr_velo_cam": 12, "Tr_imu_to_velo": 12, "Tr_imu_velo": 12}
    for lineno, text in _lines(path):
        key, _, rest = text.partition(":")
        key = key.strip()
        if key in sizes:
            parts = rest.split()
            what = f"{key}: {sizes[key]} numbers"
            if len(parts) != sizes[key]:
                raise _bad(path, lineno, what, text)
            found[key] = np.array(_floats(parts, path, lineno, what, text))
    names = {"R0_rect": ("R0_rect",), "velo": ("Tr_velo_to_cam", "Tr_velo_cam"),
             "imu": ("Tr_imu_to_velo", "Tr_imu_velo")}
    got = {}
    for role, options in names.items():
        hit = [found[o] for o in options if o in found]
        if not hit:
            raise KITTIError(f"{path}: no {options[0]} line")
        got[role] = hit[0]
    r0 = np.eye(4)
    r0[:3, :3] = got["R0_rect"].reshape(3, 3)
    velo_to_cam, imu_to_velo = np.eye(4), np.eye(4)
    velo_to_cam[:3] = got["velo"].reshape(3, 4)
    imu_to_velo[:3] = got["imu"].reshape(3, 4)
    return np.linalg.inv(r0 @ velo_to_cam @ imu_to_velo)


def read_tum(path: str) -> np.ndarray:
    """TUM rows ``t x y z qx qy qz qw`` as 4x4 poses (n, 4, 4)."""
    what = "8 numbers (t x y z qx qy qz qw)"
    out = []
    for lineno, text in _lines(path):
        parts = text.split()
        if len(parts) != 8:
            raise _bad(path, lineno, what, text)
        _, x, y, z, qx, qy, qz, qw = _floats(parts, path, lineno, what, text)
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if not 0.9 < norm < 1.1:
            raise KITTIError(f"{path}:{lineno}: quaternion norm {norm:.3g} is not 1")
        qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
        m = np.eye(4)
        m[:3, :3] = [[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
                     [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
                     [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]]
        m[:3, 3] = x, y, z
        out.append(m)
    return np.array(out).reshape(len(out), 4, 4)


def read_kitti_poses(path: str) -> np.ndarray:
    """KITTI odometry rows (3x4 row-major) as 4x4 poses (n, 4, 4)."""
    what = "12 numbers (a 3x4 row-major pose)"
    out = []
    for lineno, text in _lines(path):
        parts = text.split()
        if len(parts) != 12:
            raise _bad(path, lineno, what, text)
        m = np.eye(4)
        m[:3] = np.reshape(_floats(parts, path, lineno, what, text), (3, 4))
        out.append(m)
    return np.array(out).reshape(len(out), 4, 4)


# --------------------------------------------------------------------------- #
# Geometry
# --------------------------------------------------------------------------- #


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def planar(poses: np.ndarray) -> np.ndarray:
    """(n, 4, 4) -> (n, 3) ``[x, y, yaw]``, yaw of the x axis about z."""
    return np.column_stack([poses[:, 0, 3], poses[:, 1, 3], np.arctan2(poses[:, 1, 0], poses[:, 0, 0])])


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ∘ b`` for planar poses (..., 3)."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap(b[..., 2] - a[..., 2])], axis=-1)


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ∘ b`` for planar poses (..., 3)."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1], a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     wrap(a[..., 2] + b[..., 2])], axis=-1)


def se2_exp(xi: np.ndarray) -> np.ndarray:
    """SE(2) exponential of tangent ``[v_x, v_y, ω]`` (3,), the scenario's odometry convention."""
    vx, vy, w = xi
    if abs(w) < 1e-9:
        a, b = 1.0 - w * w / 6, w / 2
    else:
        a, b = math.sin(w) / w, (1 - math.cos(w)) / w
    return np.array([a * vx - b * vy, b * vx + a * vy, w])


def boxes_in_vehicle(box: np.ndarray, imu_from_rect: np.ndarray) -> np.ndarray:
    """Camera boxes (n, 7) -> planar object poses (n, 3) in the vehicle (IMU) frame.

    The position is the box's bottom centre; the heading is the box's forward axis
    ``(cos ry, 0, −sin ry)`` (KITTI: ``ry`` rotates about the camera's y axis, which points down)
    rotated into the IMU frame.
    """
    p = imu_from_rect[:3, :3] @ box[:, 3:6].T + imu_from_rect[:3, 3:4]
    forward = np.stack([np.cos(box[:, 6]), np.zeros(len(box)), -np.sin(box[:, 6])])
    d = imu_from_rect[:3, :3] @ forward
    return np.column_stack([p[0], p[1], np.arctan2(d[1], d[0])])


def _corners(box: np.ndarray) -> np.ndarray:
    """Bird's-eye corners (4, 2) in camera ``(x, z)`` of one box ``h w l x y z ry``."""
    _, w, l, x, _, z, ry = box
    c, s = math.cos(ry), math.sin(ry)
    local = np.array([[l, w], [l, -w], [-l, -w], [-l, w]]) / 2
    # Camera x-z plane: forward (cos ry, -sin ry), side (sin ry, cos ry).
    return np.column_stack([x + local[:, 0] * c + local[:, 1] * s, z - local[:, 0] * s + local[:, 1] * c])


def _clip(poly: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: ``poly`` clipped to the left of the directed edge a→b."""
    def side(p):
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
    out = []
    for i in range(len(poly)):
        p, q = poly[i], poly[(i + 1) % len(poly)]
        sp, sq = side(p), side(q)
        if sp >= 0:
            out.append(p)
        if sp * sq < 0:
            out.append(p + (q - p) * (sp / (sp - sq)))
    return np.array(out).reshape(-1, 2)


def _area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _ccw(poly: np.ndarray) -> np.ndarray:
    """The polygon's corners counter-clockwise (the clipping keeps the left side of each edge)."""
    u, v = poly[1] - poly[0], poly[2] - poly[1]
    return poly[::-1] if u[0] * v[1] - u[1] * v[0] < 0 else poly


def iou_3d(a: np.ndarray, b: np.ndarray) -> float:
    """3D IoU of two KITTI boxes ``h w l x y z ry`` (rotated in the ground plane, y down)."""
    pa, pb = _ccw(_corners(a)), _ccw(_corners(b))
    inter = pa
    for i in range(4):
        if len(inter) == 0:
            break
        inter = _clip(inter, pb[i], pb[(i + 1) % 4])
    # Heights: a box spans y in [y - h, y] (y is the bottom, and y points down).
    dy = max(0.0, min(a[4], b[4]) - max(a[4] - a[0], b[4] - b[0]))
    v = _area(inter) * dy
    union = a[0] * a[1] * a[2] + b[0] * b[1] * b[2] - v
    return v / union if union > 0 else 0.0


def score_vector(logits: dict[int, float]) -> np.ndarray:
    """The detection's scores (3,): ``σ(logit_c)`` where class ``c``'s detector fired, else 0.

    Each PointRCNN detector reports one logit for its own class; "did not fire here" is the limit
    ``logit → −∞``, probability 0. Entries are in [0, 1) and need not sum to 1.
    """
    z = np.zeros(len(CLASSES))
    for c, s in logits.items():
        z[c] = 1.0 / (1.0 + math.exp(-s))
    return z


def viewpoint(robot: np.ndarray, obj: np.ndarray) -> float:
    """docs/file_format.md: ``atan2(v_y, v_x)`` with ``v = R(θ_o)ᵀ (p_x − p_o)``."""
    v = between(obj, np.array([robot[0], robot[1], 0.0]))
    return float(math.atan2(v[1], v[0]))
