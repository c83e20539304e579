"""The off-the-shelf baseline: GTSAM iSAM2 with nearest-neighbour (ML) data association.

What a careful new GTSAM user writes for range-bearing SLAM with unknown associations, run on the
same scenario files (SCENARIO_FORMAT.md) as hybridslam's estimators and writing the same result files.

Per step k (one ``isam.update()``, like GTSAM's ``VisualISAM2Example.py``):

1. Odometry: ``BetweenFactorPose2(x_{k-1}, x_k, u_k)`` with noise ``motion_cov`` (GTSAM's convention is
   the scenario's); ``x_k`` is initialized at ``x_{k-1} ∘ u_k``.
2. Association, each detection in order, against the *predicted* ``x_k``: for every landmark l, the
   joint marginal of ``(x_{k-1}, l)`` from iSAM2's Bayes tree (``isam.jointMarginalCovariance``; exact,
   with the pose-landmark cross-covariance that separate ``marginalCovariance`` calls would drop),
   propagated through the odometry (``δx_k = Ad(u_k⁻¹) δx_{k-1} + w``). The innovation and its
   Jacobians come from linearizing the ``BearingRangeFactor2D`` itself (whitened by its noise model),
   so ``S = A P Aᵀ + I`` and ``d² = bᵀ S⁻¹ b``. The nearest landmark with ``d²`` inside the chi-square
   gate (2 dof, ``--gate`` 0.999 → 13.8) wins; each landmark at most once per step. Otherwise, on an
   unknown map (a ``discovery`` section) a new ``Point2`` landmark is back-projected from the
   measurement; on a known map the detection is dropped (association -1).
3. ``isam.update(new_factors, new_values)`` plus ``--extra-updates`` argument-less updates (default 1,
   the extra relinearization pass of GTSAM's iSAM2 examples); ``x_k``'s estimate and marginal are the
   step's online result.

Choices: landmarks are ``Point2`` (detections observe positions only; object orientations are
ignored); classifier scores are ignored (a geometry-only baseline); the discovery section's
``new_object_log_density`` is ignored (the gate alone decides "new"). A known map's objects get a
``PriorFactorPoint2`` from the position part of their prior. GTSAM's ``Pose2`` covariances live in the
body-frame tangent space; the scenario's and the result's are over the world-frame ``[x, y, theta]``,
so both are rotated by ``blockdiag(R(theta), 1)``. ``--true-associations`` uses each detection's
``true_object`` (the oracle; on an unknown map a true object's first detection creates its landmark).
``--batch`` re-solves the whole final graph with Levenberg-Marquardt (from the iSAM2 estimate) as the
converged reference for the smoothed ``trajectory`` and ``objects``. ``--associations-from RESULT``
uses the associations of another estimator's result file (its last step's top component) instead of
nearest neighbour: with ``--batch``, the batch solution of that estimator's final graph, against
which ``scripts/bench_whole_log.py`` checks the smoothers.

Result files: one component of weight 1 per step; ``associations`` index the scenario's objects, then
the created ones in creation order; ``classes`` all -1 (one per object so far); ``pose_mean`` /
``pose_cov`` the online iSAM2 estimate of ``x_k`` at step k; ``trajectory`` (x_0..x_T) and ``objects``
(``[x, y, 0]``) the final smoothed estimates; ``step_s`` per step: association + updates + ``x_k``'s
marginal. The printed table per file: ms/step (median, mean), final-pose translation error, APE
translation mean of the online ``x_1..x_T`` and of the smoothed trajectory (hybridslam's evo-style
APE, no alignment), landmarks created, detections dropped, and association accuracy: the fraction of
detections whose landmark is their true object (known map) or the first landmark created from a
detection of their true object (unknown map; a duplicate landmark counts as wrong).

Usage::

    python3 scripts/isam2_baseline.py /tmp/hallway/*.json -o runs/isam2 [--true-associations] [--batch]
    python3 scripts/isam2_baseline.py scenario.json -o result.json --gate 0.99 --extra-updates 0
    python3 scripts/isam2_baseline.py scenario.json -o batch.json --associations-from ours.json --batch
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from hybridslam.analysis import trajectory
from hybridslam.io.result import ComponentRecord, Result, StepRecord, parse_result, result_to_json
from hybridslam.io.scenario import Scenario, load_scenario
from hybridslam.config import setup


setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def world_jacobian(pose: gtsam.Pose2) -> np.ndarray:
    """d[x, y, theta] / d(tangent) at ``pose``: ``blockdiag(R(theta), 1)``."""
    J = np.eye(3)
    J[:2, :2] = pose.rotation().matrix()
    return J


def bearing_range(k: int, j: int, det, noise) -> gtsam.BearingRangeFactor2D:
    """The factor of detection ``det`` (range, bearing) from ``x_k`` of landmark ``j``: bearing first."""
    return gtsam.BearingRangeFactor2D(X(k), L(j), gtsam.Rot2(det.bearing), det.range, noise)


def predicted_joint(isam: gtsam.ISAM2, k: int, u: gtsam.Pose2, motion_cov: np.ndarray, j: int) -> np.ndarray:
    """Covariance (5×5, tangent coordinates) of ``(x_k, l_j)`` before step k's detections: iSAM2's joint
    marginal of ``(x_{k-1}, l_j)`` moved through ``x_k = x_{k-1} ∘ u ∘ Exp(w)``, so
    ``δx_k = Ad(u⁻¹) δx_{k-1} + w``."""
    T = np.eye(5)
    T[:3, :3] = u.inverse().AdjointMap()
    P = T @ isam.jointMarginalCovariance([X(k - 1), L(j)]).fullMatrix() @ T.T  # blocks in query order
    P[:3, :3] += motion_cov
    return P


def run(scenario: Scenario, gate: float = 0.999, true_associations: bool = False, extra_updates: int = 1,
        batch: bool = False, given: list[list[int]] | None = None) -> tuple[dict, dict]:
    """Run the baseline on one scenario: the result file's JSON object and a row of summary numbers.

    ``given``: per step, per detection, the landmark to use (−1: none; on an unknown map a landmark
    index met for the first time is created there, back-projected), instead of nearest neighbour:
    with ``batch``, the batch solution of another estimator's final graph."""
    gate_d2 = -2.0 * math.log(1.0 - gate)  # chi-square quantile, 2 dof
    unknown_map = scenario.discovery is not None
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.01)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    motion_noise = gtsam.noiseModel.Gaussian.Covariance(scenario.motion_cov)
    meas_noise = gtsam.noiseModel.Gaussian.Covariance(scenario.geometric_cov[::-1, ::-1])  # bearing, range

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    x0 = gtsam.Pose2(*scenario.robot_prior_mean)
    Jinv = np.linalg.inv(world_jacobian(x0))
    graph.add(gtsam.PriorFactorPose2(X(0), x0, gtsam.noiseModel.Gaussian.Covariance(
        Jinv @ scenario.robot_prior_cov @ Jinv.T)))
    values.insert(X(0), x0)
    for n in range(scenario.num_objects):  # known map: prior landmarks (positions only)
        p = gtsam.Point2(*scenario.object_prior_means[n, :2])
        graph.add(gtsam.PriorFactorPoint2(L(n), p, gtsam.noiseModel.Gaussian.Covariance(
            scenario.object_prior_covs[n, :2, :2])))
        values.insert(L(n), p)
    isam.update(graph, values)
    num_landmarks = scenario.num_objects
    landmark_of_truth: dict[int, int] = {}  # true object -> landmark (unknown map: created for it)
    history: list[list[int]] = []
    steps, step_s, dropped, correct, labelled = [], [], 0, 0, 0

    for k, step in enumerate(scenario.steps, start=1):
        t0 = time.perf_counter()
        u = gtsam.Pose2(*step.odometry)
        estimate = isam.calculateEstimate()
        x_pred = estimate.atPose2(X(k - 1)).compose(u)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.BetweenFactorPose2(X(k - 1), X(k), u, motion_noise))
        values.insert(X(k), x_pred)
        joint: dict[int, np.ndarray] = {}  # predicted covariance of (x_k, l), when first needed
        chosen: list[int] = []
        for det in step.detections:
            if given is not None:
                j = given[k - 1][len(chosen)]
                if j >= num_landmarks and not unknown_map:
                    raise ValueError(f"--associations-from: steps[{k - 1}] names landmark {j} of a known map of "
                                     f"{num_landmarks}")
                if j > num_landmarks:
                    raise ValueError(f"--associations-from: steps[{k - 1}] names landmark {j} before "
                                     f"{num_landmarks} exists")
                if j == num_landmarks:  # created here, as an estimator's new object
                    j = -1
            elif true_associations:
                if det.true_object is None:
                    raise ValueError(f"steps[{k - 1}]: --true-associations needs every detection's true_object")
                j = det.true_object if not unknown_map else landmark_of_truth.get(det.true_object, -1)
            else:
                best, j = gate_d2, -1
                for cand in range(num_landmarks):
                    if cand in chosen:
                        continue
                    v = gtsam.Values()
                    v.insert(X(k), x_pred)
                    v.insert(L(cand), estimate.atPoint2(L(cand)))
                    # Whitened by the noise model: A = Σ^-½ H, b = -Σ^-½ e, so S = A P Aᵀ + I.
                    A, b = bearing_range(k, cand, det, meas_noise).linearize(v).jacobian()
                    if cand not in joint:
                        joint[cand] = predicted_joint(isam, k, u, scenario.motion_cov, cand)
                    d2 = float(b @ np.linalg.solve(A @ joint[cand] @ A.T + np.eye(2), b))
                    if d2 < best:
                        best, j = d2, cand
            if j < 0 and unknown_map:  # a new landmark, back-projected from the measurement
                j, num_landmarks = num_landmarks, num_landmarks + 1
                values.insert(L(j), x_pred.transformFrom(
                    gtsam.Point2(det.range * math.cos(det.bearing), det.range * math.sin(det.bearing))))
                if det.true_object is not None:
                    landmark_of_truth.setdefault(det.true_object, j)
            if j >= 0:
                graph.add(bearing_range(k, j, det, meas_noise))
            else:
                dropped += 1
            chosen.append(j)
            if det.true_object is not None:
                labelled += 1
                correct += j >= 0 and j == (landmark_of_truth.get(det.true_object) if unknown_map
                                            else det.true_object)
        history.append(chosen)
        isam.update(graph, values)
        for _ in range(extra_updates):
            isam.update()
        pose = isam.calculateEstimatePose2(X(k))
        J = world_jacobian(pose)
        cov = J @ isam.marginalCovariance(X(k)) @ J.T
        step_s.append(time.perf_counter() - t0)

        mean = np.array([pose.x(), pose.y(), pose.theta()])
        metrics = {"entropy": 0.0, "det_cov": float(np.linalg.det(cov[:2, :2])), "num_components": 1}
        if scenario.true_robot_poses is not None:
            err = float(np.linalg.norm(mean[:2] - scenario.true_robot_poses[k, :2]))
            metrics.update(err_wmax=err, err_wavg=err)
        steps.append(StepRecord(k, [ComponentRecord(1.0, [list(a) for a in history], [-1] * num_landmarks, mean,
                                                    0.5 * (cov + cov.T))], metrics))

    final = isam.calculateEstimate()
    if batch:  # the reference: the whole graph solved to convergence from the iSAM2 estimate
        final = gtsam.LevenbergMarquardtOptimizer(isam.getFactorsUnsafe(), final).optimize()
    smoothed = np.array([[p.x(), p.y(), p.theta()] for p in (final.atPose2(X(k)) for k in range(len(steps) + 1))])
    objects = [[*final.atPoint2(L(j)), 0.0] for j in range(num_landmarks)]
    settings = (f"gate={gate:g} (d2 {gate_d2:.2f}), extra_updates={extra_updates}"
                + (", given associations" if given is not None else ", true associations" if true_associations
                   else ", nearest-neighbour association")
                + (", batch LM smoothing" if batch else ""))
    result = Result(f"isam2_baseline (GTSAM {importlib.metadata.version('gtsam')} iSAM2, geometry only; "
                    f"{settings})", steps, {"compile_s": 0.0, "step_s": step_s})
    obj = result_to_json(result) | {"trajectory": smoothed.tolist(), "objects": objects}
    parse_result(obj)
    row = {"steps": len(steps), "ms_median": 1e3 * float(np.median(step_s)), "ms_mean": 1e3 * float(np.mean(step_s)),
           "new_landmarks": num_landmarks - scenario.num_objects,
           "dropped": dropped, "assoc_acc": correct / labelled if labelled else math.nan}
    if scenario.true_robot_poses is not None:
        truth = scenario.true_robot_poses
        online = np.array([s.components[0].pose_mean for s in steps])
        row["final_err"] = float(np.linalg.norm(smoothed[-1, :2] - truth[-1, :2]))
        row["ape_online"] = trajectory.ape(truth[1:], online).statistics()["translation"]["mean"]
        row["ape_smoothed"] = trajectory.ape(truth[1:], smoothed[1:]).statistics()["translation"]["mean"]
    return obj, row


