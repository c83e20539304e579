"""Scenario files (`hybridslam-scenario/1`): load, validate, save, and stack for JAX.

The file layout is the contract in SCENARIO_FORMAT.md; this module keeps to it
exactly. Every malformed input raises `ScenarioError` whose message is one line,
`<field path>: <what is wrong>`, e.g. ``steps[3].detections[1].scores: expected 2
numbers, got 3``. Paths use the JSON layout (0-based list indices), so
``steps[0]`` is step k = 1.

Pure numpy + stdlib json; no JAX here. `stack_steps` pads the steps into dense
arrays that the estimators feed to JAX.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import numbers
import os
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple, NoReturn

import numpy as np

SCENARIO_FORMAT = "hybridslam-scenario/1"
MODELS = ("confusion", "independent", "learned", "mirror", "none")
_SYM_TOL = 1e-9  # relative to the largest absolute entry
_PROB_TOL = 1e-6
_TOP_KEYS = frozenset(
    "format num_classes objects class_prior robot motion_cov geometric_cov "
    "classifier sensor steps discovery true_objects".split()
)


class ScenarioError(ValueError):
    """Malformed scenario/result file. str(e) is one line: '<field path>: <what is wrong>'."""

    def __init__(self, path: str, message: str):
        super().__init__(path, message)
        self.path = path
        self.message = message

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


# --------------------------------------------------------------------------- #
# Equality for dataclasses holding arrays (the generated __eq__ would raise).
# --------------------------------------------------------------------------- #


def _equal(a: Any, b: Any) -> bool:
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(
            _equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.shape(a) == np.shape(b) and bool(np.array_equal(a, b))
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(map(_equal, a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    return bool(a == b)


def _eq(self: Any, other: Any) -> bool:
    return _equal(self, other) if type(other) is type(self) else NotImplemented


# --------------------------------------------------------------------------- #
# Data types
# --------------------------------------------------------------------------- #


@dataclass(frozen=True, eq=False)
class Detection:
    """One detection: geometric part [range, bearing] and classifier scores (M,)."""

    range: float
    bearing: float
    scores: np.ndarray
    true_object: int | None = None
    __eq__ = _eq


@dataclass(frozen=True, eq=False)
class Step:
    """Odometry u_k (3,) and the detections Z_k taken at x_k."""

    odometry: np.ndarray
    detections: tuple[Detection, ...]
    __eq__ = _eq


@dataclass(frozen=True, eq=False)
class Classifier:
    """Semantic likelihood model; see "Classifier models" in SCENARIO_FORMAT.md."""

    model: str  # one of MODELS
    alpha: float | None = None  # mirror, independent
    K: float | None = None  # mirror, independent
    matrix: np.ndarray | None = None  # confusion: (M, M), matrix[label, class]
    path: str | None = None  # learned: model file; load_scenario makes it absolute
    __eq__ = _eq


@dataclass(frozen=True, eq=False)
class Discovery:
    """The optional "discovery" section (unknown maps)."""

    max_objects: int
    new_object_log_density: float
    new_object_orientation_var: float
    __eq__ = _eq


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
    metadata: dict = field(default_factory=dict)  # unknown top-level keys, verbatim
    __eq__ = _eq

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


# --------------------------------------------------------------------------- #
# Validation helpers: every check below is built from these.
# --------------------------------------------------------------------------- #


def _fail(path: str, message: str) -> NoReturn:
    raise ScenarioError(path, message)


def _kind(obj: Any) -> str:
    """The JSON name of a value's type, for messages."""
    if obj is None:
        return "null"
    if isinstance(obj, (bool, np.bool_)):
        return "boolean"
    if isinstance(obj, numbers.Number):
        return "number"
    if isinstance(obj, str):
        return "string"
    if isinstance(obj, (list, tuple, np.ndarray)):
        return "list"
    return "object" if isinstance(obj, dict) else type(obj).__name__


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _get(obj: dict, key: str, path: str, parse: Callable[..., Any], *args: Any) -> Any:
    """Parse the required key `key` of the object at `path`."""
    if key not in obj:
        _fail(_join(path, key), "missing")
    return parse(obj[key], _join(path, key), *args)


