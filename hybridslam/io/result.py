"""Result files (``hybridslam-result/2``, and ``/1``): the belief an estimator records after every step.

Layout: "The result file" in docs/file_format.md. Format 2 stores each component's association
history as a link to its parent (the previous step's component whose history it extends) and that
step's own associations, and the last step's histories whole: a file linear in the run. Format 1,
each step listing every whole history (T² lists: a 1700-step log's file was 300 MB), is still
read, and written on request (``version=1``). In memory every component's ``associations`` is its
whole history, a plain list or a :class:`History` chain that reads the same.

Malformed input raises ``hybridslam.scenario.ScenarioError`` with the field path, e.g.
``steps[2].components[0].weight: expected a number in (0, 1], got 1.5``.
Pure numpy + stdlib json, built from the validation helpers of :mod:`.jsonfields`.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import operator
import os
import secrets
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, overload

import numpy as np

from ..models.scenario import dataclass_eq
from . import jsonfields as jf

RESULT_FORMATS = {1: "hybridslam-result/1", 2: "hybridslam-result/2"}
RESULT_FORMAT = RESULT_FORMATS[2]  # what the writers write unless asked for format 1
VERSIONS = tuple(RESULT_FORMATS)


class History(Sequence[list[int]]):
    """A component's association history after step ``k``: its parent's history (after step
    ``k - 1``, a :class:`History` or a plain list) and step ``k``'s own list.

    Reads like the list ``[associations of step 1, ..., of step k]``: ``len``, iteration (O(k)),
    ``h[-1]`` (this step's list, O(1)), ``h[j]`` (O(k - j)), slices (O(k)), ``==`` with any sequence
    of lists. The components of a whole run share their parents' links, so their histories take
    memory linear in the run instead of T² lists.
    """

    __slots__ = ("parent", "last", "_len")

    def __init__(self, parent: Sequence[Sequence[int]], last: list[int]):
        self.parent = parent
        self.last = last
        self._len = len(parent) + 1

    def __len__(self) -> int:
        return self._len

    def _links(self) -> tuple[Sequence[Sequence[int]], list[list[int]]]:
        """The first plain sequence down the chain and the lists of the links after it, oldest first."""
        node: Sequence[Sequence[int]] = self
        tail = []
        while isinstance(node, History):
            tail.append(node.last)
            node = node.parent
        tail.reverse()
        return node, tail

    def __iter__(self) -> Iterator[list[int]]:
        base, tail = self._links()
        yield from base  # type: ignore[misc]
        yield from tail

    @overload
    def __getitem__(self, index: int) -> list[int]: ...

    @overload
    def __getitem__(self, index: slice) -> list[list[int]]: ...

    def __getitem__(self, index: int | slice) -> list[int] | list[list[int]]:
        if isinstance(index, slice):
            return list(self)[index]
        i = operator.index(index)
        i = i + self._len if i < 0 else i
        if not 0 <= i < self._len:
            raise IndexError(f"history index {index} out of range for {self._len} steps")
        node: Sequence[Sequence[int]] = self
        while isinstance(node, History):
            if i == node._len - 1:
                return node.last
            node = node.parent
        return list(node[i])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, str):
            return NotImplemented
        return len(other) == self._len and all(list(a) == list(b) for a, b in zip(self, other))

    __hash__ = None  # type: ignore[assignment]  # mutable-looking, like the list it stands for

    def __repr__(self) -> str:
        return f"History({list(self)!r})"


@dataclass(eq=False)
class ComponentRecord:
    """One belief component after step k."""

    weight: float | np.floating  # numpy scalars are written as floats
    # per step j, object of each detection of step j+1: a list, or a History chain (format 2)
    associations: Sequence[Sequence[int] | np.ndarray]
    classes: Sequence[int | np.integer]  # per object, -1 = open
    pose_mean: np.ndarray  # (3,) mean of x_k
    pose_cov: np.ndarray  # (3, 3) covariance of x_k
    # index in the previous step's components of the one whose history this one extends (format 2
    # files; None: unknown or none). Layout, not content: records that differ only here are equal.
    parent: int | None = dataclasses.field(default=None, compare=False)
    __eq__ = dataclass_eq


@dataclass(eq=False)
class StepRecord:
    """The belief after step k: components sorted by weight (highest first) and metrics."""

    k: int
    components: list[ComponentRecord]
    metrics: dict[str, float]  # entropy, det_cov, num_components; optional err_wmax, err_wavg
    __eq__ = dataclass_eq


@dataclass(eq=False)
class Result:
    """A result file: the estimator's description and one StepRecord per step."""

    estimator: str
    steps: list[StepRecord]
    timing: dict | None = None  # {"compile_s": float, "step_s": [float] * T}
    trajectory: np.ndarray | None = None  # (T+1, 3) smoothed x_0..x_T of the final best component (smoothers)
    objects: np.ndarray | None = None  # (N, 3) final object estimates of that component, indexed like classes
    __eq__ = dataclass_eq


# --------------------------------------------------------------------------- #
# Reading
# --------------------------------------------------------------------------- #

WEIGHT_TIE = 1e-9
"""Relative slack of the weight order: components whose weights agree to this are tied and may
stand in either order (docs/file_format.md)."""


def _weight(obj: Any, path: str) -> float:
    w = jf.number(obj, path)
    if not 0.0 < w <= 1.0 + jf.PROB_TOL:
        jf.fail(path, f"expected a number in (0, 1], got {w!r}")
    return w


def _whole(obj: Any, path: str, k: int) -> list[list[int]]:
    """A whole history: ``k`` lists of object indices (-1: left unassociated, clutter / outlier)."""
    assoc = jf.as_list(obj, path)
    if len(assoc) != k:
        jf.fail(path, f"expected {k} lists (one per step so far), got {len(assoc)}")
    return jf.integer_lists(assoc, path, -1)


def _parent(obj: Any, path: str, previous: StepRecord | None) -> int:
    if previous is None:
        jf.fail(path, "step 1 has no previous step")
    return jf.integer(obj, path, 0, len(previous.components))


def _history(obj: dict, path: str, k: int, version: int, previous: StepRecord | None,
             last: bool) -> tuple[Sequence[Sequence[int]], int | None]:
    """The component's whole history and its parent's index (format 2; None in format 1)."""
    if version == 1:
        return jf.get(obj, "associations", path, _whole, k), None
    parent = jf.maybe(obj, "parent", path, _parent, previous)
    whole, own = obj.get("associations"), obj.get("step_associations")
    if whole is not None and own is not None:
        jf.fail(f"{path}.step_associations", "given with associations (expected one of the two)")
    if whole is not None:
        history = _whole(whole, f"{path}.associations", k)
        if parent is not None and previous is not None:
            before = previous.components[parent].associations
            if history[:-1] != [list(a) for a in before]:
                jf.fail(f"{path}.associations", f"its first {k - 1} lists are not the history of its parent, "
                                                f"steps[{k - 2}].components[{parent}]")
        return history, parent
    if last:
        jf.fail(f"{path}.associations", "missing (the last step lists every component's whole history)")
    if own is None:
        jf.fail(f"{path}.associations", "missing (or step_associations with parent)")
    if parent is None or previous is None:
        jf.fail(f"{path}.parent", "missing (step_associations extends the parent's history)")
    step = jf.integers(own, f"{path}.step_associations", -1)
    return History(previous.components[parent].associations, step), parent


def _poses(raw: list) -> tuple[np.ndarray, np.ndarray] | None:
    """Every component's ``pose_mean`` (K, 3) and ``pose_cov`` (K, 3, 3), checked at once where all
    are lists of finite numbers and the covariances symmetric (a long file's 16 components of 1700
    steps, one by one, took most of its loading); None: to be read one by one (naming the fault)."""
    try:
        means, covs = [c["pose_mean"] for c in raw], [c["pose_cov"] for c in raw]
    except (TypeError, KeyError, IndexError):
        return None
    if not (all(type(m) is list and len(m) == 3 for m in means)
            and all(type(c) is list and len(c) == 3 for c in covs)):
        return None
    rows = list(itertools.chain.from_iterable(covs))
    numbers = itertools.chain(itertools.chain.from_iterable(means), itertools.chain.from_iterable(rows))
    if not (all(type(r) is list and len(r) == 3 for r in rows) and set(map(type, numbers)) <= {float, int}):
        return None
    try:
        mean, cov = np.array(means, dtype=np.float64), np.array(covs, dtype=np.float64)
    except OverflowError:  # an integer beyond float64
        return None
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        return None
    asymmetry = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2))
    if np.any(asymmetry > jf.SYM_TOL * np.abs(cov).max(axis=(1, 2))):
        return None
    return mean, cov


