"""Simulator of the paper's experimental setup (Sec. V), writing scenario files.

Six objects of one class (``M = 2``, all of true class 0) scattered in two perceptually aliased
rows, an uncertain map (``Σ_o = diag(0.05, 0.05, 0.5e-3)``), a highly uncertain start
(``Σ_p = diag(100, 100, 0.04)``), ``Σ_w = diag(0.75e-3, 0.75e-3, 0.25e-3)``,
``Σ_v = diag(0.1, 0.05)``, classifier Eq. 18 with ``alpha = 0.25``, ``K = 15``. Every track
starts at the same pose and wanders smoothly (a random walk on the heading). Measurements are
sampled from the models, ground truth is recorded. The paper does not publish its map, so the
layout here is ours (see docs/studies/paper.md).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np

from ..models.scenario import Classifier, Detection, Scenario, Step
from ..models.registry import make_classifier


@dataclasses.dataclass(frozen=True)
class PaperSetup:
    """The constants of the paper's Sec. V (and the map and track shape we chose)."""

    object_poses: tuple[tuple[float, float, float], ...] = (
        (4.0, 3.0, 0.6), (4.5, -3.0, 2.2), (10.0, 3.5, -1.4),
        (10.5, -3.0, 2.9), (16.0, 3.0, -2.4), (16.5, -3.5, 1.1),
    )
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    object_cov: tuple[float, float, float] = (0.05, 0.05, 0.5e-3)
    robot_cov: tuple[float, float, float] = (100.0, 100.0, 0.04)
    motion_cov: tuple[float, float, float] = (0.75e-3, 0.75e-3, 0.25e-3)
    geometric_cov: tuple[float, float] = (0.1, 0.05)
    max_range: float = 6.0
    fov: float = 2.0 * np.pi / 3.0
    step_length: float = 1.0
    turn_std: float = 0.15  # radians per step, heading random walk
    max_detections: int = 2  # the detector reports at most this many (nearest) objects
    true_class: int = 0


def _between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[2]), np.sin(a[2])
    d = b[:2] - a[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], _wrap(b[2] - a[2])])


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], _wrap(a[2] + b[2])])


def _wrap(a: float) -> float:
    w = float(np.arctan2(np.sin(a), np.cos(a)))
    return w + 2 * np.pi if w <= -np.pi else w


def _exp(xi: np.ndarray) -> np.ndarray:
    t = xi[2]
    a, b = (1.0, 0.0) if abs(t) < 1e-9 else (np.sin(t) / t, (1 - np.cos(t)) / t)
    return np.array([a * xi[0] - b * xi[1], b * xi[0] + a * xi[1], _wrap(t)])


def _track(rng: np.random.Generator, setup: PaperSetup, steps: int) -> np.ndarray:
    poses = [np.asarray(setup.start, dtype=float)]
    for _ in range(steps):
        turn = rng.normal(0.0, setup.turn_std)
        poses.append(_compose(poses[-1], np.array([setup.step_length, 0.0, turn])))
    return np.stack(poses)


@eqx.filter_jit
def _score_model(classifier, viewpoint):
    """The classifier's class means ``(C, M)`` and square-root informations ``(C, M, M)`` at one
    viewpoint ``(2,)`` (Eq. 18), as one compiled call: evaluated op by op, the two cost about
    2 ms per detection, most of a simulated track's time."""
    return classifier.class_means(viewpoint), classifier.class_sqrt_informations(viewpoint)


