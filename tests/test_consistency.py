"""Consistency checks against ground truth: NEES, the Cramér-Rao heading bound, the association audit."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridslam  # noqa: F401  (float64)
from hybridslam.analysis import consistency
from hybridslam.io.result import ComponentRecord, Result, StepRecord
from hybridslam.models import geometry
from hybridslam.models.motion import odometry_residual
from hybridslam.sim.hallway import hallway


@pytest.fixture(scope="module")
def scenario():
    return hallway(0, 0.021)


@given(st.floats(-3.0, 3.0), st.integers(-2, 2))
@settings(max_examples=25, deadline=None)
def test_nees_is_the_mahalanobis_norm_with_the_heading_wrapped(dtheta, turns):
    cov = np.diag([0.5, 2.0, 0.25])
    truth = np.array([1.0, -2.0, 0.3])
    mean = truth - np.array([1.0, 2.0, dtheta + 2.0 * math.pi * turns])
    assert consistency.pose_nees(truth, mean, cov) == pytest.approx(1.0 / 0.5 + 4.0 / 2.0 + dtheta**2 / 0.25)


def test_without_detections_the_bound_is_dead_reckoning(scenario):
    blind = scenario.replace(steps=tuple(dataclasses.replace(s, detections=()) for s in scenario.steps))
    for k in (0, 1, 7, 30):
        assert consistency.heading_bound(blind, k) == pytest.approx(
            math.sqrt(consistency.dead_reckoning_heading_var(blind, k)), rel=1e-9)


def _bound_by_loops(scenario, k):
    """The same information matrix assembled factor by factor (an independent check of the indexing)."""
    poses = scenario.true_robot_poses
    marks = np.array([p for p, _ in scenario.true_objects])
    dets = [(j + 1, d.true_object) for j, s in enumerate(scenario.steps[:k]) for d in s.detections]
    col = {t: 3 * (k + 1) + 2 * i for i, t in enumerate(sorted({t for _, t in dets}))}
    n = 3 * (k + 1) + 2 * len(col)
    info = np.zeros((n, n))
    info[:3, :3] = np.linalg.inv(scenario.robot_prior_cov)
    odometry_jac = jax.jit(jax.jacfwd(odometry_residual, argnums=(0, 1)))
    detection_jac = jax.jit(jax.jacfwd(geometry.range_bearing, argnums=(0, 1)))
    for j in range(1, k + 1):
        ja, jb = odometry_jac(poses[j - 1], poses[j], scenario.steps[j - 1].odometry)
        jac = np.zeros((3, n))
        jac[:, 3 * j - 3:3 * j], jac[:, 3 * j:3 * j + 3] = ja, jb
        info += jac.T @ np.linalg.inv(scenario.motion_cov) @ jac
    for j, t in dets:
        jx, jo = detection_jac(poses[j], marks[t])
        jac = np.zeros((2, n))
        jac[:, 3 * j:3 * j + 3], jac[:, col[t]:col[t] + 2] = jx, np.asarray(jo)[:, :2]
        info += jac.T @ np.linalg.inv(scenario.geometric_cov) @ jac
    return math.sqrt(np.linalg.inv(info)[3 * k + 2, 3 * k + 2])


def test_bound_matches_a_factor_by_factor_assembly_and_lies_below_dead_reckoning(scenario):
    for k in (3, 9):
        bound = consistency.heading_bound(scenario, k)
        assert bound == pytest.approx(_bound_by_loops(scenario, k), rel=1e-9)
        assert bound < math.sqrt(consistency.dead_reckoning_heading_var(scenario, k))
    with pytest.raises(ValueError, match="k: expected a step"):
        consistency.heading_bound(scenario, scenario.num_steps + 1)


def test_audit_counts_closures_wrong_merges_and_objects():
    truth = [[0, 1], [0], [2], [1], [0, 2], [3]]
    # step 4: landmark 1 (first seen at step 1) gets object 5, a new one: not closed;
    # step 5: landmark 0 is closed (object 0); landmark 2 (seen 2 steps ago: not a re-detection) is merged into landmark 1's object 1;
    # step 6: landmark 3 is merged into object 0 (landmark 0's).
    est = [[0, 1], [0], [2], [5], [0, 1], [0]]
    audit = consistency.association_audit(truth, est, gap=2)
    assert audit == consistency.Audit(redetections=2, closed=1, wrong=2, objects=4, landmarks=4, first_redetection=4)
    assert consistency.association_audit(truth, truth, gap=2).closed == 2
    with pytest.raises(ValueError, match=r"associations\[1\]: 2 detections"):
        consistency.association_audit(truth, [[0, 1], [0, 1], [2], [1], [0, 2], [3]])


def test_report_of_the_truth_itself(scenario):
    """A result that follows the truth exactly: every loop closed, nothing merged, NEES 0."""
    truth = [[d.true_object for d in s.detections] for s in scenario.steps]
    steps = [StepRecord(k, [ComponentRecord(1.0, truth[:k], [], scenario.true_robot_poses[k], 0.01 * np.eye(3))], {})
             for k in range(1, scenario.num_steps + 1)]
    report = consistency.loop_closure_report(scenario, Result("truth", steps))
    assert report.audit.redetections > 0 and report.audit.closed == report.audit.redetections
    assert report.audit.wrong == 0 and report.audit.objects == report.audit.landmarks
    assert report.nees == 0.0 and report.heading_z == 0.0
    assert report.heading_sd_ratio == pytest.approx(0.1 / math.sqrt(consistency.dead_reckoning_heading_var(
        scenario, report.audit.first_redetection - 1)))


@pytest.mark.slow  # 60 smoother solves of a 60-step hallway; the suite's time
def test_with_the_true_associations_the_smoother_meets_the_bound():
    """The full smoother given the true associations reports the Cramér-Rao heading sd (the
    Laplace marginal at the MAP against the Fisher information at the truth: equal up to the
    estimation error) and, on a run where ``ml`` associates every detection right, its final
    trajectory is ``ml``'s smoothed trajectory (the same graph, solved by the same solver)."""
    import hybridslam as hs

    scenario = hs.simulate(0, steps=6)
    oracle = consistency.true_association_smoother(scenario)
    assert not oracle.failed.any()
    for k in range(1, scenario.num_steps + 1):
        sd = math.sqrt(oracle.covs[k - 1][2, 2])
        assert sd == pytest.approx(consistency.heading_bound(scenario, k), rel=0.1)
    run = hs.run_estimator(scenario, "ml")
    truth = [[d.true_object for d in s.detections] for s in scenario.steps]
    ml = run.result.steps[-1].components[0].associations
    assert [list(a[: len(t)]) for a, t in zip(ml, truth)] == truth  # ml got every association right
    np.testing.assert_allclose(oracle.trajectory, run.result.trajectory, atol=1e-6)


def test_oracle_drift_is_read_before_the_first_redetection_and_the_loop_closure_removes_it():
    from hybridslam.sim.hallway import HallwaySetup

    scenario = hallway(0, 0.005, setup=HallwaySetup(length=8.0, width=4.0))  # a 24-step loop
    drift = consistency.oracle_drift(scenario, gap=10)
    first = {}
    redetected = None
    for k, step in enumerate(scenario.steps, start=1):
        for d in step.detections:
            if redetected is None and d.true_object in first and k - first[d.true_object] > 10:
                redetected = k
            first.setdefault(d.true_object, k)
    assert drift.before_step == redetected - 1
    oracle = consistency.true_association_smoother(scenario)
    truth = np.asarray(scenario.true_robot_poses)
    err = np.linalg.norm(oracle.means[drift.before_step - 1, :2] - truth[drift.before_step, :2])
    assert drift.before_error == pytest.approx(err)
    assert drift.before_sd > 0 and drift.before_heading_sd > 0
    assert drift.final_error < drift.before_error  # the re-detections close the loop
    with pytest.raises(ValueError, match="gap: expected a non-negative int"):
        consistency.oracle_drift(scenario, gap=-1)