def _component(obj: Any, path: str, k: int, version: int, previous: StepRecord | None,
               last: bool, pose: tuple[np.ndarray, np.ndarray] | None = None) -> ComponentRecord:
    """``pose``: its ``pose_mean`` and ``pose_cov`` already read (:func:`_poses`)."""
    obj = jf.as_object(obj, path)
    weight = jf.get(obj, "weight", path, _weight)
    history, parent = _history(obj, path, k, version, previous, last)
    classes = jf.get(obj, "classes", path, jf.integers, -1)
    if pose is None:
        pose = jf.get(obj, "pose_mean", path, jf.vector, 3), jf.get(obj, "pose_cov", path, jf.symmetric, 3)
    return ComponentRecord(weight=weight, associations=history, classes=classes, pose_mean=pose[0],
                           pose_cov=pose[1], parent=parent)


def _metrics(obj: Any, path: str, num_components: int) -> dict[str, float]:
    obj = jf.as_object(obj, path)
    n = jf.get(obj, "num_components", path, jf.integer)
    if n != num_components:
        jf.fail(f"{path}.num_components", f"{n}, but the step has {num_components} components")
    out: dict[str, float] = {key: jf.get(obj, key, path, jf.number) for key in ("entropy", "det_cov")}
    out.update({key: jf.number(v, f"{path}.{key}") for key, v in obj.items() if key not in out})
    return out | {"num_components": n}


