"""Is an estimator's covariance honest, and did it associate right? Checks against ground truth.

A filter that reports too small a covariance gates out the right object, or accepts a wrong one,
when a loop closes. These host-side checks make that visible on simulated runs:

* :func:`pose_nees`: the normalized estimation error squared ``eᵀ Σ⁻¹ e`` of a pose (3 degrees
  of freedom: mean 3 for a consistent estimator, above 11.34 in 1% of its steps);
* :func:`heading_bound`: the Cramér-Rao bound on the heading of ``x_k``: the batch Fisher
  information of every factor up to step ``k`` (the prior on ``x_0``, the odometry of Eq. 11 and
  the range-bearing detections of Eq. 10, true associations), linearized at the true poses. No
  estimator can be more certain; a filter that reports less is overconfident;
* :func:`association_audit`: per detection, whether the estimator assigned it to the object it
  made of the same landmark's first detection (a loop closure, for a landmark first seen long
  ago), to an object that another landmark created (a wrong merge), or to a new object;
* :func:`loop_closure_report`: the audit and the pose's consistency, for one scenario and one result file;
* :func:`true_association_smoother`: the full smoother with the true associations, the reference
  against which the bound and the NEES are checked (issue 13 §5; ``scripts/hallway_consistency.py``);
* :func:`gated_oracle_result`: a result file whose associations are the truth, except that a
  landmark re-detected after ``gap`` steps becomes a new object, as a gated one-step association
  leaves it: the input on which a loop-closure back end is judged apart from the front end.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax
import numpy as np
import optimistix as optx

from ..estimators.smoothers import factors as smoother_factors
from ..inference import smoother as sm
from ..io.result import ComponentRecord, Result, StepRecord
from ..models.scenario import Scenario
from ..models import geometry, se2
from ..models.model import model_from_scenario
from ..models.motion import odometry_residual

NEES_BOUND_99 = 11.34  # chi-square 99% quantile, 3 degrees of freedom

_odometry_jacobians = jax.jit(jax.vmap(jax.jacfwd(odometry_residual, argnums=(0, 1))))  # Eq. 11
_detection_jacobians = jax.jit(jax.vmap(jax.jacfwd(geometry.range_bearing, argnums=(0, 1))))  # Eq. 10


def pose_nees(true_pose: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> float:
    """``eᵀ Σ⁻¹ e`` with ``e = x_true − x̂`` (heading wrapped to (−π, π]); dimensionless."""
    e = np.asarray(true_pose, float) - np.asarray(mean, float)
    e[2] = (e[2] + math.pi) % (2.0 * math.pi) - math.pi
    return float(e @ np.linalg.solve(np.asarray(cov, float), e))


def dead_reckoning_heading_var(scenario: Scenario, k: int) -> float:
    """Heading variance of ``x_k`` from the prior and odometry alone (rad²): ``Σ₀[θ,θ] + k Λ_t[θ,θ]``."""
    return float(scenario.robot_prior_cov[2, 2] + k * scenario.motion_cov[2, 2])


def heading_bound(scenario: Scenario, k: int) -> float:
    """The Cramér-Rao bound on the heading standard deviation of ``x_k`` given steps ``1..k`` (rad).

    The information matrix is ``Jᵀ W J`` over the poses ``x_0..x_k`` and the positions of the
    landmarks detected up to ``k``, with ``J`` the Jacobians of the factors at the truth and ``W``
    their inverse covariances (Eq. 10-11), plus the prior on ``x_0`` and, on a known map, the
    object priors' position marginals (``true_object`` indexes them); landmark orientations are
    not observed and left out.
    Needs the scenario's ground truth (``robot.true_poses``, ``true_object`` per detection and the
    objects' true poses).
    """
    poses, landmarks = _truth(scenario)
    if not 0 <= k <= scenario.num_steps:
        raise ValueError(f"k: expected a step in 0..{scenario.num_steps}, got {k}")
    step_of = np.array([j + 1 for j, step in enumerate(scenario.steps[:k]) for _ in step.detections], dtype=int)
    seen = np.array([d.true_object for step in scenario.steps[:k] for d in step.detections], dtype=int)
    landmark_ids, slot = np.unique(seen, return_inverse=True) if seen.size else (seen, seen)  # landmark -> column block
    n = 3 * (k + 1) + 2 * (int(slot.max()) + 1 if seen.size else 0)
    odometry = np.array([s.odometry for s in scenario.steps]).reshape(-1, 3)
    ja, jb = (np.asarray(a)[:k] for a in _odometry_jacobians(poses[:-1], poses[1:], odometry))
    # Padded to a power of two so that runs of one study share a few compiled shapes.
    pad = 1 << max(seen.size - 1, 0).bit_length()
    jx, jo = (np.asarray(a)[:seen.size] for a in _detection_jacobians(
        poses[np.resize(step_of, pad)] if seen.size else np.zeros((1, 3)),
        landmarks[np.resize(seen, pad)] if seen.size else np.zeros((1, 3))))
    # Whitened by the square-root information, so that the information is jacᵀ jac.
    w_odo = np.linalg.cholesky(np.linalg.inv(scenario.motion_cov)).T
    w_geo = np.linalg.cholesky(np.linalg.inv(scenario.geometric_cov)).T
    ja, jb, jx, jo = w_odo @ np.asarray(ja), w_odo @ np.asarray(jb), w_geo @ np.asarray(jx), w_geo @ np.asarray(jo)
    jac = np.zeros((3 * k + 2 * seen.size, n))
    rows = np.arange(3 * k).reshape(k, 3)
    for block, col in ((ja, 3 * np.arange(k)), (jb, 3 * np.arange(1, k + 1))):
        jac[rows[:, :, None], col[:, None, None] + np.arange(3)] = block
    rows = 3 * k + np.arange(2 * seen.size).reshape(-1, 2)
    jac[rows[:, :, None], 3 * step_of[:, None, None] + np.arange(3)] = jx
    jac[rows[:, :, None], 3 * (k + 1) + 2 * slot[:, None, None] + np.arange(2)] = jo[:, :, :2]
    info = jac.T @ jac
    info[:3, :3] += np.linalg.inv(scenario.robot_prior_cov)
    if scenario.discovery is None:  # a known map: the object priors inform the landmarks' positions
        for j, obj in enumerate(landmark_ids):
            block = 3 * (k + 1) + 2 * j + np.arange(2)
            info[block[:, None], block] += np.linalg.inv(np.asarray(scenario.object_prior_covs[obj])[:2, :2])
    e = np.zeros(n)
    e[3 * k + 2] = 1.0
    return float(math.sqrt(np.linalg.solve(info, e)[3 * k + 2]))


def _truth(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    if scenario.true_robot_poses is None:
        raise ValueError("robot.true_poses: the scenario has no ground truth for the robot")
    if scenario.true_objects is not None:
        landmarks = np.array([pose for pose, _ in scenario.true_objects])
    elif scenario.true_object_poses is not None:
        landmarks = np.asarray(scenario.true_object_poses)
    else:
        raise ValueError("true_objects: the scenario has no ground-truth object poses")
    for j, step in enumerate(scenario.steps):
        for i, d in enumerate(step.detections):
            if d.true_object is None:
                raise ValueError(f"steps[{j}].detections[{i}].true_object: missing (ground truth is needed)")
    return np.asarray(scenario.true_robot_poses), landmarks


@dataclasses.dataclass(frozen=True)
class Audit:
    """Counts over one run's detections (see :func:`association_audit`)."""

    redetections: int  # detections of a landmark first detected more than ``gap`` steps earlier
    closed: int  # ... assigned to the object made of that landmark's first detection
    wrong: int  # detections assigned to an object that another landmark's detection made first
    objects: int  # distinct objects the estimator used
    landmarks: int  # distinct true landmarks detected
    first_redetection: int | None  # step (1-based) of the first re-detection, None if none


