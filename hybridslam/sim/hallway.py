"""The simulated hallway of Doherty's thesis (Sec. 5.4.1, Fig. 5-3), written as scenario files.

A rectangular hallway loop (centerline ``length`` × ``width``, default 20 m × 10 m) that the robot
drives counterclockwise at ``step_length`` per step, from the origin facing +x, turning 90° at each
corner; the default ``steps`` is one full loop, so the run ends where it started (a loop closure).
Landmarks of two classes stand in rows along both walls of the hallway (``wall_offset`` from the
centerline, every ``spacing`` metres) with classes in the repeating ``pattern`` A A B A A B …: every
stretch of wall looks like every other (perceptual aliasing).

The sensor and noise are the thesis's: detections of every landmark within a 120° field of view up
to 3.5 m (the file's ``sensor.detection_probability`` is 1), range and bearing noise of variance
0.01 each, semantic labels drawn from a confusion matrix of 90% accuracy (thesis Eq. 2.14; scores are the one-hot label), and odometry
``u_k = between(x_{k-1}, x_k) ∘ Exp(w_k)``, ``w_k ~ N(0, Λ_t)`` with
``Λ_t = diag(σ², σ², σ_θ²)`` (:func:`odometry_cov`). The study sweeps ``tr(Λ_t)`` over
:data:`LEVELS`.

Two maps: the default is an **unknown map** (no objects in the file, a ``discovery`` section,
ground truth under ``true_objects``), the thesis's setting; ``known_map=True`` lists every
landmark as a prior object instead, for estimators without discovery.

Seeded and reproducible. The odometry noise is ``sqrt(Λ_t)`` times standard normals drawn from one
stream and the detections from another, so scenarios of one seed at different noise levels share
their detections and differ only in the scale of the same odometry errors.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from ..models.scenario import Classifier, Detection, Discovery, Scenario, Step
from ..models import geometry, se2

LEVELS: tuple[float, ...] = tuple(float(v) for v in np.linspace(0.005, 0.05, 5))  # tr(Λ_t), Fig. 5-3d

_between = jax.jit(jax.vmap(se2.between))
_compose = jax.jit(jax.vmap(se2.compose))
_exp = jax.jit(jax.vmap(se2.exp))
_range_bearing = jax.jit(jax.vmap(jax.vmap(geometry.range_bearing, (None, 0)), (0, None)))


@dataclasses.dataclass(frozen=True)
class HallwaySetup:
    """The hallway's geometry, sensor and noise (thesis Sec. 5.4.1; the layout is ours)."""

    length: float = 20.0  # centerline of the loop, x extent (m)
    width: float = 10.0  # y extent (m)
    wall_offset: float = 1.0  # landmark rows this far either side of the centerline (m)
    spacing: float = 2.0  # between landmarks along a row (m)
    pattern: tuple[int, ...] = (0, 0, 1)  # classes along each row, repeated
    step_length: float = 1.0  # m per step
    max_range: float = 3.5
    fov: float = 2.0 * math.pi / 3.0  # 120°
    range_var: float = 0.01
    bearing_var: float = 0.01
    accuracy: float = 0.9  # diagonal of the confusion matrix
    rotation_ratio: float = 0.1  # σ_θ² / σ²: the thesis's example Λ_t = diag(0.01, 0.01, 0.001)
    robot_prior_var: float = 1e-4  # x_0 is (almost) known: it anchors the world frame
    object_prior_var: tuple[float, float, float] = (0.05, 0.05, 0.5e-3)  # known-map variant only
    discovery_margin: int = 10  # object slots beyond the true landmarks (spurious new objects)
    new_object_orientation_var: float = math.pi**2  # unobserved by range-bearing: ~uniform

    @property
    def perimeter(self) -> float:
        return 2.0 * (self.length + self.width)

    @property
    def loop_steps(self) -> int:
        """Steps of one loop (the default run)."""
        return int(round(self.perimeter / self.step_length))

    @property
    def num_classes(self) -> int:
        return max(2, max(self.pattern) + 1)

    @property
    def confusion(self) -> np.ndarray:
        """``matrix[label, class]``: ``accuracy`` on the diagonal, the rest spread evenly (Eq. 2.15)."""
        m = self.num_classes
        off = (1.0 - self.accuracy) / (m - 1)
        return np.full((m, m), off) + (self.accuracy - off) * np.eye(m)

    @property
    def new_object_log_density(self) -> float:
        """``-log(max_range · fov)``: a new object's detection uniform over the sensor footprint.

        The density is in range-bearing space, the space of the known objects' Gaussian
        ``N(z; h, Σ_v)`` it competes with; the semantic evidence is added by the estimator. A
        known object then loses to "new" beyond a Mahalanobis distance ``d² ≈ 2 (log N(0; Σ_v) +
        log(max_range · fov)) ≈ 9.5`` here (a ~3σ gate).
        """
        return -math.log(self.max_range * self.fov)


