"""Trajectory error of an SE(2) estimate against ground truth: APE and RPE, and TUM trajectory files.

The definitions are evo's (``evo.core.metrics``, the metrics of the thesis's Table 4.1), for planar
poses ``[x, y, theta]`` embedded in SE(3) with ``z = 0`` and a rotation about ``z``:

* APE (absolute pose error) of pose ``i``: ``E_i = P_ref,i⁻¹ P_est,i``; its translation part is
  ``‖t_est,i − t_ref,i‖`` (m), its rotation part the angle of ``E_i``'s rotation,
  ``|wrap(θ_est,i − θ_ref,i)|`` (rad, in ``[0, π]``, evo's ``rotation_angle_rad``).
* RPE (relative pose error) over ``delta`` frames: ``E_i = (Q_i⁻¹ Q_{i+δ})⁻¹ (P_i⁻¹ P_{i+δ})`` with ``Q``
  the reference and ``P`` the estimate (TUM RGB-D benchmark, Sturm et al. 2012, Eq. 2); translation
  ``‖t(E_i)‖``, rotation ``|θ(E_i)|``.
* Statistics of an error sequence: max, mean, median, min, rmse, sse, std (population), exactly
  evo's ``get_all_statistics``.

No alignment is applied (evo's default without ``--align``): the estimate and the reference share the
world frame of the scenario. Trajectories are compared pose by pose, so they must have equal length.

A TUM file (``evo_ape tum ref.txt est.txt``) has one line ``t tx ty tz qx qy qz qw`` per pose;
:func:`write_tum` writes SE(2) poses as ``tz = qx = qy = 0``, ``qz = sin(θ/2)``, ``qw = cos(θ/2)``.
Host-side, after a run, in numpy: the SE(2) algebra of :mod:`hybridslam.models.se2`, row by row.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
from jaxtyping import ArrayLike, Float

from ..io.result import Result
from ..models.scenario import Scenario

STATISTICS = ("max", "mean", "median", "min", "rmse", "sse", "std")
_PLANAR_TOL = 1e-9  # a TUM pose further than this from the plane is not an SE(2) pose

def _wrap(angle: np.ndarray) -> np.ndarray:
    """:func:`hybridslam.models.se2.wrap` in numpy: angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2 * np.pi)


def _between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a_i⁻¹ ∘ b_i`` for every row (:func:`hybridslam.models.se2.between`, in numpy: these host-side
    metrics would otherwise compile a small XLA program per array shape)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    d = b[:, :2] - a[:, :2]
    t = np.stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0]], axis=-1)  # R(θ_a)ᵀ (b − a)
    return np.concatenate([t, _wrap(b[:, 2:] - a[:, 2:])], axis=-1)


@dataclasses.dataclass(frozen=True)
class PoseError:
    """Per-pose (APE) or per-pair (RPE) errors: translation (m) and rotation angle (rad)."""

    translation: np.ndarray  # (n,)
    rotation: np.ndarray  # (n,), in [0, pi]

    def statistics(self) -> dict[str, dict[str, float]]:
        """``{"translation": {stat: value}, "rotation": {stat: value}}`` over :data:`STATISTICS`."""
        return {"translation": statistics(self.translation), "rotation": statistics(self.rotation)}


def statistics(errors: np.ndarray) -> dict[str, float]:
    """max, mean, median, min, rmse, sse and std of ``errors``: evo's ``PE.get_all_statistics``."""
    e = np.asarray(errors, dtype=float)
    if e.ndim != 1 or e.size == 0:
        raise ValueError(f"errors: expected a non-empty 1-D array, got shape {e.shape}")
    return {
        "max": float(np.max(e)), "mean": float(np.mean(e)), "median": float(np.median(e)),
        "min": float(np.min(e)), "rmse": math.sqrt(float(np.mean(e**2))), "sse": float(np.sum(e**2)),
        "std": float(np.std(e)),
    }