def association_audit(true_objects: list[list[int | None]], associations: Sequence[Sequence[int] | np.ndarray], gap: int = 20) -> Audit:
    """Compare an association history with the truth, detection by detection.

    ``true_objects[j]`` / ``associations[j]``: the true landmark and the estimator's object of each
    detection of step ``j + 1`` (a result file component's ``associations``). An object *belongs*
    to the landmark of the first detection assigned to it.
    """
    if len(true_objects) != len(associations):
        raise ValueError(f"associations: {len(associations)} steps, the truth has {len(true_objects)}")
    owner: dict[int, int | None] = {}  # None: a detection without a true landmark (clutter)
    first: dict[int | None, tuple[int, int]] = {}  # landmark -> (step, object) of its first detection
    redet = closed = wrong = 0
    first_redetection = None
    for k, (truth, objs) in enumerate(zip(true_objects, associations), start=1):
        if len(truth) != len(objs):
            raise ValueError(f"associations[{k - 1}]: {len(objs)} detections, the truth has {len(truth)}")
        for t, o in zip(truth, objs):
            wrong += owner.get(o, t) != t
            if t in first and k - first[t][0] > gap:
                redet += 1
                closed += o == first[t][1]
                first_redetection = first_redetection or k
            owner.setdefault(o, t)
            first.setdefault(t, (k, o))
    return Audit(redet, closed, wrong, len(owner), len(first), first_redetection)