def _maybe(obj: dict, key: str, path: str, parse: Callable[..., Any], *args: Any) -> Any:
    """Parse an optional key; absent or null gives None."""
    value = obj.get(key)
    return None if value is None else parse(value, _join(path, key), *args)


def _object(obj: Any, path: str) -> dict:
    if not isinstance(obj, dict):
        _fail(path, f"expected an object, got {_kind(obj)}")
    return obj


def _list(obj: Any, path: str) -> list:
    if isinstance(obj, np.ndarray):
        obj = obj.tolist()
    if not isinstance(obj, (list, tuple)):
        _fail(path, f"expected a list, got {_kind(obj)}")
    return list(obj)


def _string(obj: Any, path: str) -> str:
    if not isinstance(obj, str):
        _fail(path, f"expected a string, got {_kind(obj)}")
    return obj


def _number(obj: Any, path: str) -> float:
    if isinstance(obj, (bool, np.bool_)) or not isinstance(obj, numbers.Real):
        _fail(path, f"expected a number, got {_kind(obj)}")
    try:
        value = float(obj)
    except OverflowError:
        value = math.inf
    if not math.isfinite(value):
        _fail(path, "not a finite number")
    return value


def _positive(obj: Any, path: str) -> float:
    value = _number(obj, path)
    if value <= 0:
        _fail(path, f"expected a positive number, got {value!r}")
    return value


def _integer(obj: Any, path: str, lo: int | None = None, hi: int | None = None) -> int:
    """An integer in [lo, hi) (either bound may be None)."""
    if isinstance(obj, (bool, np.bool_)) or not isinstance(obj, numbers.Integral):
        got = repr(obj) if isinstance(obj, float) else _kind(obj)
        _fail(path, f"expected an integer, got {got}")
    value = int(obj)
    if (lo is not None and value < lo) or (hi is not None and value >= hi):
        want = f">= {lo}" if hi is None else f"in [{lo}, {hi})"
        _fail(path, f"expected an integer {want}, got {value}")
    return value


def _integers(obj: Any, path: str, lo: int | None = None) -> list[int]:
    return [_integer(x, f"{path}[{i}]", lo) for i, x in enumerate(_list(obj, path))]


def _vector(obj: Any, path: str, n: int | None = None) -> np.ndarray:
    items = _list(obj, path)
    if n is not None and len(items) != n:
        _fail(path, f"expected {n} numbers, got {len(items)}")
    return np.array([_number(x, f"{path}[{i}]") for i, x in enumerate(items)], dtype=np.float64)


def _matrix(obj: Any, path: str, rows: int | None, cols: int) -> np.ndarray:
    """A list of rows; `rows=None` accepts any number of rows."""
    items = _list(obj, path)
    lens = {len(_list(r, f"{path}[{i}]")) for i, r in enumerate(items)}
    if rows is not None and len(lens) <= 1 and (len(items) != rows or lens - {cols}):
        _fail(path, f"expected a {rows}x{cols} matrix, got {len(items)}x{min(lens, default=0)}")
    data = [_vector(r, f"{path}[{i}]", cols) for i, r in enumerate(items)]
    return np.array(data, dtype=np.float64).reshape(len(items), cols)


def _symmetric(obj: Any, path: str, n: int) -> np.ndarray:
    m = _matrix(obj, path, n, n)
    if np.abs(m - m.T).max(initial=0.0) > _SYM_TOL * np.abs(m).max(initial=0.0):
        _fail(path, "not symmetric")
    return m


def _spd(obj: Any, path: str, n: int) -> np.ndarray:
    m = _symmetric(obj, path, n)
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        _fail(path, "not positive definite")
    return m


def _distributions(m: np.ndarray, path: str, axis: int) -> np.ndarray:
    """Check each row (axis=1) or column (axis=0) of m is a probability vector."""
    for i, j in np.argwhere(m < 0)[:1]:
        _fail(f"{path}[{i}][{j}]", f"negative probability {float(m[i, j])!r}")
    for i, total in enumerate(m.sum(axis=axis)):
        if abs(total - 1.0) > _PROB_TOL:
            if axis == 1:
                _fail(f"{path}[{i}]", f"sums to {total:.9g}, expected 1")
            _fail(path, f"column {i} sums to {total:.9g}, expected 1")
    return m


