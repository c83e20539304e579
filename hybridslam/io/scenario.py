"""Scenario files (`hybridslam-scenario/1`): load, validate, save, and stack for JAX.

The file layout is the contract in docs/file_format.md; this module keeps to it
exactly. The types it reads into (:class:`Scenario`, :class:`Step`, :class:`Detection`, ...) are the
model layer's (:mod:`hybridslam.models.scenario`), importable from here too. Every malformed input raises `ScenarioError` whose message is one line,
`<field path>: <what is wrong>`, e.g. ``steps[3].detections[1].scores: expected 2
numbers, got 3``. Paths use the JSON layout (0-based list indices), so
``steps[0]`` is step k = 1.

Pure numpy + stdlib json; no JAX here. `stack_steps` pads the steps into dense
arrays that the estimators feed to JAX.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
from typing import Any

import numpy as np

from . import jsonfields as jf
from .jsonfields import ScenarioError as ScenarioError
from ..models.scenario import MODELS as MODELS  # the domain types, read and written here
from ..models.scenario import Classifier as Classifier
from ..models.scenario import Detection as Detection
from ..models.scenario import Discovery as Discovery
from ..models.scenario import Scenario as Scenario
from ..models.scenario import StackedSteps as StackedSteps
from ..models.scenario import Step as Step

SCENARIO_FORMAT = "hybridslam-scenario/1"
_TOP_KEYS = frozenset(
    "format num_classes objects class_prior robot motion_cov geometric_cov "
    "classifier sensor steps discovery true_objects".split()
)


# --------------------------------------------------------------------------- #
# Equality for dataclasses holding arrays (the generated __eq__ would raise).
# --------------------------------------------------------------------------- #


# --------------------------------------------------------------------------- #
# Validation helpers: every check below is built from these.
# --------------------------------------------------------------------------- #


# --------------------------------------------------------------------------- #
# Sections
# --------------------------------------------------------------------------- #




def _classifier(obj: Any, path: str, num_classes: int) -> Classifier:
    obj = jf.as_object(obj, path)
    model = jf.get(obj, "model", path, jf.string)
    if model not in MODELS:
        jf.fail(jf.join(path, "model"), f"unknown model {model!r} (known: {', '.join(MODELS)})")
    if model in ("mirror", "independent"):
        if num_classes != 2:
            jf.fail(jf.join(path, "model"), f"{model!r} needs num_classes == 2, got {num_classes}")
        alpha = jf.get(obj, "alpha", path, jf.number)
        return Classifier(model, alpha=alpha, K=jf.get(obj, "K", path, jf.positive))
    if model == "confusion":
        matrix = jf.get(obj, "matrix", path, jf.matrix, num_classes, num_classes)
        return Classifier(model, matrix=jf.distributions(matrix, jf.join(path, "matrix"), axis=0))
    if model == "learned":
        file = jf.get(obj, "path", path, jf.string)
        if not file.strip():
            jf.fail(jf.join(path, "path"), "empty path")
        return Classifier(model, path=file)
    return Classifier(model)


def _sensor(obj: Any, path: str) -> tuple[float, float, float | None, float | None]:
    obj = jf.as_object(obj, path)
    max_range = jf.get(obj, "max_range", path, jf.positive)
    # Any positive field of view: from 2π on, every bearing is inside it (|bearing| <= fov / 2).
    fov = jf.get(obj, "fov", path, jf.positive)
    return (max_range, fov, jf.maybe(obj, "clutter_log_density", path, jf.number),
            jf.maybe(obj, "detection_probability", path, _probability))


def _probability(obj: Any, path: str) -> float:
    """A detection probability: in (0, 1]."""
    value = jf.number(obj, path)
    if not 0.0 < value <= 1.0:
        jf.fail(path, f"expected a number in (0, 1], got {value!r}")
    return value


def _discovery(obj: Any, path: str, num_objects: int) -> Discovery:
    obj = jf.as_object(obj, path)
    return Discovery(
        max_objects=jf.get(obj, "max_objects", path, jf.integer, num_objects),
        new_object_log_density=jf.get(obj, "new_object_log_density", path, jf.number),
        new_object_orientation_var=jf.get(obj, "new_object_orientation_var", path, jf.positive),
    )


def _true_object(obj: Any, path: str, num_classes: int) -> tuple[np.ndarray, int]:
    obj = jf.as_object(obj, path)
    return jf.get(obj, "pose", path, jf.vector, 3), jf.get(obj, "class", path, jf.integer, 0, num_classes)


def _detection(obj: Any, path: str, num_classes: int, num_truth: int) -> Detection:
    obj = jf.as_object(obj, path)
    rng = jf.get(obj, "range", path, jf.number)
    if rng < 0:
        jf.fail(jf.join(path, "range"), f"expected a non-negative number, got {rng!r}")
    return Detection(
        range=rng,
        bearing=jf.get(obj, "bearing", path, jf.number),
        scores=jf.get(obj, "scores", path, jf.vector, num_classes),
        true_object=jf.maybe(obj, "true_object", path, _truth_index(num_truth)),
    )


def _truth_index(num_truth: int):
    """``true_object``: an index into the map's objects (``true_objects`` with discovery). A module-level
    function bound by ``partial``, not a closure: a closure would be defined (and, under a runtime type
    checker's import hook, decorated) anew for every detection parsed."""
    return functools.partial(_parse_truth_index, num_truth)


def _parse_truth_index(num_truth: int, obj: Any, path: str) -> int:
    if num_truth == 0:
        jf.fail(path, "names a true object, but the scenario lists none (with discovery, the top-level "
                      "true_objects list holds them)")
    return jf.integer(obj, path, 0, num_truth)


def _step(obj: Any, path: str, num_classes: int, num_truth: int) -> Step:
    obj = jf.as_object(obj, path)
    odometry = jf.get(obj, "odometry", path, jf.vector, 3)
    dets = jf.get(obj, "detections", path, jf.as_list)
    path = jf.join(path, "detections")
    return Step(
        odometry,
        tuple(_detection(d, f"{path}[{i}]", num_classes, num_truth) for i, d in enumerate(dets)),
    )


def _all_or_none(values: list[Any]) -> np.ndarray | None:
    return np.array(values) if values and all(v is not None for v in values) else None


def parse_scenario(obj: Any) -> Scenario:
    """Validate a decoded JSON object and return the Scenario it describes."""
    top = jf.as_object(obj, "<root>")
    jf.check_format(top, SCENARIO_FORMAT)
    M = jf.get(top, "num_classes", "", jf.integer, 1)
    objects = [jf.as_object(o, f"objects[{i}]") for i, o in enumerate(jf.get(top, "objects", "", jf.as_list))]
    N = len(objects)
    paths = [f"objects[{i}]" for i in range(N)]
    class_prior = jf.maybe(top, "class_prior", "", jf.matrix, N, M)
    class_prior = np.full((N, M), 1.0 / M) if class_prior is None else class_prior
    robot = jf.get(top, "robot", "", jf.as_object)
    raw_steps = jf.get(top, "steps", "", jf.as_list)
    true_poses = jf.maybe(robot, "true_poses", "robot", jf.matrix, None, 3)
    if true_poses is not None and len(true_poses) != len(raw_steps) + 1:
        jf.fail("robot.true_poses", f"expected {len(raw_steps) + 1} poses (x_0 and one per step), "
                                  f"got {len(true_poses)}")
    max_range, fov, clutter, detection_probability = jf.get(top, "sensor", "", _sensor)
    discovery = jf.maybe(top, "discovery", "", _discovery, N)
    true_objects = jf.maybe(top, "true_objects", "", jf.as_list)
    if true_objects is not None:
        true_objects = tuple(_true_object(t, f"true_objects[{i}]", M)
                             for i, t in enumerate(true_objects))
    num_truth = N if discovery is None else len(true_objects or ())
    return Scenario(
        num_classes=M,
        object_prior_means=np.array([jf.get(o, "prior_mean", p, jf.vector, 3)
                                     for o, p in zip(objects, paths)]).reshape(N, 3),
        object_prior_covs=np.array([jf.get(o, "prior_cov", p, jf.spd, 3)
                                    for o, p in zip(objects, paths)]).reshape(N, 3, 3),
        class_prior=jf.distributions(class_prior, "class_prior", axis=1),
        robot_prior_mean=jf.get(robot, "prior_mean", "robot", jf.vector, 3),
        robot_prior_cov=jf.get(robot, "prior_cov", "robot", jf.spd, 3),
        motion_cov=jf.get(top, "motion_cov", "", jf.spd, 3),
        geometric_cov=jf.get(top, "geometric_cov", "", jf.spd, 2),
        classifier=jf.get(top, "classifier", "", _classifier, M),
        max_range=max_range,
        fov=fov,
        clutter_log_density=clutter,
        detection_probability=detection_probability,
        steps=tuple(_step(s, f"steps[{k}]", M, num_truth) for k, s in enumerate(raw_steps)),
        true_object_poses=_all_or_none([jf.maybe(o, "true_pose", p, jf.vector, 3)
                                        for o, p in zip(objects, paths)]),
        true_classes=_all_or_none([jf.maybe(o, "true_class", p, jf.integer, 0, M)
                                   for o, p in zip(objects, paths)]),
        true_robot_poses=true_poses,
        discovery=discovery,
        true_objects=true_objects,
        metadata={k: copy.deepcopy(v) for k, v in top.items() if k not in _TOP_KEYS},
    )


# --------------------------------------------------------------------------- #
# Writing
# --------------------------------------------------------------------------- #


def _classifier_json(c: Classifier) -> dict:
    out: dict[str, Any] = {"model": c.model}
    if c.alpha is not None:
        out["alpha"] = float(c.alpha)
    if c.K is not None:
        out["K"] = float(c.K)
    if c.matrix is not None:
        out["matrix"] = jf.floats(c.matrix)
    if c.path is not None:
        out["path"] = c.path
    return out


def _detection_json(d: Detection) -> dict:
    out = {"range": float(d.range), "bearing": float(d.bearing), "scores": jf.floats(d.scores)}
    if d.true_object is not None:
        out["true_object"] = int(d.true_object)
    return out


def _object_json(s: Scenario, n: int) -> dict:
    out = {"prior_mean": jf.floats(s.object_prior_means[n]),
           "prior_cov": jf.floats(s.object_prior_covs[n])}
    if s.true_object_poses is not None:
        out["true_pose"] = jf.floats(s.true_object_poses[n])
    if s.true_classes is not None:
        out["true_class"] = int(s.true_classes[n])
    return out


def scenario_to_json(s: Scenario) -> dict:
    """The JSON object for `s` (inverse of `parse_scenario`), metadata keys included."""
    robot = {"prior_mean": jf.floats(s.robot_prior_mean), "prior_cov": jf.floats(s.robot_prior_cov)}
    if s.true_robot_poses is not None:
        robot["true_poses"] = jf.floats(s.true_robot_poses)
    out: dict[str, Any] = {"format": SCENARIO_FORMAT}
    out.update({k: copy.deepcopy(v) for k, v in s.metadata.items() if k not in _TOP_KEYS})
    out.update(
        num_classes=int(s.num_classes),
        objects=[_object_json(s, n) for n in range(s.num_objects)],
        class_prior=jf.floats(s.class_prior),
        robot=robot,
        motion_cov=jf.floats(s.motion_cov),
        geometric_cov=jf.floats(s.geometric_cov),
        classifier=_classifier_json(s.classifier),
        sensor={"max_range": float(s.max_range), "fov": float(s.fov),
                **({} if s.clutter_log_density is None else {"clutter_log_density": float(s.clutter_log_density)}),
                **({} if s.detection_probability is None
                   else {"detection_probability": float(s.detection_probability)})},
        steps=[{"odometry": jf.floats(st.odometry),
                "detections": [_detection_json(d) for d in st.detections]} for st in s.steps],
    )
    if s.discovery is not None:
        out["discovery"] = {
            "max_objects": int(s.discovery.max_objects),
            "new_object_log_density": float(s.discovery.new_object_log_density),
            "new_object_orientation_var": float(s.discovery.new_object_orientation_var),
        }
    if s.true_objects is not None:
        out["true_objects"] = [{"pose": jf.floats(p), "class": int(c)} for p, c in s.true_objects]
    return out


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read and validate a scenario file.

    A relative ``classifier.path`` is resolved against the file's directory (and kept absolute, so
    the scenario can be saved anywhere).
    """
    s = parse_scenario(jf.read_json(path))
    file = s.classifier.path
    if file is not None and not os.path.isabs(file):
        file = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(path)), file))
        s = s.replace(classifier=dataclasses.replace(s.classifier, path=file))
    return s


def save_scenario(s: Scenario, path: str | os.PathLike) -> None:
    """Validate `s` and write it as a scenario file (floats written exactly)."""
    obj = scenario_to_json(s)
    parse_scenario(obj)
    jf.write_json(obj, path)


def stack_steps(s: Scenario, max_detections: int | None = None) -> StackedSteps:
    """Pad the steps to `max_detections` (default: the most in any step, at least 1)."""
    D = max(1, s.max_detections) if max_detections is None else int(max_detections)
    T, M = s.num_steps, s.num_classes
    odometry = np.zeros((T, 3))
    geo, scores = np.zeros((T, D, 2)), np.zeros((T, D, M))
    mask, true_object = np.zeros((T, D), bool), np.full((T, D), -1, dtype=np.int64)
    for k, step in enumerate(s.steps):
        if len(step.detections) > D:
            jf.fail(f"steps[{k}].detections",
                  f"{len(step.detections)} detections, more than max_detections = {D}")
        odometry[k] = step.odometry
        for d, det in enumerate(step.detections):
            geo[k, d] = (det.range, det.bearing)
            scores[k, d] = det.scores
            mask[k, d] = True
            true_object[k, d] = -1 if det.true_object is None else det.true_object
    return StackedSteps(odometry, geo, scores, mask, true_object)