def _observe(rng, setup: PaperSetup, classifier, x: np.ndarray, objects: np.ndarray) -> tuple[Detection, ...]:
    seen = []
    for n, o in enumerate(objects):
        q = _between(x, np.array([o[0], o[1], 0.0]))[:2]
        rng_, bearing = float(np.hypot(*q)), float(np.arctan2(q[1], q[0]))
        if rng_ <= setup.max_range and abs(bearing) <= setup.fov / 2:
            seen.append((rng_, bearing, n))
    seen.sort()
    dets = []
    for rng_, bearing, n in seen[: setup.max_detections]:
        noise = rng.multivariate_normal(np.zeros(2), np.diag(setup.geometric_cov))
        v = _between(objects[n], np.array([x[0], x[1], 0.0]))
        vp = v[:2] / np.linalg.norm(v[:2])  # the viewpoint as (cos θ, sin θ)
        mean, r = (np.asarray(a)[setup.true_class] for a in _score_model(classifier, vp))
        scores = mean + np.linalg.solve(r, rng.standard_normal(mean.shape[0]))
        dets.append(Detection(max(rng_ + noise[0], 0.0), _wrap(bearing + noise[1]), scores, n))
    return tuple(dets)


def move(pose: np.ndarray, action: np.ndarray, rng: np.random.Generator, setup: PaperSetup = PaperSetup()) -> np.ndarray:
    """The true next pose ``x ∘ a ∘ Exp(w)``, ``w ~ N(0, Σ_w)`` (the motion model of Eq. 11)."""
    w = rng.multivariate_normal(np.zeros(3), np.diag(setup.motion_cov))
    return _compose(_compose(np.asarray(pose, float), np.asarray(action, float)), _exp(w))


def observe(rng: np.random.Generator, pose: np.ndarray, objects: np.ndarray, classifier,
            setup: PaperSetup = PaperSetup()) -> tuple[Detection, ...]:
    """Detections from ``pose`` of the true ``objects`` (N, 3): the nearest visible ones, with
    range-bearing noise and scores drawn from ``classifier`` for class ``setup.true_class``."""
    return _observe(rng, setup, classifier, np.asarray(pose, float), np.asarray(objects, float))


def simulate(
    seed: int, steps: int = 10, alpha: float = 0.25, K: float = 15.0, setup: PaperSetup = PaperSetup()
) -> Scenario:
    """One paper-setup scenario: a sampled track of ``steps`` steps with its measurements.

    Seeded and reproducible: the same arguments give the same scenario. Scores are sampled from
    the ``mirror`` model (Eq. 18) with the given ``alpha`` and ``K``; the file names ``mirror``.
    """
    rng = np.random.default_rng(seed)
    classifier = make_classifier("mirror", 2, alpha, K)
    map_means = np.asarray(setup.object_poses, dtype=float)
    n = map_means.shape[0]
    object_cov = np.diag(setup.object_cov)
    truth = np.stack([_compose(m, rng.multivariate_normal(np.zeros(3), object_cov)) for m in map_means])
    poses = _track(rng, setup, steps)
    motion_cov = np.diag(setup.motion_cov)
    scenario_steps = []
    for k in range(1, steps + 1):
        w = rng.multivariate_normal(np.zeros(3), motion_cov)
        odometry = _compose(_between(poses[k - 1], poses[k]), _exp(w))
        scenario_steps.append(Step(odometry, _observe(rng, setup, classifier, poses[k], truth)))
    return Scenario(
        num_classes=2,
        object_prior_means=map_means,
        object_prior_covs=np.broadcast_to(object_cov, (n, 3, 3)).copy(),
        class_prior=np.full((n, 2), 0.5),
        robot_prior_mean=poses[0].copy(),
        robot_prior_cov=np.diag(setup.robot_cov),
        motion_cov=motion_cov,
        geometric_cov=np.diag(setup.geometric_cov),
        classifier=Classifier("mirror", alpha=float(alpha), K=float(K)),
        max_range=setup.max_range,
        fov=setup.fov,
        steps=tuple(scenario_steps),
        true_object_poses=truth,
        true_classes=np.full(n, setup.true_class),
        true_robot_poses=poses,
        metadata={"generator": f"hybridslam.simulate seed={seed} steps={steps} alpha={alpha} K={K}"},
    )
