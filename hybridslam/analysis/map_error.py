"""How far a result's map lies from the true one.

A smoother's result file carries the final best component's objects (``objects``, indexed like its
``classes``). Each estimated object that some detection was associated with stands for a true
object: on a known map the object itself, on an unknown map the true object most of its detections
came from (its *majority* object, as in ``experiments/mrclam.py``'s purity score). The map error is
the distance between the two positions (m), summarized over those objects.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from ..io.result import Result
from ..models.scenario import Scenario


def true_positions(scenario: Scenario) -> np.ndarray | None:
    """The true object positions ``(N, 2)`` that detections' ``true_object`` index (``true_objects``
    on an unknown map, the objects' ``true_pose`` on a known one), or ``None`` without them."""
    if scenario.discovery is not None:
        return None if not scenario.true_objects else np.array([p[:2] for p, _ in scenario.true_objects], float)
    poses = scenario.true_object_poses
    return None if poses is None else np.asarray(poses, float)[:, :2]


def majority(votes: dict[int, Counter]) -> dict[int, int]:
    """Each estimated object's majority true object, from its detections' ``votes`` (true object →
    count); ties go to the lower index."""
    return {o: min(c.items(), key=lambda kv: (-kv[1], kv[0]))[0] for o, c in votes.items()}


def object_landmarks(scenario: Scenario, result: Result) -> dict[int, int]:
    """Each estimated object of the final best component that a detection was associated with, and
    the true object it stands for (known map: itself; unknown map: its majority object, ties to the
    lower index). Detections without ``true_object`` are left out."""
    final = result.steps[-1].components[0].associations if result.steps else []
    votes: dict[int, Counter] = {}
    for step, associations in zip(scenario.steps, final):
        for detection, o in zip(step.detections, associations):
            if o >= 0 and detection.true_object is not None and detection.true_object >= 0:
                votes.setdefault(int(o), Counter())[int(detection.true_object)] += 1
    if scenario.discovery is None:
        return {o: o for o in votes}
    return majority(votes)


def map_error(scenario: Scenario, result: Result) -> dict[str, float]:
    """``objects`` (how many estimated objects were scored), ``mean_m`` and ``median_m`` (their
    distances to the true objects they stand for, m). Empty without the result's ``objects`` (a
    filter writes none) or without ground truth; ``{"objects": 0}`` when no object was detected."""
    truth = true_positions(scenario)
    if result.objects is None or truth is None:
        return {}
    pairs = object_landmarks(scenario, result)
    distances = [float(np.hypot(*(result.objects[o, :2] - truth[t]))) for o, t in sorted(pairs.items())
                 if o < len(result.objects)]
    if not distances:
        return {"objects": 0}
    return {"objects": len(distances), "mean_m": float(np.mean(distances)), "median_m": float(np.median(distances))}
