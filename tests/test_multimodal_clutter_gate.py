"""multimodal on a known map with a clutter density: its candidates are the objects inside the
0.999 chi-square gate (``CLUTTER_GATE``), and a detection beyond every gate is clutter."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import hybridslam as hs
from hybridslam.driver import run
from hybridslam.io.scenario import Step


def _beside_object_0(clutter_log_density: float | None, offset: float, steps: int = 3) -> hs.Scenario:
    """A robot standing at the origin (heading sd 0.05 rad) that sees, at every step, one detection of
    no object at object 0's range but ``offset`` rad beside it. Objects known to 1 mm."""
    base = hs.simulate(2, steps=1, setup=hs.PaperSetup(max_detections=2, max_range=12.0))
    x, y = base.object_prior_means[0, :2]
    spurious = dataclasses.replace(base.steps[0].detections[0], range=float(math.hypot(x, y)),
                                   bearing=float(math.atan2(y, x)) + offset, true_object=None)
    return base.replace(
        steps=tuple(Step(odometry=np.zeros(3), detections=(spurious,)) for _ in range(steps)),
        robot_prior_cov=np.diag([1e-4, 1e-4, 0.0025]), geometric_cov=np.diag([0.01, 0.0004]),
        object_prior_covs=np.tile(np.eye(3) * 1e-6, (base.num_objects, 1, 1)),
        clutter_log_density=clutter_log_density, true_robot_poses=np.zeros((steps + 1, 3)))


def _best_headings(scenario: hs.Scenario) -> tuple[np.ndarray, list[int]]:
    est = hs.make_estimator("multimodal", capacity=2, samples=32, max_detections=1, smoother="filter")
    out = run(est, scenario)
    best = [max(s.components, key=lambda c: c.weight) for s in out.result.steps]
    return np.array([float(c.pose_mean[2]) for c in best]), [int(i.rejected) for i in out.infos]


def test_a_detection_beyond_the_gate_is_clutter():
    """0.25 rad beside object 0 (d² about 21 under the prediction, beyond the gate's 13.8) with a
    clutter density so low (-10) that object 0, rotating the pose 5 sds, would explain it better:
    it is clutter at every step and the heading stays put. Inside the gate (0.1 rad, d² about 3.4)
    the same density leaves it object 0's, and the heading follows it."""
    heading, rejected = _best_headings(_beside_object_0(-10.0, 0.25))
    assert rejected == [1, 1, 1]
    assert np.max(np.abs(heading)) < 1e-3
    heading, rejected = _best_headings(_beside_object_0(-10.0, 0.1))
    assert rejected == [0, 0, 0]
    assert heading[-1] < -0.05