# --------------------------------------------------------------------------- #
# Sections
# --------------------------------------------------------------------------- #


def _format(obj: dict, expected: str) -> None:
    fmt = _get(obj, "format", "", _string)
    if fmt != expected:
        _fail("format", f"expected {expected!r}, got {fmt!r}")


def _classifier(obj: Any, path: str, num_classes: int) -> Classifier:
    obj = _object(obj, path)
    model = _get(obj, "model", path, _string)
    if model not in MODELS:
        _fail(_join(path, "model"), f"unknown model {model!r} (known: {', '.join(MODELS)})")
    if model in ("mirror", "independent"):
        if num_classes != 2:
            _fail(_join(path, "model"), f"{model!r} needs num_classes == 2, got {num_classes}")
        alpha = _get(obj, "alpha", path, _number)
        return Classifier(model, alpha=alpha, K=_get(obj, "K", path, _positive))
    if model == "confusion":
        matrix = _get(obj, "matrix", path, _matrix, num_classes, num_classes)
        return Classifier(model, matrix=_distributions(matrix, _join(path, "matrix"), axis=0))
    if model == "learned":
        file = _get(obj, "path", path, _string)
        if not file.strip():
            _fail(_join(path, "path"), "empty path")
        return Classifier(model, path=file)
    return Classifier(model)


def _sensor(obj: Any, path: str) -> tuple[float, float]:
    obj = _object(obj, path)
    max_range = _get(obj, "max_range", path, _positive)
    fov = _get(obj, "fov", path, _number)
    if not 0.0 < fov <= 2.0 * math.pi:
        _fail(_join(path, "fov"), f"expected a number in (0, 2*pi], got {fov!r}")
    return max_range, fov


def _discovery(obj: Any, path: str, num_objects: int) -> Discovery:
    obj = _object(obj, path)
    return Discovery(
        max_objects=_get(obj, "max_objects", path, _integer, num_objects),
        new_object_log_density=_get(obj, "new_object_log_density", path, _number),
        new_object_orientation_var=_get(obj, "new_object_orientation_var", path, _positive),
    )


def _true_object(obj: Any, path: str, num_classes: int) -> tuple[np.ndarray, int]:
    obj = _object(obj, path)
    return _get(obj, "pose", path, _vector, 3), _get(obj, "class", path, _integer, 0, num_classes)


def _detection(obj: Any, path: str, num_classes: int, num_truth: int) -> Detection:
    obj = _object(obj, path)
    rng = _get(obj, "range", path, _number)
    if rng < 0:
        _fail(_join(path, "range"), f"expected a non-negative number, got {rng!r}")
    return Detection(
        range=rng,
        bearing=_get(obj, "bearing", path, _number),
        scores=_get(obj, "scores", path, _vector, num_classes),
        true_object=_maybe(obj, "true_object", path, _integer, 0, num_truth),
    )


def _step(obj: Any, path: str, num_classes: int, num_truth: int) -> Step:
    obj = _object(obj, path)
    odometry = _get(obj, "odometry", path, _vector, 3)
    dets = _get(obj, "detections", path, _list)
    path = _join(path, "detections")
    return Step(
        odometry,
        tuple(_detection(d, f"{path}[{i}]", num_classes, num_truth) for i, d in enumerate(dets)),
    )


def _all_or_none(values: list[Any]) -> np.ndarray | None:
    return np.array(values) if values and all(v is not None for v in values) else None


