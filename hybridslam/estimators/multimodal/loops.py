"""Loop closure during the run for ``multimodal``: its :class:`~..base.LoopClosureAccess`.

The search (:class:`~..loops.online.OnlineLoopClosure`) is the hybrid belief's: merges of late
objects into old ones, scored by their log Bayes factor against new objects (Doherty thesis Eq.
4.13's new-object density) and negative information, verified by re-solving the whole graph. What
differs is the state:

- classes: ``multimodal`` keeps a class posterior per object (``class_log_probs``), not a
  realization; the search pairs objects whose reported classes (the argmax of the posterior, where
  the component has associated the object: :meth:`Multimodal.view`'s) are equal or open;
- the graph re-solved is the one ``multimodal`` smooths: geometric factors only (its semantic term
  enters the weights and the class posteriors, not the Gaussian; :mod:`hybridslam.estimators.multimodal`);
- a merged object's class posterior is the product of its parts' (each divided by the class prior
  once: ``p(c | Z_a, Z_b) ∝ p(c | Z_a) p(c | Z_b) / p(c)``, the detections given the class
  independent, as Eq. 5.10's semantic term has them). A stretch of an object's detections that the
  search splits off keeps the whole object's posterior: the state holds no posterior per stretch.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..base import LoopClosureAccess, MergedComponent
from ..loops.online import whole, write_fields
from .state import State


@dataclasses.dataclass(frozen=True)
class MultimodalLoopAccess(LoopClosureAccess):
    """``multimodal``'s fields for :class:`~..loops.online.OnlineLoopClosure` (module docstring)."""

    max_steps: int

    def classes(self, state: State, i: int) -> np.ndarray:
        lp = np.asarray(state.class_log_probs[i])
        return np.where(np.asarray(state.observed[i]), np.argmax(lp, axis=-1), -1).astype(np.int64)

    def factors(self, state: State) -> tuple[bool, bool]:
        return False, False

    def write(self, state: State, slot: int, log_weights: np.ndarray, component: MergedComponent,
              parent: int) -> State:
        c = component
        class_lp, observed = merged_class_posteriors(np.asarray(state.class_log_probs[parent]),
                                                     np.asarray(state.observed[parent]),
                                                     np.asarray(state.model.class_prior), c.sources)
        return write_fields(
            state, slot,
            lambda x: (x.log_weights, x.history, x.class_log_probs, x.observed, x.num_created, x.smoothing.poses,
                       x.mean, x.cov),
            (whole(log_weights), c.history, class_lp, observed, c.num, c.poses, c.mean, c.cov))


def merged_class_posteriors(class_lp: np.ndarray, observed: np.ndarray, class_prior: np.ndarray,
                            sources: tuple[tuple[int, ...], ...]) -> tuple[np.ndarray, np.ndarray]:
    """The class log posteriors ``(Nmax, M)`` and observed flags ``(Nmax,)`` of a renumbered
    component: object ``t`` joins the parent's objects ``sources[t]`` (``class_lp``, ``observed``,
    the parent's; ``class_prior (Nmax, M)``, each slot's prior probabilities), its posterior
    ``∝ Π_s p_s(c) / p(c)^(|sources[t]| − 1)`` with ``p`` the first source's prior; slots past the
    objects in use uniform and unobserved, as uncreated slots start (:meth:`Multimodal.init`)."""
    n_max, m = class_lp.shape
    out = np.full((n_max, m), -math.log(m))
    seen = np.zeros(n_max, bool)
    for t, parts in enumerate(sources):
        with np.errstate(divide="ignore"):
            log_prior = np.log(class_prior[parts[0]])
        lp = class_lp[list(parts)].sum(axis=0) - (len(parts) - 1) * log_prior
        lp = np.where(np.isnan(lp), -np.inf, lp)  # a class the prior rules out stays out
        total = np.logaddexp.reduce(lp)
        # Parts that rule each other's classes out (no class left): the first part's posterior.
        out[t] = lp - total if np.isfinite(total) else class_lp[parts[0]]
        seen[t] = bool(observed[list(parts)].any())
    return out, seen
