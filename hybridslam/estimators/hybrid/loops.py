"""Loop closure during the run for the hybrid belief: its :class:`~..base.LoopClosureAccess`.

The search (:class:`~..loops.online.OnlineLoopClosure`) is shared with ``multimodal``. The hybrid
belief holds each object's class realization (``classes``, -1 open: Sec. IV-D), so the merge search
pairs objects of equal or open realizations, and a merged object takes the old one's realization
(the late one's where it is open, :func:`~..loops.merge.compact`). The re-solved graph is the
belief's own: its semantic factors, with the realizations where the classifier sees scores.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..base import LoopClosureAccess, MergedComponent
from ..loops.online import ClosureHypothesis as ClosureHypothesis  # the names' former home, still importable
from ..loops.online import OnlineLoopClosure as OnlineLoopClosure
from ..loops.online import whole, write_fields
from .belief import Belief


@dataclasses.dataclass(frozen=True)
class HybridLoopAccess(LoopClosureAccess):
    """The hybrid belief's fields for :class:`~..loops.online.OnlineLoopClosure`."""

    max_steps: int

    def classes(self, state: Belief, i: int) -> np.ndarray:
        return np.asarray(state.classes[i])

    def factors(self, state: Belief) -> tuple[bool, bool]:
        return True, bool(state.model.sensor.classifier.uses_scores)

    def write(self, state: Belief, slot: int, log_weights: np.ndarray, component: MergedComponent,
              parent: int) -> Belief:
        c = component
        return write_fields(
            state, slot,
            lambda x: (x.log_weights, x.history, x.classes, x.num_created, x.smoothing.poses, x.mean, x.cov),
            (whole(log_weights), c.history, c.classes, c.num, c.poses, c.mean, c.cov))