@dataclasses.dataclass(frozen=True)
class LoopClosureReport:
    """:class:`Audit` of the top component, and its pose just before the first re-detection."""

    audit: Audit
    nees: float | None  # pose NEES of the highest-weight component after step first_redetection − 1
    heading_z: float | None  # |heading error| / its reported standard deviation there
    heading_sd_ratio: float | None  # reported heading sd / dead-reckoning sd there


def loop_closure_report(scenario: Scenario, result: Result, gap: int = 20) -> LoopClosureReport:
    """Audit the highest-weight final component of ``result`` on ``scenario``'s ground truth."""
    poses, _ = _truth(scenario)
    truth = [[d.true_object for d in step.detections] for step in scenario.steps]
    top = max(result.steps[-1].components, key=lambda c: c.weight)
    audit = association_audit(truth, top.associations, gap)
    if audit.first_redetection is None or audit.first_redetection < 2:
        return LoopClosureReport(audit, None, None, None)
    k = audit.first_redetection - 1
    comp = max(result.steps[k - 1].components, key=lambda c: c.weight)
    cov = np.asarray(comp.pose_cov)
    err = (poses[k][2] - comp.pose_mean[2] + math.pi) % (2.0 * math.pi) - math.pi
    return LoopClosureReport(audit, pose_nees(poses[k], comp.pose_mean, cov), abs(err) / math.sqrt(cov[2, 2]),
                             math.sqrt(cov[2, 2] / dead_reckoning_heading_var(scenario, k)))


@dataclasses.dataclass(frozen=True)
class OracleRun:
    """:func:`true_association_smoother`'s output: per step ``k = 1..T`` the smoothed ``x_k``
    (``means (T, 3)``, ``covs (T, 3, 3)``: the Laplace marginal given steps ``1..k``), the final
    smoothed trajectory ``(T+1, 3)`` and, per step, whether the solve failed to converge."""

    means: np.ndarray
    covs: np.ndarray
    trajectory: np.ndarray
    failed: np.ndarray