def odometry_cov(trace: float, rotation_ratio: float = HallwaySetup.rotation_ratio) -> np.ndarray:
    """``Λ_t = diag(σ², σ², σ_θ²)`` with ``tr(Λ_t) = trace`` and ``σ_θ² = rotation_ratio · σ²``.

    The default ratio 0.1 is that of the thesis's example ``Λ_t = diag(0.01, 0.01, 0.001)``
    (Sec. 5.4.1), so ``trace = 0.021`` gives exactly that matrix.
    """
    if not (math.isfinite(trace) and trace > 0):
        raise ValueError(f"trace: expected a positive number, got {trace!r}")
    s2 = trace / (2.0 + rotation_ratio)
    return np.diag([s2, s2, rotation_ratio * s2])


def _rectangle(s: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> tuple[np.ndarray, np.ndarray]:
    """Points at arc lengths ``s`` along the counterclockwise rectangle from ``(x0, y0)``, and the
    unit direction of the side each point lies on (a corner belongs to the side that starts there)."""
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])
    sides = np.diff(corners, axis=0)
    ends = np.cumsum(np.linalg.norm(sides, axis=1))
    s = np.mod(s, ends[-1])
    side = np.minimum(np.searchsorted(ends, s + 1e-9, side="right"), 3)
    start = np.concatenate([[0.0], ends[:-1]])[side]
    direction = sides[side] / np.linalg.norm(sides[side], axis=1, keepdims=True)
    return corners[side] + (s - start)[:, None] * direction, direction


def true_track(setup: HallwaySetup, steps: int) -> np.ndarray:
    """Poses ``x_0..x_T`` (T + 1, 3) along the centerline, each facing the side it drives next."""
    s = setup.step_length * np.arange(steps + 1)
    xy, d = _rectangle(s, 0.0, 0.0, setup.length, setup.width)
    return np.column_stack([xy, np.arctan2(d[:, 1], d[:, 0])])