def _step(obj: Any, path: str, k: int, version: int = 1, previous: StepRecord | None = None,
          last: bool = False) -> StepRecord:
    """Step ``k``'s record; ``previous``: step ``k - 1``'s (format 2's parents), ``last``: the file's last step."""
    obj = jf.as_object(obj, path)
    got = jf.get(obj, "k", path, jf.integer)
    if got != k:
        jf.fail(f"{path}.k", f"expected {k} (steps in order from 1), got {got}")
    raw = jf.get(obj, "components", path, jf.as_list)
    if not raw:
        jf.fail(f"{path}.components", "empty (weights must sum to 1)")
    poses = _poses(raw)
    comps = [_component(c, f"{path}.components[{i}]", k, version, previous, last,
                        None if poses is None else (poses[0][i], poses[1][i])) for i, c in enumerate(raw)]
    weights = [float(c.weight) for c in comps]
    for i in range(1, len(weights)):
        # Tied components (weights equal to TIE_RESOLUTION, relative) are in index order
        # (hybridslam.inference.ties), so a tie's last bits may rise by a few ulps.
        if weights[i] > weights[i - 1] * (1.0 + WEIGHT_TIE):
            jf.fail(f"{path}.components[{i}].weight",
                  f"{weights[i]!r} exceeds the previous weight {weights[i - 1]!r} "
                  "(components must be sorted by weight, highest first)")
    if abs(sum(weights) - 1.0) > jf.PROB_TOL:
        jf.fail(f"{path}.components", f"weights sum to {sum(weights):.9g}, expected 1")
    return StepRecord(k, comps, jf.get(obj, "metrics", path, _metrics, len(comps)))


def _timing(obj: Any, path: str, num_steps: int) -> dict:
    obj = jf.as_object(obj, path)
    return {"compile_s": jf.get(obj, "compile_s", path, jf.number),
            "step_s": jf.get(obj, "step_s", path, jf.vector, num_steps).tolist()}


def _version(top: dict) -> int:
    fmt = jf.get(top, "format", "", jf.string)
    for version, name in RESULT_FORMATS.items():
        if fmt == name:
            return version
    jf.fail("format", f"expected {' or '.join(map(repr, RESULT_FORMATS.values()))}, got {fmt!r}")


def parse_result(obj: Any) -> Result:
    """Validate a decoded JSON object (format 1 or 2) and return the Result it describes."""
    top = jf.as_object(obj, "<root>")
    version = _version(top)
    raw = jf.get(top, "steps", "", jf.as_list)
    steps: list[StepRecord] = []
    for i, s in enumerate(raw):
        steps.append(_step(s, f"steps[{i}]", i + 1, version, steps[-1] if steps else None, i == len(raw) - 1))
    return Result(steps=steps, **_head(top, len(steps)))


def _head(top: dict, num_steps: int) -> dict[str, Any]:
    """The fields of a result file besides its steps, checked against its number of steps."""
    return {"estimator": jf.get(top, "estimator", "", jf.string),
            "timing": jf.maybe(top, "timing", "", _timing, num_steps),
            "trajectory": jf.maybe(top, "trajectory", "", jf.matrix, num_steps + 1, 3),
            "objects": jf.maybe(top, "objects", "", jf.matrix, None, 3)}