def parse_scenario(obj: Any) -> Scenario:
    """Validate a decoded JSON object and return the Scenario it describes."""
    top = _object(obj, "<root>")
    _format(top, SCENARIO_FORMAT)
    M = _get(top, "num_classes", "", _integer, 1)
    objects = [_object(o, f"objects[{i}]") for i, o in enumerate(_get(top, "objects", "", _list))]
    N = len(objects)
    paths = [f"objects[{i}]" for i in range(N)]
    class_prior = _maybe(top, "class_prior", "", _matrix, N, M)
    class_prior = np.full((N, M), 1.0 / M) if class_prior is None else class_prior
    robot = _get(top, "robot", "", _object)
    raw_steps = _get(top, "steps", "", _list)
    true_poses = _maybe(robot, "true_poses", "robot", _matrix, None, 3)
    if true_poses is not None and len(true_poses) != len(raw_steps) + 1:
        _fail("robot.true_poses", f"expected {len(raw_steps) + 1} poses (x_0 and one per step), "
                                  f"got {len(true_poses)}")
    max_range, fov = _get(top, "sensor", "", _sensor)
    discovery = _maybe(top, "discovery", "", _discovery, N)
    true_objects = _maybe(top, "true_objects", "", _list)
    if true_objects is not None:
        true_objects = tuple(_true_object(t, f"true_objects[{i}]", M)
                             for i, t in enumerate(true_objects))
    num_truth = N if discovery is None else len(true_objects or ())
    return Scenario(
        num_classes=M,
        object_prior_means=np.array([_get(o, "prior_mean", p, _vector, 3)
                                     for o, p in zip(objects, paths)]).reshape(N, 3),
        object_prior_covs=np.array([_get(o, "prior_cov", p, _spd, 3)
                                    for o, p in zip(objects, paths)]).reshape(N, 3, 3),
        class_prior=_distributions(class_prior, "class_prior", axis=1),
        robot_prior_mean=_get(robot, "prior_mean", "robot", _vector, 3),
        robot_prior_cov=_get(robot, "prior_cov", "robot", _spd, 3),
        motion_cov=_get(top, "motion_cov", "", _spd, 3),
        geometric_cov=_get(top, "geometric_cov", "", _spd, 2),
        classifier=_get(top, "classifier", "", _classifier, M),
        max_range=max_range,
        fov=fov,
        steps=tuple(_step(s, f"steps[{k}]", M, num_truth) for k, s in enumerate(raw_steps)),
        true_object_poses=_all_or_none([_maybe(o, "true_pose", p, _vector, 3)
                                        for o, p in zip(objects, paths)]),
        true_classes=_all_or_none([_maybe(o, "true_class", p, _integer, 0, M)
                                   for o, p in zip(objects, paths)]),
        true_robot_poses=true_poses,
        discovery=discovery,
        true_objects=true_objects,
        metadata={k: copy.deepcopy(v) for k, v in top.items() if k not in _TOP_KEYS},
    )


# --------------------------------------------------------------------------- #
# Writing
# --------------------------------------------------------------------------- #


def _floats(a: Any) -> Any:
    return np.asarray(a, dtype=np.float64).tolist()


def _classifier_json(c: Classifier) -> dict:
    out: dict[str, Any] = {"model": c.model}
    if c.alpha is not None:
        out["alpha"] = float(c.alpha)
    if c.K is not None:
        out["K"] = float(c.K)
    if c.matrix is not None:
        out["matrix"] = _floats(c.matrix)
    if c.path is not None:
        out["path"] = c.path
    return out


def _detection_json(d: Detection) -> dict:
    out = {"range": float(d.range), "bearing": float(d.bearing), "scores": _floats(d.scores)}
    if d.true_object is not None:
        out["true_object"] = int(d.true_object)
    return out


def _object_json(s: Scenario, n: int) -> dict:
    out = {"prior_mean": _floats(s.object_prior_means[n]),
           "prior_cov": _floats(s.object_prior_covs[n])}
    if s.true_object_poses is not None:
        out["true_pose"] = _floats(s.true_object_poses[n])
    if s.true_classes is not None:
        out["true_class"] = int(s.true_classes[n])
    return out