def landmarks(setup: HallwaySetup) -> tuple[np.ndarray, np.ndarray]:
    """True landmark poses (N, 3), facing the hallway, and classes (N,): the inner row, then the outer."""
    o = setup.wall_offset
    rows = []
    for ring, outward in (((o, o, setup.length - o, setup.width - o), True),
                          ((-o, -o, setup.length + o, setup.width + o), False)):
        perimeter = 2.0 * (ring[2] - ring[0] + ring[3] - ring[1])
        s = setup.spacing * (0.5 + np.arange(int(perimeter // setup.spacing)))
        xy, d = _rectangle(s, *ring)
        # Counterclockwise, the left normal points into the loop: the inner row faces out, the outer in.
        normal = np.column_stack([d[:, 1], -d[:, 0]]) if outward else np.column_stack([-d[:, 1], d[:, 0]])
        rows.append(np.column_stack([xy, np.arctan2(normal[:, 1], normal[:, 0])]))
    poses = np.concatenate(rows)
    classes = np.concatenate([np.resize(np.asarray(setup.pattern), len(r)) for r in rows])
    return poses, classes


def _detections(rng: np.random.Generator, setup: HallwaySetup, poses: np.ndarray, objects: np.ndarray,
                classes: np.ndarray) -> list[tuple[Detection, ...]]:
    """Every landmark in view from each pose, nearest first, with range-bearing noise and a label."""
    rb = np.asarray(_range_bearing(poses, objects))  # (T, N, 2)
    # Draw for every (pose, landmark) pair, so the draws do not depend on what is in view.
    z = rb + rng.standard_normal(rb.shape) * np.sqrt([setup.range_var, setup.bearing_var])
    z[..., 0] = np.maximum(z[..., 0], 0.0)
    z[..., 1] = np.asarray(se2.wrap(z[..., 1]))
    u = rng.uniform(size=rb.shape[:2])
    cdf = np.cumsum(setup.confusion, axis=0)[:, classes]  # (M, N): P(label <= i | class of n)
    labels = np.minimum(np.sum(u[:, :, None] > cdf.T[None], axis=-1), setup.num_classes - 1)
    seen = (rb[..., 0] <= setup.max_range) & (np.abs(rb[..., 1]) <= setup.fov / 2)
    eye = np.eye(setup.num_classes)
    out = []
    for k in range(poses.shape[0]):
        visible = sorted(np.flatnonzero(seen[k]), key=lambda n: rb[k, n, 0])
        out.append(tuple(
            Detection(float(z[k, n, 0]), float(z[k, n, 1]), eye[labels[k, n]].copy(), int(n))
            for n in visible))
    return out


def hallway(
    seed: int, trace: float = 0.021, *, steps: int | None = None, known_map: bool = False,
    setup: HallwaySetup = HallwaySetup(),
) -> Scenario:
    """One hallway scenario with odometry noise ``tr(Λ_t) = trace`` (:func:`odometry_cov`).

    ``steps`` defaults to one loop (``setup.loop_steps``); more steps keep driving the loop.
    ``known_map=False`` (default) writes an unknown map: ``objects`` empty, ``discovery`` with
    ``max_objects = N + setup.discovery_margin`` (plus, beyond one loop, two slots per extra step and
    at most ``N``: room for the duplicates an estimator that has not closed the loop makes) and
    ``new_object_log_density`` of :attr:`HallwaySetup.new_object_log_density`, ground truth in
    ``true_objects``.
    ``known_map=True`` lists the ``N`` landmarks as objects whose prior means are their true poses
    perturbed by ``N(0, diag(object_prior_var))`` (the prior is honest), uniform class priors.
    """
    steps = setup.loop_steps if steps is None else int(steps)
    if steps < 1:
        raise ValueError(f"steps: expected a positive number, got {steps}")
    lam = odometry_cov(trace, setup.rotation_ratio)
    poses = true_track(setup, steps)
    objects, classes = landmarks(setup)
    odo_rng, det_rng, map_rng = (np.random.default_rng([seed, i]) for i in range(3))
    w = odo_rng.standard_normal((steps, 3)) * np.sqrt(np.diag(lam))
    odometry = np.asarray(_compose(_between(poses[:-1], poses[1:]), _exp(w)))
    dets = _detections(det_rng, setup, poses[1:], objects, classes)
    n, m = objects.shape[0], setup.num_classes
    common = dict(
        num_classes=m,
        robot_prior_mean=poses[0].copy(),
        robot_prior_cov=setup.robot_prior_var * np.eye(3),
        motion_cov=lam,
        geometric_cov=np.diag([setup.range_var, setup.bearing_var]),
        classifier=Classifier("confusion", matrix=setup.confusion),
        max_range=setup.max_range,
        fov=setup.fov,
        detection_probability=1.0,  # every landmark in view is detected (_detections)
        steps=tuple(Step(u, d) for u, d in zip(odometry, dets)),
        true_robot_poses=poses,
        metadata={"generator": f"hybridslam.hallway seed={seed} trace={trace!r} steps={steps} "
                               f"known_map={known_map}"},
    )
    if known_map:
        cov = np.diag(setup.object_prior_var)
        prior = objects + map_rng.standard_normal(objects.shape) * np.sqrt(setup.object_prior_var)
        prior[:, 2] = np.asarray(se2.wrap(prior[:, 2]))
        return Scenario(object_prior_means=prior, object_prior_covs=np.broadcast_to(cov, (n, 3, 3)).copy(),
                        class_prior=np.full((n, m), 1.0 / m), true_object_poses=objects,
                        true_classes=classes, **common)
    return Scenario(
        object_prior_means=np.zeros((0, 3)), object_prior_covs=np.zeros((0, 3, 3)),
        class_prior=np.zeros((0, m)),
        discovery=Discovery(n + setup.discovery_margin + min(2 * max(steps - setup.loop_steps, 0), n),
                            setup.new_object_log_density,
                            setup.new_object_orientation_var),
        true_objects=tuple((p, int(c)) for p, c in zip(objects, classes)), **common,
    )


def scenario_name(trace: float, seed: int) -> str:
    """The file name of one study cell, e.g. ``hallway_tr0.0050_seed0.json``."""
    return f"hallway_tr{trace:.4f}_seed{seed}.json"
