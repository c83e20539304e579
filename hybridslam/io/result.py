"""Result files (`hybridslam-result/1`): the belief an estimator records after every step.

Layout: "Result file" in SCENARIO_FORMAT.md. Malformed input raises
`hybridslam.scenario.ScenarioError` with the field path, e.g.
``steps[2].components[0].weight: expected a number in (0, 1], got 1.5``.
Pure numpy + stdlib json, built from the validation helpers of `scenario`.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from collections.abc import Sequence
from typing import Any

import numpy as np

from . import jsonfields as jf

RESULT_FORMAT = "hybridslam-result/1"


@dataclass(eq=False)
class ComponentRecord:
    """One belief component after step k."""

    weight: float | np.floating  # numpy scalars are written as floats
    associations: Sequence[Sequence[int] | np.ndarray]  # per step j, object of each detection of step j+1
    classes: Sequence[int | np.integer]  # per object, -1 = open
    pose_mean: np.ndarray  # (3,) mean of x_k
    pose_cov: np.ndarray  # (3, 3) covariance of x_k
    __eq__ = jf.dataclass_eq


@dataclass(eq=False)
class StepRecord:
    """The belief after step k: components sorted by weight (highest first) and metrics."""

    k: int
    components: list[ComponentRecord]
    metrics: dict[str, float]  # entropy, det_cov, num_components; optional err_wmax, err_wavg
    __eq__ = jf.dataclass_eq


@dataclass(eq=False)
class Result:
    """A result file: the estimator's description and one StepRecord per step."""

    estimator: str
    steps: list[StepRecord]
    timing: dict | None = None  # {"compile_s": float, "step_s": [float] * T}
    trajectory: np.ndarray | None = None  # (T+1, 3) smoothed x_0..x_T of the final best component (smoothers)
    objects: np.ndarray | None = None  # (N, 3) final object estimates of that component, indexed like classes
    __eq__ = jf.dataclass_eq


def _weight(obj: Any, path: str) -> float:
    w = jf.number(obj, path)
    if not 0.0 < w <= 1.0 + jf.PROB_TOL:
        jf.fail(path, f"expected a number in (0, 1], got {w!r}")
    return w


def _component(obj: Any, path: str, k: int) -> ComponentRecord:
    obj = jf.as_object(obj, path)
    assoc = jf.get(obj, "associations", path, jf.as_list)
    if len(assoc) != k:
        jf.fail(f"{path}.associations", f"expected {k} lists (one per step so far), got {len(assoc)}")
    return ComponentRecord(
        weight=jf.get(obj, "weight", path, _weight),
        # -1: the component left the detection unassociated (clutter / outlier hypothesis)
        associations=jf.integer_lists(assoc, f"{path}.associations", -1),
        classes=jf.get(obj, "classes", path, jf.integers, -1),
        pose_mean=jf.get(obj, "pose_mean", path, jf.vector, 3),
        pose_cov=jf.get(obj, "pose_cov", path, jf.symmetric, 3),
    )


def _metrics(obj: Any, path: str, num_components: int) -> dict[str, float]:
    obj = jf.as_object(obj, path)
    n = jf.get(obj, "num_components", path, jf.integer)
    if n != num_components:
        jf.fail(f"{path}.num_components", f"{n}, but the step has {num_components} components")
    out: dict[str, float] = {key: jf.get(obj, key, path, jf.number) for key in ("entropy", "det_cov")}
    out.update({key: jf.number(v, f"{path}.{key}") for key, v in obj.items() if key not in out})
    return out | {"num_components": n}


def _step(obj: Any, path: str, k: int) -> StepRecord:
    obj = jf.as_object(obj, path)
    got = jf.get(obj, "k", path, jf.integer)
    if got != k:
        jf.fail(f"{path}.k", f"expected {k} (steps in order from 1), got {got}")
    raw = jf.get(obj, "components", path, jf.as_list)
    if not raw:
        jf.fail(f"{path}.components", "empty (weights must sum to 1)")
    comps = [_component(c, f"{path}.components[{i}]", k) for i, c in enumerate(raw)]
    weights = [float(c.weight) for c in comps]
    for i in range(1, len(weights)):
        if weights[i] > weights[i - 1]:
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


