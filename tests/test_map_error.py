"""hybridslam.analysis.map_error: a result's objects against the true objects they stand for."""

from __future__ import annotations

import numpy as np

import hybridslam as hs
from hybridslam.analysis.map_error import map_error, object_landmarks
from hybridslam.io.result import ComponentRecord, Result, StepRecord
from hybridslam.io.scenario import Discovery


def _result(scenario, associations, objects=None) -> Result:
    top = ComponentRecord(1.0, associations, [0] * scenario.num_objects, np.zeros(3), np.eye(3))
    steps = [StepRecord(k, [top], {"entropy": 0.0, "det_cov": 1.0, "num_components": 1})
             for k in range(1, scenario.num_steps + 1)]
    return Result("test", steps, objects=objects)


def test_a_known_maps_objects_are_scored_against_their_own_true_poses():
    s = hs.simulate(0, steps=3)
    truth = [[d.true_object for d in step.detections] for step in s.steps]
    seen = sorted({o for step in truth for o in step})
    shift = np.zeros((s.num_objects, 3))
    shift[seen, 0] = 0.1 * (1 + np.arange(len(seen)))  # object seen[i] is 0.1 (i + 1) m off in x
    error = map_error(s, _result(s, truth, s.true_object_poses + shift))
    distances = 0.1 * (1 + np.arange(len(seen)))
    assert error["objects"] == len(seen)
    np.testing.assert_allclose([error["mean_m"], error["median_m"]], [distances.mean(), np.median(distances)])
    assert map_error(s, _result(s, truth)) == {}  # a filter writes no objects


def test_an_unknown_maps_objects_stand_for_their_majority_object():
    s = hs.simulate(0, steps=3)
    truth = [[d.true_object for d in step.detections] for step in s.steps]
    true_objects = tuple((p, 0) for p in s.true_object_poses)
    unknown = s.replace(object_prior_means=np.zeros((0, 3)), object_prior_covs=np.zeros((0, 3, 3)),
                        class_prior=np.zeros((0, 2)), true_object_poses=None, true_classes=None,
                        discovery=Discovery(8, -2.0, 9.87), true_objects=true_objects)
    assert truth == [[0, 1], [0], [0]]
    # Object 0 holds the three detections of true object 0 and object 1 the one of true object 1.
    objects = np.array([s.true_object_poses[0], s.true_object_poses[1]]) + [0.2, 0.0, 0.0]
    error = map_error(unknown, _result(unknown, truth, objects))
    assert object_landmarks(unknown, _result(unknown, truth)) == {0: 0, 1: 1}
    assert error["objects"] == 2
    np.testing.assert_allclose([error["mean_m"], error["median_m"]], 0.2, atol=1e-12)
    # The stray detection of true object 1 named object 0 too: object 0 still stands for true
    # object 0 (three votes to one), and object 1, with no detection left, is not scored.
    merged = [[0, 0], [0], [0]]
    assert object_landmarks(unknown, _result(unknown, merged)) == {0: 0}
    assert map_error(unknown, _result(unknown, merged, objects))["objects"] == 1