def load_result(path: str | os.PathLike) -> Result:
    """Read and validate a result file (format 1 or 2)."""
    return parse_result(jf.read_json(path))


# --------------------------------------------------------------------------- #
# Parents
# --------------------------------------------------------------------------- #


class HistoryLinker:
    """Links each step's record to the previous step's, one step after the other: each component's
    ``parent`` (the first of the previous step's components whose whole history is this one's
    without its last list; None where none is, e.g. a loop closure rewrote an earlier step) and its
    ``associations`` as a :class:`History` on that parent's.

    A history already linked to one of the previous record's (the records of a linked run, or of a
    format 2 file) keeps its link; others are matched by content (O(k) per component).
    """

    def __init__(self) -> None:
        self._k = 0
        self._histories: list[Sequence[Any]] = []  # the previous step's, by component
        self._ids: dict[int, int] = {}  # id of each of those -> its index
        self._keys: dict[tuple, int] | None = {}  # whole history as tuples -> index; None: not built

    def _previous_keys(self) -> dict[tuple, int]:
        if self._keys is None:
            self._keys = {}
            for i, h in enumerate(self._histories):
                self._keys.setdefault(tuple(map(tuple, h)), i)
        return self._keys

    def __call__(self, record: StepRecord) -> StepRecord:
        if record.k != self._k + 1:  # not the next step: nothing to link to
            self._histories, self._ids, self._keys = [], {}, {}
        keys: dict[tuple, int] | None = {}  # this step's, where every component's is computed
        components = []
        for i, c in enumerate(record.components):
            a: Any = c.associations
            parent = self._ids.get(id(a.parent)) if isinstance(a, History) else None
            if parent is not None and self._histories[parent] is a.parent:
                history, keys = a, None
            else:
                parent, history = None, a if isinstance(a, list) else list(a)
                if len(a) != record.k:  # malformed: the writer's check names it
                    keys = None
                else:
                    key = tuple(map(tuple, a))
                    if keys is not None:
                        keys.setdefault(key, i)
                    if record.k > 1 and self._histories:
                        parent = self._previous_keys().get(key[:-1])
                        if parent is not None:
                            history = History(self._histories[parent], [int(x) for x in a[-1]])
            components.append(dataclasses.replace(c, associations=history, parent=parent))
        self._k = record.k
        self._histories = [c.associations for c in components]
        self._ids = {id(h): i for i, h in enumerate(self._histories)}
        self._keys = keys
        return dataclasses.replace(record, components=components)


# --------------------------------------------------------------------------- #
# Writing
# --------------------------------------------------------------------------- #


def _component_json(c: ComponentRecord, version: int, whole: bool) -> dict:
    """``whole``: the component's whole history (format 1, the last step of format 2, no parent)."""
    out: dict[str, Any] = {"weight": float(c.weight)}
    if version == 2 and c.parent is not None:
        out["parent"] = int(c.parent)
    if whole or version == 1 or c.parent is None:
        out["associations"] = [list(map(int, a)) for a in c.associations]
    else:
        out["step_associations"] = list(map(int, c.associations[-1]))
    out.update(classes=[int(i) for i in c.classes], pose_mean=jf.floats(c.pose_mean),
               pose_cov=jf.floats(c.pose_cov))
    return out


def _step_json(s: StepRecord, version: int = 1, whole: bool = True) -> dict:
    return {"k": int(s.k),
            "components": [_component_json(c, version, whole) for c in s.components],
            # + 0.0 in Python (IEEE): -0.0 becomes 0.0 (an entropy of one hypothesis computed as
            # -0.0 inside jit, where XLA drops the same addition), so text comparisons agree too.
            "metrics": {key: int(v) if key == "num_components" else float(v) + 0.0
                        for key, v in s.metrics.items()}}


def _head_json(r: Result) -> dict[str, Any]:
    out: dict[str, Any] = {"estimator": r.estimator}
    if r.timing is not None:
        out["timing"] = {"compile_s": float(r.timing["compile_s"]),
                         "step_s": jf.floats(r.timing["step_s"])}
    if r.trajectory is not None:
        out["trajectory"] = jf.floats(r.trajectory)
    if r.objects is not None:
        out["objects"] = jf.floats(r.objects)
    return out


def _check_version(version: int) -> int:
    if version not in RESULT_FORMATS:
        raise ValueError(f"result format version {version!r}: expected one of {list(RESULT_FORMATS)}")
    return version