def parse_result(obj: Any) -> Result:
    """Validate a decoded JSON object and return the Result it describes."""
    top = jf.as_object(obj, "<root>")
    jf.check_format(top, RESULT_FORMAT)
    steps = jf.get(top, "steps", "", jf.as_list)
    return Result(steps=[_step(s, f"steps[{i}]", i + 1) for i, s in enumerate(steps)],
                  **_head(top, len(steps)))


def _head(top: dict, num_steps: int) -> dict[str, Any]:
    """The fields of a result file besides its steps, checked against its number of steps."""
    return {"estimator": jf.get(top, "estimator", "", jf.string),
            "timing": jf.maybe(top, "timing", "", _timing, num_steps),
            "trajectory": jf.maybe(top, "trajectory", "", jf.matrix, num_steps + 1, 3),
            "objects": jf.maybe(top, "objects", "", jf.matrix, None, 3)}


def _component_json(c: ComponentRecord) -> dict:
    return {
        "weight": float(c.weight),
        "associations": [list(map(int, a)) for a in c.associations],
        "classes": [int(i) for i in c.classes],
        "pose_mean": jf.floats(c.pose_mean),
        "pose_cov": jf.floats(c.pose_cov),
    }


def _step_json(s: StepRecord) -> dict:
    return {"k": int(s.k),
            "components": [_component_json(c) for c in s.components],
            # + 0.0 in Python (IEEE): -0.0 becomes 0.0 (an entropy of one hypothesis computed as
            # -0.0 inside jit, where XLA drops the same addition), so text comparisons agree too.
            "metrics": {key: int(v) if key == "num_components" else float(v) + 0.0
                        for key, v in s.metrics.items()}}


def result_to_json(r: Result) -> dict:
    """The JSON object for `r` (inverse of `parse_result`)."""
    out: dict[str, Any] = {"format": RESULT_FORMAT, "estimator": r.estimator,
                           "steps": [_step_json(s) for s in r.steps]}
    if r.timing is not None:
        out["timing"] = {"compile_s": float(r.timing["compile_s"]),
                         "step_s": jf.floats(r.timing["step_s"])}
    if r.trajectory is not None:
        out["trajectory"] = jf.floats(r.trajectory)
    if r.objects is not None:
        out["objects"] = jf.floats(r.objects)
    return out


def load_result(path: str | os.PathLike) -> Result:
    """Read and validate a result file."""
    return parse_result(jf.read_json(path))


class ResultWriter:
    """Writes a result file one step at a time, as a run goes.

    A result file holds every component's whole association history at every step, T² lists in
    all: a whole 1700-step log's file is 300 MB and its lists, held at once, take gigabytes. The
    writer checks each record (as :func:`load_result` would) and writes it to a temporary file
    beside ``path``; :meth:`finish` adds the other fields and moves the file to ``path``, byte for
    byte what :func:`save_result` writes for the same :class:`Result`. Leaving a ``with`` block on
    an exception, or before :meth:`finish`, writes nothing::

        with hybridslam.ResultWriter("result.json") as writer:
            r = hybridslam.run(estimator, scenario, on_step=lambda record, info, s: writer.add(record),
                               keep_associations=False).result
            writer.finish(r)
    """

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        self._steps = jf.StreamedList(path, "steps")
        self._done = False

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if not self._done:
            self._steps.discard()

    def __len__(self) -> int:
        """The steps written so far."""
        return len(self._steps)

    def add(self, record: StepRecord) -> None:
        """Check and write the record of the next step (``record.k`` = the steps written so far + 1)."""
        obj = _step_json(record)
        _step(obj, f"steps[{len(self)}]", len(self) + 1)
        self._steps.append(obj)

    def finish(self, result: Result) -> None:
        """Check ``result``'s fields besides its steps (the records added are the steps:
        ``timing["step_s"]`` and ``trajectory`` must match them) and write the file."""
        try:
            head = result_to_json(dataclasses.replace(result, steps=[]))
            _head(head, len(self))
            self._steps.close(head)
        except BaseException:
            self._steps.discard()
            raise
        self._done = True


def save_result(r: Result, path: str | os.PathLike) -> None:
    """Validate `r` and write it as a result file (nothing is written if it is invalid)."""
    with ResultWriter(path) as writer:
        for step in r.steps:
            writer.add(step)
        writer.finish(r)
