"""Recall of the truth in a belief: does some kept component hold the right loop closure?

A belief of several components (the hybrid belief, ``multimodal``) promises to keep the right
association history while it is not yet the most probable one. :func:`closure_recall` measures that
promise on a run with ground truth: at the last step, which kept components associate every
*loop-closing re-detection* (a detection of a landmark first detected more than ``gap`` steps
earlier, :func:`~.consistency.association_audit`) with the object that component made of that
landmark's first detection, and how far that component's final pose lies from the truth, beside the
top component's. Ground truth is read here only, for evaluation.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..io.result import ComponentRecord, Result
from ..models.scenario import Scenario
from .consistency import Audit, association_audit


@dataclasses.dataclass(frozen=True)
class ClosureRecall:
    """:func:`closure_recall`'s answer for one run.

    ``redetections``: loop-closing re-detections (the same in every component: they are the
    scenario's); ``components``: components kept at the last step; ``top_closed``: re-detections the
    top (highest-weight) component associates right; ``holding``: indices (in the last step's
    order, highest weight first) of the components that associate every one right; ``top_error`` /
    ``kept_error``: the translation error (m) of the final pose mean of the top component and of the
    highest-weight holding component (``None`` if none holds); ``kept_weight``: that component's
    weight."""

    redetections: int
    components: int
    top_closed: int
    holding: tuple[int, ...]
    top_error: float
    kept_error: float | None
    kept_weight: float | None

    @property
    def top_right(self) -> bool:
        """The top component closes the loop right (every re-detection on its landmark's first object)."""
        return self.redetections > 0 and 0 in self.holding

    @property
    def kept(self) -> bool:
        """Some kept component closes the loop right."""
        return self.redetections > 0 and bool(self.holding)


def component_audit(scenario: Scenario, component: ComponentRecord, gap: int = 20) -> Audit:
    """:func:`~.consistency.association_audit` of one component's association history."""
    truth = [[d.true_object for d in step.detections] for step in scenario.steps]
    return association_audit(truth, component.associations, gap)


def closure_recall(scenario: Scenario, result: Result, gap: int = 20) -> ClosureRecall:
    """Which of ``result``'s last-step components hold the right loop closure (module docstring).

    Needs the scenario's ``robot.true_poses`` and every detection's ``true_object``; raises a
    ``ValueError`` naming the missing field otherwise."""
    if scenario.true_robot_poses is None:
        raise ValueError("robot.true_poses: the scenario has no ground truth for the robot")
    for j, step in enumerate(scenario.steps):
        for i, d in enumerate(step.detections):
            if d.true_object is None:
                raise ValueError(f"steps[{j}].detections[{i}].true_object: missing (ground truth is needed)")
    if len(result.steps) != scenario.num_steps or not result.steps:
        raise ValueError(f"result: {len(result.steps)} steps, the scenario has {scenario.num_steps}")
    truth_xy = np.asarray(scenario.true_robot_poses, float)[-1, :2]
    comps = result.steps[-1].components
    audits = [component_audit(scenario, c, gap) for c in comps]
    holding = tuple(i for i, a in enumerate(audits) if a.redetections > 0 and a.closed == a.redetections)

    def error(c: ComponentRecord) -> float:
        return float(np.linalg.norm(np.asarray(c.pose_mean, float)[:2] - truth_xy))

    best = holding[0] if holding else None
    return ClosureRecall(
        redetections=audits[0].redetections, components=len(comps), top_closed=audits[0].closed, holding=holding,
        top_error=error(comps[0]), kept_error=None if best is None else error(comps[best]),
        kept_weight=None if best is None else float(comps[best].weight))
