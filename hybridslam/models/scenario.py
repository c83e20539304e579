"""The domain types: a scenario (prior map and robot, noise, classifier model, the steps'
odometry and detections, optional ground truth) and its steps stacked into fixed-shape arrays.

What every layer reads; the file format that holds them (``hybridslam-scenario/1``: parsing with
field-path errors, writing) is :mod:`hybridslam.io.scenario`. Pure numpy and the standard library.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

MODELS = ("confusion", "independent", "learned", "mirror", "none")  # the classifier models a file may name


def equal(a: Any, b: Any) -> bool:
    """Value equality of dataclasses, arrays, sequences and dicts, nested (arrays by shape and
    elements)."""
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(
            equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a) if f.compare
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.shape(a) == np.shape(b) and bool(np.array_equal(a, b))
    if isinstance(a, Sequence) and not isinstance(a, str):  # lists, tuples, a result's lazy histories
        if not (isinstance(b, Sequence) and not isinstance(b, str) and len(a) == len(b)):
            return False
        try:
            if a == b:  # lists of numbers (a result's T² association lists) at C speed
                return True
        except (TypeError, ValueError):  # arrays inside: compared one by one below
            pass
        return all(map(equal, a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)
    return bool(a == b)


def dataclass_eq(self: Any, other: Any) -> bool:
    """``__eq__`` of the frozen dataclasses here and in :mod:`hybridslam.io.result`: :func:`equal`."""
    return equal(self, other) if type(other) is type(self) else NotImplemented


@dataclass(frozen=True, eq=False)
class Detection:
    """One detection: geometric part [range, bearing] and classifier scores (M,)."""

    range: float
    bearing: float
    scores: np.ndarray
    true_object: int | None = None
    __eq__ = dataclass_eq


@dataclass(frozen=True, eq=False)
class Step:
    """Odometry u_k (3,) and the detections Z_k taken at x_k."""

    odometry: np.ndarray
    detections: tuple[Detection, ...]
    __eq__ = dataclass_eq


@dataclass(frozen=True, eq=False)
class Classifier:
    """Semantic likelihood model; see "Classifier models" in docs/file_format.md."""

    model: str  # one of MODELS
    alpha: float | None = None  # mirror, independent
    K: float | None = None  # mirror, independent
    matrix: np.ndarray | None = None  # confusion: (M, M), matrix[label, class]
    path: str | None = None  # learned: model file; load_scenario makes it absolute
    __eq__ = dataclass_eq


@dataclass(frozen=True, eq=False)
class Discovery:
    """The optional "discovery" section (unknown maps)."""

    max_objects: int
    new_object_log_density: float
    new_object_orientation_var: float
    __eq__ = dataclass_eq


@dataclass(frozen=True, eq=False)
class Scenario:
    """A parsed scenario file. N objects, M classes, T steps."""

    num_classes: int
    object_prior_means: np.ndarray  # (N, 3)
    object_prior_covs: np.ndarray  # (N, 3, 3)
    class_prior: np.ndarray  # (N, M)
    robot_prior_mean: np.ndarray  # (3,)
    robot_prior_cov: np.ndarray  # (3, 3)
    motion_cov: np.ndarray  # (3, 3)
    geometric_cov: np.ndarray  # (2, 2)
    classifier: Classifier
    max_range: float
    fov: float
    steps: tuple[Step, ...]
    true_object_poses: np.ndarray | None = None  # (N, 3) if every object has true_pose
    true_classes: np.ndarray | None = None  # (N,) int if every object has true_class
    true_robot_poses: np.ndarray | None = None  # (T + 1, 3)
    discovery: Discovery | None = None
    true_objects: tuple[tuple[np.ndarray, int], ...] | None = None  # (pose (3,), class)
    clutter_log_density: float | None = None  # sensor.clutter_log_density: a detection may be spurious
    detection_probability: float | None = None  # sensor.detection_probability: P(detected | in view)
    metadata: dict = field(default_factory=dict)  # unknown top-level keys, verbatim
    __eq__ = dataclass_eq

    @property
    def num_objects(self) -> int:
        return int(np.shape(self.object_prior_means)[0])

    @property
    def num_steps(self) -> int:
        return len(self.steps)

    @property
    def max_detections(self) -> int:
        return max((len(s.detections) for s in self.steps), default=0)

    def replace(self, **changes: Any) -> Scenario:
        return dataclasses.replace(self, **changes)


class StackedSteps(NamedTuple):
    """The steps padded to D detections each (T steps, M classes)."""

    odometry: np.ndarray  # (T, 3)
    geo: np.ndarray  # (T, D, 2) [range, bearing]; padded rows 0
    scores: np.ndarray  # (T, D, M); padded rows 0
    mask: np.ndarray  # (T, D) bool
    true_object: np.ndarray  # (T, D) int, -1 where unknown or padded