def result_to_json(r: Result, version: int = 2) -> dict:
    """The JSON object for ``r`` in format ``version`` (inverse of :func:`parse_result`)."""
    _check_version(version)
    link = HistoryLinker()
    steps = [_step_json(link(s) if version == 2 else s, version, whole=i == len(r.steps) - 1)
             for i, s in enumerate(r.steps)]
    return {"format": RESULT_FORMATS[version], "estimator": r.estimator, "steps": steps} | _head_json(r)


class ResultWriter:
    """Writes a result file one step at a time, as a run goes.

    Each record is checked (as :func:`load_result` would) and written to a temporary file beside
    ``path``; :meth:`finish` adds the other fields and moves the file to ``path``. Format 2 (the
    default) writes each component's parent and that step's associations, and the last step's
    whole histories (the writer holds one step back until it knows which is the last); ``version=1``
    writes every whole history at every step (T² lists over a run). Leaving a ``with`` block on an
    exception, or before :meth:`finish`, writes nothing::

        with hybridslam.ResultWriter("result.json") as writer:
            r = hybridslam.run(estimator, scenario, on_step=lambda record, info, s: writer.add(record),
                               keep_associations=False).result
            writer.finish(r)

    The text: one key of the top-level object per line, one step per line, or one component per
    line where a step's line would be long (:func:`hybridslam.io.jsonfields.dumps`).
    """

    def __init__(self, path: str | os.PathLike, version: int = 2):
        self.path = os.fspath(path)
        self.version = _check_version(version)
        if os.path.isdir(self.path):
            raise IsADirectoryError(f"{self.path!r} is a folder")
        folder, name = os.path.split(os.path.abspath(self.path))
        # open(..., "x"), not tempfile's 0600 files: the result gets the permissions of any file written
        self._file = open(os.path.join(folder, f".{name}.{secrets.token_hex(4)}.partial"), "x", encoding="utf-8")
        self._file.write("{" + f'"format": {json.dumps(RESULT_FORMATS[version])},\n "steps": [')
        self._count = 0  # steps added
        self._written = 0  # steps written to the temporary file
        self._link = HistoryLinker()
        self._previous: StepRecord | None = None  # format 2: the record before the one held back
        self._held: StepRecord | None = None  # format 2: the latest record, written once the next comes
        self._done = False

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if not self._done:
            self.discard()

    def __len__(self) -> int:
        """The steps added so far."""
        return self._count

    def _write(self, obj: dict) -> None:
        self._file.write(("," if self._written else "") + "\n  " + jf.dumps(obj, 2))
        self._written += 1

    def add(self, record: StepRecord) -> None:
        """Check and write the record of the next step (``record.k`` = the steps added so far + 1)."""
        k, path = self._count + 1, f"steps[{self._count}]"
        if self.version == 1:
            obj = _step_json(record)
            _step(obj, path, k)
            self._write(obj)
            self._count += 1
            return
        linked = self._link(record)
        _step(_step_json(linked, 2, whole=False), path, k, 2, self._held)
        if self._held is not None:
            self._write(_step_json(self._held, 2, whole=False))
        self._previous, self._held = self._held, linked
        self._count += 1

    def finish(self, result: Result) -> None:
        """Check ``result``'s fields besides its steps (the records added are the steps:
        ``timing["step_s"]`` and ``trajectory`` must match them) and write the file."""
        try:
            head = _head_json(result)
            _head(head, len(self))
            if self._held is not None:  # the last step: whole histories
                obj = _step_json(self._held, 2, whole=True)
                _step(obj, f"steps[{self._count - 1}]", self._count, 2, self._previous, True)
                self._write(obj)
            self._file.write("\n ]" + "".join(f",\n {json.dumps(key)}: {jf.dumps(value, 1)}"
                                              for key, value in head.items()) + "\n}\n")
            self._file.close()
            os.replace(self._file.name, self.path)
        except BaseException:
            self.discard()
            raise
        self._done = True

    def discard(self) -> None:
        """Write nothing: remove the temporary file."""
        self._file.close()
        if os.path.exists(self._file.name):
            os.remove(self._file.name)


def save_result(r: Result, path: str | os.PathLike, version: int = 2) -> None:
    """Validate ``r`` and write it as a result file in format ``version`` (nothing is written if it
    is invalid)."""
    with ResultWriter(path, version) as writer:
        for step in r.steps:
            writer.add(step)
        writer.finish(r)