def _cell(value: float) -> str:
    return f"{value:>14d}" if isinstance(value, int) else f"{value:>14.3f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scenarios", nargs="+", help="hybridslam-scenario/1 files")
    p.add_argument("-o", "--output", required=True, help="folder for the result files, or a file for one input")
    p.add_argument("--gate", type=float, default=0.999, help="chi-square gate probability, 2 dof (default 0.999)")
    p.add_argument("--true-associations", action="store_true", help="use each detection's true_object (oracle)")
    p.add_argument("--extra-updates", type=int, default=1, help="extra isam.update() calls per step (default 1)")
    p.add_argument("--batch", action="store_true", help="smooth the final graph with Levenberg-Marquardt")
    p.add_argument("--associations-from", metavar="RESULT",
                   help="use the associations of RESULT's last step's top component (a hybridslam result file of "
                        "the one scenario given): with --batch, the batch solution of that estimator's final graph")
    args = p.parse_args(argv)
    given = None
    if args.associations_from is not None:
        if len(args.scenarios) != 1 or args.true_associations:
            p.error("--associations-from: one scenario, and not with --true-associations")
        from hybridslam.io.result import load_result
        given = [list(a) for a in load_result(args.associations_from).steps[-1].components[0].associations]
    if not 0.0 < args.gate < 1.0:
        p.error(f"--gate: expected a probability in (0, 1), got {args.gate}")
    if args.extra_updates < 0:
        p.error(f"--extra-updates: expected a non-negative number, got {args.extra_updates}")
    to_file = len(args.scenarios) == 1 and args.output.endswith(".json") and not os.path.isdir(args.output)
    if not to_file:
        os.makedirs(args.output, exist_ok=True)
    cols = ("steps", "ms_median", "ms_mean", "final_err", "ape_online", "ape_smoothed", "new_landmarks",
            "dropped", "assoc_acc")
    print(f"{'file':<32}" + "".join(f"{c:>14}" for c in cols))
    rows = []
    for path in args.scenarios:
        obj, row = run(load_scenario(path), args.gate, args.true_associations, args.extra_updates, args.batch, given)
        out = args.output if to_file else os.path.join(args.output, os.path.basename(path))
        with open(out, "w", encoding="utf-8") as f:
            json.dump(obj, f)
        rows.append(row)
        print(f"{os.path.basename(path):<32}" + "".join(_cell(row.get(c, math.nan)) for c in cols))
    if len(rows) > 1:
        print(f"{'mean':<32}" + "".join(_cell(float(np.mean([r.get(c, math.nan) for r in rows]))) for c in cols))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
