"""SE(2) on arrays of poses, the odometry path, the ground truth and the robust noise calibration
of an MRCLAM log (used by :mod:`.mrclam`; numpy only, no JAX compiles).

The calibration is the one the module docstring of :mod:`.mrclam` describes (Noise): per
component the median and ``1.4826·MAD`` of the residuals against the ground truth, the variance
written ``scale² + median²``; the odometry's drift from the residuals' sums over blocks of 5, 10,
20 and 40 s (:func:`drift_over_horizons`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

MAD_TO_SD = 1.4826  # 1 / Φ⁻¹(3/4): MAD · this is the sd of a Gaussian
DRIFT_BLOCK_S, MIN_BLOCKS = 5.0, 5  # the shortest drift horizon (s), and the blocks it needs
# The longer drift horizons (s): a landmark may be out of sight for tens of seconds (MRCLAM
# dataset 7, robot 1: 28 s from the start), and the odometry's errors stay correlated over that
# long. Each counts where the window holds LONG_MIN_BLOCKS of its blocks: an sd from n blocks is
# off by about 1/sqrt(2n) (32% at 5, 16% at 20), and the largest of several noisy estimates errs
# upwards, so a horizon may only raise the noise where it is measured well (logs of 200 s for 10 s,
# 800 s for 40 s; a 100 s window keeps the 5 s horizon alone).
DRIFT_HORIZONS_S, LONG_MIN_BLOCKS = (5.0, 10.0, 20.0, 40.0), 20

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


def drift_per_step(residuals: np.ndarray, block: int, min_blocks: int = MIN_BLOCKS) -> np.ndarray | None:
    """The per-step sd (d,) that the sums of ``residuals`` (T, d) over blocks of ``block`` steps
    imply, ``sqrt(mean(block sum²) / block)``; None with fewer than ``min_blocks`` blocks.

    For white noise it equals the per-step RMS; larger, the errors are correlated in time (a
    velocity scale error, command latency) and dead reckoning drifts faster than the per-step
    covariance says.
    """
    n = len(residuals) // block
    if n < min_blocks:
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

def _stats(residuals: np.ndarray) -> dict[str, Any]:
    """Median and robust scale per component, for the ``generator`` metadata."""
    if not len(residuals):
        return {"count": 0}
    median, scale = robust_location_scale(residuals)
    return {"count": len(residuals), "median": _floats(median), "scale": _floats(scale)}


def _drift_block(dt: float, horizon: float = DRIFT_BLOCK_S) -> int:
    """Steps of ``dt`` seconds in one drift block of ``horizon`` seconds."""
    return max(1, round(horizon / dt))


def drift_over_horizons(residuals: np.ndarray, dt: float) -> tuple[np.ndarray, dict[str, Any]] | None:
    """The per-step sd (d,) that covers the odometry's drift at every horizon of
    :data:`DRIFT_HORIZONS_S` the window measures (:data:`MIN_BLOCKS` blocks of the shortest,
    :data:`LONG_MIN_BLOCKS` of a longer one), per component the largest :func:`drift_per_step`;
    None when it does not hold 5 blocks of the shortest.

    A random walk with that per-step sd predicts a dead-reckoning covariance at least as large as
    the error's mean square over each of those horizons, so the first reading after a stretch
    without landmarks lies where ``S`` says it may (the clutter test, module docstring of
    :mod:`.mrclam`, Noise). One 5 s horizon undercounts it: on dataset 7's whole logs the
    longer horizons imply 1.8-2.1× the 5 s sd per step forward and up to 1.5× in heading. The metadata lists
    every horizon's sd.
    """
    rows = []
    for i, horizon in enumerate(DRIFT_HORIZONS_S):
        block = _drift_block(dt, horizon)
        sd = drift_per_step(residuals, block, MIN_BLOCKS if i == 0 else LONG_MIN_BLOCKS)
        if sd is not None:
            rows.append((horizon, block, sd))
    if not rows:
        return None
    sd = np.max([r[2] for r in rows], axis=0)
    return sd, {"horizons_s": [r[0] for r in rows], "block_steps": [r[1] for r in rows],
                "sd_by_horizon": [_floats(r[2]) for r in rows], "sd": _floats(sd)}


def _drift(residuals: np.ndarray, dt: float) -> dict[str, Any] | None:
    drift = drift_over_horizons(residuals, dt)
    return None if drift is None else drift[1]


def _floats(a: Any) -> Any:
    return np.round(np.asarray(a, dtype=np.float64), 9).tolist()