def true_association_smoother(scenario: Scenario, max_steps: int = 50) -> OracleRun:
    """The full smoother (:mod:`hybridslam.inference.smoother`) with the true associations: at every
    step ``k`` the factor graph of steps ``1..k`` (prior, odometry Eq. 11, range-bearing factors
    Eq. 10 of every detection to its true landmark) re-solved by Levenberg-Marquardt, warm-started
    from step ``k-1``'s solution, and the marginal of ``x_k`` taken. The reference for
    :func:`heading_bound` and :func:`pose_nees`: with the right associations a consistent smoother
    reports the Cramér-Rao heading sd and a NEES below :data:`NEES_BOUND_99` in 99% of its steps.

    On an unknown map a landmark's slot is made at its first detection, initialized by
    back-projection from the dead-reckoning pose; on a known map ``true_object`` indexes the prior
    objects. Geometric factors only (the CRB's model). Needs ``true_object`` on every detection.
    """

    _truth(scenario)  # the ground truth it needs, with field-named errors
    t, dmax = scenario.num_steps, max(scenario.max_detections, 1)
    known = scenario.discovery is None
    slot_of: dict[int, int] = {}
    history = np.full((t, dmax), -1, dtype=np.int32)
    created = np.zeros(t + 1, dtype=np.int32)
    for j, step in enumerate(scenario.steps):
        for i, d in enumerate(step.detections):
            assert d.true_object is not None  # checked by _truth
            slot = d.true_object if known else slot_of.setdefault(d.true_object, len(slot_of))
            history[j, i] = slot
        created[j + 1] = scenario.num_objects if known else len(slot_of)
    n = scenario.num_objects if known else max(len(slot_of), 1)
    log = smoother_factors.scenario_log(scenario, n)
    odometry = np.asarray(log.odometry)
    factors = smoother_factors.history_factors(jax.numpy.asarray(history))
    model = model_from_scenario(scenario.replace(discovery=None) if not known else scenario)

    @jax.jit
    def solve(k, poses, objects, num_created):
        g = smoother_factors.graph(log, factors, k, num_created, model.sensor, model.motion_cov, semantic=False)
        sol = sm.solve(g, poses, objects, max_steps=max_steps)
        mean, cov = sm.marginal(sol, k)
        return sol.poses, sol.objects, mean[:3], cov[:3, :3], sol.result != optx.RESULTS.successful

    poses = np.tile(np.asarray(scenario.robot_prior_mean, float), (t + 1, 1))
    objects = np.zeros((n, 3))
    if known:
        objects[:] = scenario.object_prior_means
    means, covs, failed = np.zeros((t, 3)), np.zeros((t, 3, 3)), np.zeros(t, dtype=bool)
    for k in range(1, t + 1):
        poses[k] = np.asarray(se2.compose(jax.numpy.asarray(poses[k - 1]), jax.numpy.asarray(odometry[k - 1])))
        for i, d in enumerate(scenario.steps[k - 1].detections):
            slot = history[k - 1, i]
            if not known and slot >= created[k - 1]:  # first detection: back-projected
                c, s = math.cos(poses[k, 2] + d.bearing), math.sin(poses[k, 2] + d.bearing)
                objects[slot] = (poses[k, 0] + d.range * c, poses[k, 1] + d.range * s, 0.0)
        out = solve(k, poses, objects, int(created[k]))
        poses, objects = np.array(out[0]), np.array(out[1])
        means[k - 1], covs[k - 1], failed[k - 1] = np.asarray(out[2]), np.asarray(out[3]), bool(out[4])
    return OracleRun(means, covs, poses, failed)


@dataclasses.dataclass(frozen=True)
class OracleDrift:
    """How far the true-association smoother is from the truth just before the loop closes, and after.

    ``before_step``: the last step before the first re-detection (1-based; ``None`` if nothing is
    re-detected, and then the ``before_*`` fields are those of the last step). Position error (m),
    its reported sd along the worst direction (m, the largest eigenvalue of the marginal's
    position block), heading error (rad, wrapped) and sd there; ``final_error``: the final
    smoothed pose's position error (m), after every re-detection has closed the loop.
    """

    before_step: int | None
    before_error: float
    before_sd: float
    before_heading_error: float
    before_heading_sd: float
    final_error: float