def scenario_to_json(s: Scenario) -> dict:
    """The JSON object for `s` (inverse of `parse_scenario`), metadata keys included."""
    robot = {"prior_mean": _floats(s.robot_prior_mean), "prior_cov": _floats(s.robot_prior_cov)}
    if s.true_robot_poses is not None:
        robot["true_poses"] = _floats(s.true_robot_poses)
    out: dict[str, Any] = {"format": SCENARIO_FORMAT}
    out.update({k: copy.deepcopy(v) for k, v in s.metadata.items() if k not in _TOP_KEYS})
    out.update(
        num_classes=int(s.num_classes),
        objects=[_object_json(s, n) for n in range(s.num_objects)],
        class_prior=_floats(s.class_prior),
        robot=robot,
        motion_cov=_floats(s.motion_cov),
        geometric_cov=_floats(s.geometric_cov),
        classifier=_classifier_json(s.classifier),
        sensor={"max_range": float(s.max_range), "fov": float(s.fov)},
        steps=[{"odometry": _floats(st.odometry),
                "detections": [_detection_json(d) for d in st.detections]} for st in s.steps],
    )
    if s.discovery is not None:
        out["discovery"] = {
            "max_objects": int(s.discovery.max_objects),
            "new_object_log_density": float(s.discovery.new_object_log_density),
            "new_object_orientation_var": float(s.discovery.new_object_orientation_var),
        }
    if s.true_objects is not None:
        out["true_objects"] = [{"pose": _floats(p), "class": int(c)} for p, c in s.true_objects]
    return out


def _dumps(obj: Any, indent: int = 0, width: int = 100) -> str:
    """JSON text; objects and lists of lists/objects are spread over lines when long."""
    text = json.dumps(obj, allow_nan=False)
    nested = isinstance(obj, dict) or (
        isinstance(obj, list) and any(isinstance(x, (dict, list)) for x in obj))
    if not nested or len(text) + indent <= width:
        return text
    pad, inner = " " * indent, " " * (indent + 1)
    if isinstance(obj, dict):
        lines = [f"{inner}{json.dumps(k)}: {_dumps(v, indent + 1, width)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(lines) + "\n" + pad + "}"
    lines = [inner + _dumps(x, indent + 1, width) for x in obj]
    return "[\n" + ",\n".join(lines) + "\n" + pad + "]"


def _write_json(obj: Any, path: str | os.PathLike) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(_dumps(obj) + "\n")


def _read_json(path: str | os.PathLike) -> Any:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except OSError as e:
        _fail("<file>", f"cannot read {os.fspath(path)!r}: {e.strerror or e}")
    except json.JSONDecodeError as e:
        _fail("<file>", f"{os.fspath(path)!r} is not valid JSON: {e}")
    except UnicodeDecodeError as e:
        _fail("<file>", f"{os.fspath(path)!r} is not UTF-8 text: {e.reason}")


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read and validate a scenario file.

    A relative ``classifier.path`` is resolved against the file's directory (and kept absolute, so
    the scenario can be saved anywhere).
    """
    s = parse_scenario(_read_json(path))
    file = s.classifier.path
    if file is not None and not os.path.isabs(file):
        file = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(path)), file))
        s = s.replace(classifier=dataclasses.replace(s.classifier, path=file))
    return s


def save_scenario(s: Scenario, path: str | os.PathLike) -> None:
    """Validate `s` and write it as a scenario file (floats written exactly)."""
    obj = scenario_to_json(s)
    parse_scenario(obj)
    _write_json(obj, path)


def stack_steps(s: Scenario, max_detections: int | None = None) -> StackedSteps:
    """Pad the steps to `max_detections` (default: the most in any step, at least 1)."""
    D = max(1, s.max_detections) if max_detections is None else int(max_detections)
    T, M = s.num_steps, s.num_classes
    odometry = np.zeros((T, 3))
    geo, scores = np.zeros((T, D, 2)), np.zeros((T, D, M))
    mask, true_object = np.zeros((T, D), bool), np.full((T, D), -1, dtype=np.int64)
    for k, step in enumerate(s.steps):
        if len(step.detections) > D:
            _fail(f"steps[{k}].detections",
                  f"{len(step.detections)} detections, more than max_detections = {D}")
        odometry[k] = step.odometry
        for d, det in enumerate(step.detections):
            geo[k, d] = (det.range, det.bearing)
            scores[k, d] = det.scores
            mask[k, d] = True
            true_object[k, d] = -1 if det.true_object is None else det.true_object
    return StackedSteps(odometry, geo, scores, mask, true_object)