def _poses(poses: Float[ArrayLike, "T 3"], name: str) -> np.ndarray:
    p = np.asarray(poses, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ValueError(f"{name}: expected a (T, 3) array of poses [x, y, theta], got shape {p.shape}")
    if not bool(np.all(np.isfinite(p))):
        raise ValueError(f"{name}: not all finite")
    return p


def _pair(reference, estimate) -> tuple[np.ndarray, np.ndarray]:
    ref, est = _poses(reference, "reference"), _poses(estimate, "estimate")
    if ref.shape != est.shape:
        raise ValueError(f"estimate: {est.shape[0]} poses, but the reference has {ref.shape[0]}")
    return ref, est


def _error(poses: np.ndarray) -> PoseError:
    """Translation norm and absolute rotation angle of error poses ``E`` (n, 3)."""
    e = np.asarray(poses)
    return PoseError(np.linalg.norm(e[:, :2], axis=-1), np.abs(e[:, 2]))


def ape(reference: Float[ArrayLike, "T 3"], estimate: Float[ArrayLike, "T 3"]) -> PoseError:
    """Absolute pose error ``E_i = P_ref,i⁻¹ P_est,i`` of every pose (evo's ``APE``, module docstring)."""
    ref, est = _pair(reference, estimate)
    return _error(_between(ref, est))


def rpe(reference: Float[ArrayLike, "T 3"], estimate: Float[ArrayLike, "T 3"], delta: int = 1) -> PoseError:
    """Relative pose error over ``delta`` frames, consecutive pairs ``(i, i + delta)`` (evo's ``RPE``)."""
    ref, est = _pair(reference, estimate)
    if not (isinstance(delta, int) and 1 <= delta < ref.shape[0]):
        raise ValueError(f"delta: expected an integer in [1, {ref.shape[0] - 1}] frames, got {delta!r}")
    i = np.arange(0, ref.shape[0] - delta, delta)
    q_rel = _between(ref[i], ref[i + delta])
    p_rel = _between(est[i], est[i + delta])
    return _error(_between(q_rel, p_rel))


def trajectory_errors(
    reference: Float[ArrayLike, "T 3"], estimate: Float[ArrayLike, "T 3"]
) -> dict[str, dict[str, float]]:
    """All of Table 4.1 for both metrics: keys ``ape_translation``, ``ape_rotation``, ``rpe_translation``,
    ``rpe_rotation`` (RPE over 1 frame; absent for a one-pose trajectory), each ``{stat: value}``."""
    out = {f"ape_{part}": s for part, s in ape(reference, estimate).statistics().items()}
    if np.shape(reference)[0] > 1:
        out.update({f"rpe_{part}": s for part, s in rpe(reference, estimate).statistics().items()})
    return out


def trajectory_from_result(result: Result) -> tuple[np.ndarray, np.ndarray]:
    """The estimated trajectory: timestamps ``k`` and the highest-weight component's ``pose_mean`` after
    each step ``k`` (the components of a result step are sorted by weight, so it is the first).

    This is the MAP-component trajectory as it was estimated online (a filter's ``x_k`` at time ``k``,
    not smoothed by later steps).
    """
    if not result.steps:
        raise ValueError("result: no steps, so no trajectory")
    stamps = np.array([s.k for s in result.steps], dtype=float)
    return stamps, np.stack([np.asarray(s.components[0].pose_mean, dtype=float) for s in result.steps])


def smoothed_trajectory_from_result(result: Result) -> tuple[np.ndarray, np.ndarray] | None:
    """The smoothed trajectory ``x_1..x_T`` of a result file's optional ``trajectory`` key (the final
    highest-weight component, every pose relinearized with all the data), timestamps ``k = 1..T``;
    ``None`` when the result has none (a filter). Same timestamps as :func:`trajectory_from_result`,
    so both compare to :func:`trajectory_from_scenario` pose by pose."""
    if result.trajectory is None:
        return None
    poses = np.asarray(result.trajectory, dtype=float)[1:]
    return np.arange(1, poses.shape[0] + 1, dtype=float), poses


def error_summary(result: Result, scenario: Scenario) -> dict[str, float]:
    """Translation errors of a run against the scenario's ground truth (m): ``ape_online`` (APE mean of
    the online ``x_k``), ``rpe_online`` (RPE mean, 1 frame), ``final`` (the last pose), and, with a
    smoothed trajectory, ``ape_smoothed``, ``rpe_smoothed`` and ``final_smoothed`` (its last pose; left
    out if it is not finite). Empty
    without ground truth or with a non-finite online estimate."""
    if scenario.true_robot_poses is None or not result.steps:
        return {}
    _, truth = trajectory_from_scenario(scenario)
    _, online = trajectory_from_result(result)
    if not (np.all(np.isfinite(truth)) and np.all(np.isfinite(online))):
        return {}
    out = {"ape_online": float(np.mean(ape(truth, online).translation)),
           "final": float(np.linalg.norm(online[-1, :2] - truth[-1, :2]))}
    if truth.shape[0] > 1:
        out["rpe_online"] = float(np.mean(rpe(truth, online).translation))
    smoothed = smoothed_trajectory_from_result(result)
    if smoothed is not None and np.all(np.isfinite(smoothed[1])):
        out["ape_smoothed"] = float(np.mean(ape(truth, smoothed[1]).translation))
        out["final_smoothed"] = float(np.linalg.norm(smoothed[1][-1, :2] - truth[-1, :2]))
        if truth.shape[0] > 1:
            out["rpe_smoothed"] = float(np.mean(rpe(truth, smoothed[1]).translation))
    return out


def trajectory_from_scenario(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth trajectory ``x_1..x_T`` (``robot.true_poses[1:]``) with timestamps ``k = 1..T``."""
    if scenario.true_robot_poses is None:
        raise ValueError("robot.true_poses: the scenario has no ground truth")
    poses = np.asarray(scenario.true_robot_poses, dtype=float)[1:]
    return np.arange(1, poses.shape[0] + 1, dtype=float), poses


def write_tum(path: str | os.PathLike, timestamps: ArrayLike, poses: Float[ArrayLike, "T 3"]) -> None:
    """Write SE(2) ``poses`` as a TUM trajectory file: a ``t tx ty tz qx qy qz qw`` line each, exact floats."""
    p = np.asarray(_poses(poses, "poses"))
    t = np.asarray(timestamps, dtype=float)
    if t.shape != (p.shape[0],):
        raise ValueError(f"timestamps: expected {p.shape[0]} numbers (one per pose), got shape {t.shape}")
    half = 0.5 * p[:, 2]
    rows = np.stack([t, p[:, 0], p[:, 1], np.zeros_like(t), np.zeros_like(t), np.zeros_like(t),
                     np.sin(half), np.cos(half)], axis=-1)
    with open(path, "w", encoding="utf-8") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        f.writelines(" ".join(repr(float(v)) for v in row) + "\n" for row in rows)


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file of planar poses: timestamps ``(T,)`` and poses ``(T, 3)`` ``[x, y, theta]``.

    Lines starting with ``#`` are comments. A pose off the plane (``tz``, ``qx`` or ``qy`` not 0) is an
    error naming its line.
    """
    rows = []
    with open(path, encoding="utf-8") as f:
        for n, line in enumerate(f, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            try:
                values = [float(v) for v in text.replace(",", " ").split()]
            except ValueError:
                raise ValueError(f"{os.fspath(path)}:{n}: not a list of numbers") from None
            if len(values) != 8:
                raise ValueError(
                    f"{os.fspath(path)}:{n}: expected 8 numbers (t tx ty tz qx qy qz qw), got {len(values)}")
            t, x, y, z, qx, qy, qz, qw = values
            norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
            if norm == 0.0 or max(abs(z), abs(qx) / norm, abs(qy) / norm) > _PLANAR_TOL:
                raise ValueError(f"{os.fspath(path)}:{n}: not a planar pose (tz, qx, qy must be 0)")
            rows.append((t, x, y, 2.0 * math.atan2(qz, qw)))
    if not rows:
        raise ValueError(f"{os.fspath(path)}: no poses")
    data = np.array(rows)
    return data[:, 0], np.concatenate([data[:, 1:3], _wrap(data[:, 3:])], axis=-1)