def oracle_drift(scenario: Scenario, gap: int = 20, max_steps: int = 50) -> OracleDrift:
    """:func:`true_association_smoother` on ``scenario``, read just before its first re-detection
    (a landmark first detected more than ``gap`` steps earlier, as in :func:`association_audit`).

    It answers how much drift an estimator has to bridge to close the loop with *perfect*
    associations before it: no estimator of the same model can be expected to be closer than this
    when the re-detections arrive, so a gate or a new-object density that rejects an association
    at that distance rejects the loop closure itself.
    """
    if not (isinstance(gap, int) and gap >= 0):
        raise ValueError(f"gap: expected a non-negative int, got {gap!r}")
    poses, _ = _truth(scenario)
    truth = [[d.true_object for d in s.detections] for s in scenario.steps]
    perfect = [[-1 if t is None else t for t in row] for row in truth]  # every detection to its own landmark
    k = association_audit(truth, perfect, gap).first_redetection  # > gap + 1 >= 2: a step precedes it
    before = scenario.num_steps if k is None else k - 1
    run = true_association_smoother(scenario, max_steps)
    mean, cov = run.means[before - 1], run.covs[before - 1]
    return OracleDrift(
        before_step=None if k is None else before,
        before_error=float(np.linalg.norm(mean[:2] - poses[before, :2])),
        before_sd=float(math.sqrt(np.linalg.eigvalsh(cov[:2, :2])[-1])),
        before_heading_error=float(se2.wrap(mean[2] - poses[before, 2])),
        before_heading_sd=float(math.sqrt(cov[2, 2])),
        final_error=float(np.linalg.norm(run.trajectory[-1, :2] - poses[-1, :2])),
    )


def gated_oracle_result(scenario: Scenario, gap: int = 20) -> tuple[Result, dict[int, int]]:
    """A one-component result whose associations are the true ones, except that a detection of a
    landmark last detected more than ``gap`` steps earlier (and every later detection of it) goes to
    a new object (module docstring). ``pose_mean`` is dead reckoning (there is no estimator behind
    it; ``pose_cov`` is a placeholder). Returns it and the true landmark of each object.
    """
    if scenario.discovery is None:
        raise ValueError("gated_oracle_result: needs an unknown map (discovery)")
    _truth(scenario)
    slot: dict[object, int] = {}
    last: dict[int, int] = {}
    landmark: dict[int, int] = {}
    assoc: list[list[int]] = []
    for k, step in enumerate(scenario.steps):
        row = []
        for d in step.detections:
            assert d.true_object is not None  # checked by _truth
            o = int(d.true_object)
            key: object = ("late", o) if ("late", o) in slot or (o in last and k - last[o] > gap) else o
            s = slot.setdefault(key, len(slot))
            landmark[s] = o
            if key == o:
                last[o] = k
            row.append(s)
        assoc.append(row)
    n = scenario.discovery.max_objects
    if len(slot) > n:
        raise ValueError(f"gated_oracle_result: {len(slot)} objects, more than discovery.max_objects = {n}")
    classes = [-1] * n
    for s, o in landmark.items():
        classes[s] = int(scenario.true_objects[o][1]) if scenario.true_objects is not None else -1
    pose = jax.numpy.asarray(scenario.robot_prior_mean, dtype=float)
    steps = []
    for k, step in enumerate(scenario.steps):
        pose = se2.compose(pose, jax.numpy.asarray(step.odometry, dtype=float))
        steps.append(StepRecord(k + 1, [ComponentRecord(1.0, assoc[: k + 1], classes, np.asarray(pose), 0.01 * np.eye(3))],
                                {"entropy": 0.0, "det_cov": 1e-4, "num_components": 1}))
    return Result("true associations, re-detections after the gap as new objects", steps), landmark
