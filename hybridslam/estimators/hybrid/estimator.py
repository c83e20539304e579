"""The hybrid belief as an estimator: ``Hybrid(weights=LaplaceIS(), capacity=64, ...)``."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar


import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from ...models.scenario import Scenario
from ...models.classifier import ClassifierModel
from ...models.measurement import Detections
from ...models.model import NewObjects, model_from_scenario
from .. import novelty
from ...inference.gating import chi2_gate
from ..options import GATE, GATE_PROBABILITY, MAX_CHILDREN, MERGE_THRESHOLD, SAMPLES, Option, setting
from ..smoothers.kinds import Full, Smoother, check_smoother
from ..base import (CLUTTER_FROM_FILE, AbstractEstimator, Mixture, StepInfo, check_clutter, detection_slots,
                    history_length, object_slots, resolve_clutter)
from ...inference.ties import best_slot
from .belief import Belief, init_belief, priors_from_scenario
from .branching import Beam, Branching, Exhaustive
from .step import hybrid_step
from .weighers import WEIGHERS, AbstractWeigher, LaplaceIS, Sampled, make_weigher


def _positive_int(name: str, value, allow_none: bool = False) -> None:
    if allow_none and value is None:
        return
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        raise ValueError(f"Hybrid.{name}: expected a positive int{' or None' if allow_none else ''}, got {value!r}")


WEIGHTS = Option("weights", "association weights: laplace-is (low-variance Eq. 16), sampled (the paper's Monte-Carlo "
                            "Eq. 16) or linearized (deterministic)", parse=str, choices=tuple(WEIGHERS))
EXHAUSTIVE = Option("exhaustive", "enumerate every child (exponential in the detections; the exact reference)",
                    parse=None)
PRUNE_RATIO = Option("prune_ratio", "drop components below w_max / ratio", parse=float)
VISIBILITY_TEMPERATURE = Option("visibility_temperature", "tau_r or (tau_r, tau_b) of the smooth object observation "
                                                          "model (docs/gradients.md)",
                                parse=float, none="the paper's 0/1 footprint", command_line=False)


def _weigher(weights: str = LaplaceIS.name, samples: int | None = None) -> AbstractWeigher:
    """``Hybrid.weights`` from ``--weights`` and ``--samples``."""
    return make_weigher(weights, samples)


def _branching(max_children: int | None = None, exhaustive: bool | None = None) -> Branching:
    """``Hybrid.branching`` from ``--max-children`` and ``--exhaustive``."""
    if exhaustive:
        if max_children is not None:
            raise ValueError("--max-children: the exhaustive enumeration keeps every child")
        return Exhaustive()
    return Beam() if max_children is None else Beam(width=max_children)


class Hybrid(AbstractEstimator):
    """The hybrid belief of Tchuiev, Feldman & Indelman (IROS 2019): Algorithm 1 over weighted
    Gaussian components indexed by (class realization C, association history β_1:k).

    Settings (all static: each fixes a shape or a code path):

    * ``weights`` — the PropWeights estimator of Eq. 16 (:class:`~.weighers.LaplaceIS` by default,
      :class:`~.weighers.Sampled` is the paper's, :class:`~.weighers.Linearized` is deterministic);
    * ``branching`` — how parents split into children (Algorithm 1, line 2):
      :class:`~.branching.Exhaustive` (every assignment × class realization, exponential in the
      detections) or :class:`~.branching.Beam` (built one detection at a time, ``width`` kept);
    * ``capacity`` — ``K``, the most components kept after pruning;
    * ``prune_ratio`` — drop children below ``w_max / prune_ratio`` (Sec. V: 150); traced (it lives
      in the state's model), so changing it does not recompile;
    * ``gate`` — association gating (thesis Sec. 3.2.1): a detection may only be associated with the
      ``gate`` objects of lowest Mahalanobis distance per component (or a new object); ``None``
      enumerates every object exactly;
    * ``gate_probability`` — with clutter (the file's or the ``clutter`` setting), only the
      candidates inside the chi-square gate at this probability (thesis Sec. 3.2.1, as ``ml``,
      ``gpda`` and ``max-mixture`` gate: 0.999 is d² ≤ 13.8); a detection beyond it of every object
      is clutter in every child (counted in ``StepInfo.rejected``). ``None`` (the default, the
      paper's Algorithm 1): no chi-square gate. Without clutter it changes nothing;
    * ``clutter`` — with a :class:`~.branching.Beam`, each detection may also be clutter (a false
      detection of no object): the log density of its ``[range, bearing]`` under that hypothesis
      (prior probability of clutter included; e.g. ``log(0.01 / (max_range · fov))``), its scores
      of no known class; ``"file"`` (default): the scenario's ``sensor.clutter_log_density``, none
      without it; ``None`` or ``"none"``: every detection is of an object (the paper's model);
    * ``new_landmark`` — an unknown map's rule for a new object: ``"density"`` (default: "new" is a
      hypothesis of the scenario's new-object density everywhere) or ``"mahalanobis:TAU"`` (thesis
      Sec. 3.2.1: "new" only where no known object lies within ``d² <= TAU``; :mod:`..novelty`);
    * ``merge_threshold`` — ``None`` (default, Algorithm 1 as published): no merging; a squared Mahalanobis
      distance: after each step every component merges into the likeliest component with the same
      class realization and objects whose Gaussian holds its mean within that distance, their
      weights added (:mod:`hybridslam.inference.merging`; counted in ``StepInfo.merged``). Repeated
      readings of a landmark cluster otherwise fill the capacity with copies of one hypothesis
      (docs/studies/mrclam_unfiltered.md);
    * ``gn_max_steps`` — Gauss-Newton iteration budget of the update (Eq. 9) and of the laplace-is
      mode search. 50: the semantic factors of a strongly viewpoint-dependent classifier make
      Gauss-Newton converge only linearly (the default study at alpha 0.5 has 4 of 263 mode
      searches that need more than 20 iterations; all converge within 60); a search that converged
      stops early, so the budget costs nothing elsewhere;
    * ``smoother`` — :class:`~..smoothers.kinds.Full` (default): every component keeps its trajectory
      and re-solves it, relinearized, at every step (:mod:`..smoothers.kinds`); :class:`~..smoothers.kinds.Filter`:
      the joint Gaussian over ``[x_k, objects]`` only (past poses marginalized, never relinearized);
    * ``classifier`` — a classifier model name or object replacing the scenario's (``None``: the file's);
    * ``max_detections`` — detection slots per step (``None``: the scenario's largest step);
    * ``max_steps`` — the length of the association history (``None``: the scenario's steps; a larger
      value lets scenarios of different lengths share one compiled step);
    * ``visibility_temperature`` — ``τ_r`` or ``(τ_r, τ_b)`` for the smooth object observation model
      (``docs/gradients.md``); ``None`` is the paper's 0/1 footprint;
    * ``batch_axis`` — the name of an enclosing ``jax.vmap`` over beliefs (set by the studies):
      the step then skips component slots that are empty in every belief of the batch.
    """

    weights: AbstractWeigher = eqx.field(default=LaplaceIS(), metadata=setting(
        WEIGHTS, SAMPLES, build=_weigher, show=lambda e: f"weights={e.weights.name}, samples={e.weights.draws}",
        note={"samples": f"per parent for --weights sampled (n_s of Eq. 16, default {Sampled.samples}), per "
                         f"candidate child for laplace-is (default {LaplaceIS.samples})"}))
    branching: Branching = eqx.field(default=Beam(), metadata=setting(
        MAX_CHILDREN, EXHAUSTIVE, build=_branching, note={"max_children": f"children, default {Beam.width}"},
        show=lambda e: "" if isinstance(e.branching, Exhaustive) else f"branching=beam({e.branching.width})"))
    capacity: int = eqx.field(default=64, static=True)
    prune_ratio: float = eqx.field(default=150.0, static=True,
                                   metadata=setting(PRUNE_RATIO, note="the paper's {default}"))
    gate: int | None = eqx.field(default=None, static=True, metadata=setting(
        GATE, show=lambda e: "" if e.gate is None else f"gate_candidates={e.gate}"))
    clutter: float | str | None = eqx.field(default=CLUTTER_FROM_FILE, static=True,
                                            metadata=setting(note="a known or an unknown map"))
    new_landmark: str = eqx.field(default=novelty.DENSITY, static=True)
    gn_max_steps: int = eqx.field(default=50, static=True)
    smoother: Smoother = Full()
    classifier: str | ClassifierModel | None = None
    max_detections: int | None = eqx.field(default=None, static=True)
    max_steps: int | None = eqx.field(default=None, static=True)
    visibility_temperature: float | tuple[float, float] | None = eqx.field(
        default=None, static=True, metadata=setting(VISIBILITY_TEMPERATURE))
    gate_probability: float | None = eqx.field(default=None, static=True, metadata=setting(
        GATE_PROBABILITY, show=lambda e: "" if e.gate_probability is None else f"gate_probability={e.gate_probability:g}"))
    merge_threshold: float | None = eqx.field(default=None, static=True, metadata=setting(
        MERGE_THRESHOLD, show=lambda e: "" if e.merge_threshold is None else f"merge_threshold={e.merge_threshold:g}"))
    batch_axis: str | None = eqx.field(default=None, static=True)

    name: ClassVar[str] = "hybrid"
    title: ClassVar[str] = "hybrid belief"
    reference: ClassVar[str] = "Tchuiev et al. 2019, Alg. 1"
    init_settings = ("prune_ratio", "clutter", "new_landmark", "classifier", "visibility_temperature")
    described = ("weights", "capacity", "prune_ratio", "gate", "gate_probability", "branching", "clutter",
                 "new_landmark", "merge_threshold", "smoother")

    def __check_init__(self):
        if not isinstance(self.branching, (Exhaustive, Beam)):
            raise ValueError(f"Hybrid.branching: expected Exhaustive() or Beam(width), got {self.branching!r}")
        check_smoother("Hybrid", self.smoother)
        check_clutter("Hybrid", self.clutter)
        novelty.parse_new_landmark("Hybrid", self.new_landmark)
        if isinstance(self.clutter, (int, float)) and not isinstance(self.branching, Beam):
            raise ValueError("Hybrid.clutter: the clutter hypothesis needs branching=Beam(...)")
        if not isinstance(self.weights, AbstractWeigher):
            raise ValueError(f"Hybrid.weights: expected a weigher (LaplaceIS(), Sampled(), Linearized()), "
                             f"got {self.weights!r}")
        _positive_int("capacity", self.capacity)
        _positive_int("gate", self.gate, allow_none=True)
        if self.gate_probability is not None:
            try:
                chi2_gate(self.gate_probability)
            except (TypeError, ValueError):
                raise ValueError(f"Hybrid.gate_probability: expected a number in (0, 1) or None, "
                                 f"got {self.gate_probability!r}") from None
        _positive_int("gn_max_steps", self.gn_max_steps)
        _positive_int("max_detections", self.max_detections, allow_none=True)
        _positive_int("max_steps", self.max_steps, allow_none=True)
        if not (isinstance(self.prune_ratio, (int, float)) and self.prune_ratio >= 1.0):
            raise ValueError(f"Hybrid.prune_ratio: must be >= 1, got {self.prune_ratio!r}")
        d2 = self.merge_threshold
        if d2 is not None and not (isinstance(d2, (int, float)) and not isinstance(d2, bool) and math.isfinite(d2)
                                   and d2 >= 0):
            raise ValueError(f"Hybrid.merge_threshold: expected a non-negative squared Mahalanobis distance or None, "
                             f"got {d2!r}")
        if self.batch_axis is not None and not isinstance(self.batch_axis, str):
            raise ValueError(f"Hybrid.batch_axis: expected a vmap axis name (str) or None, got {self.batch_axis!r}")

    def init(self, scenario: Scenario) -> Belief:
        """One component of weight 1, every class open (Eq. 3), sized for ``scenario``."""
        object_slots(scenario)  # a scenario with nothing to associate is refused
        model = model_from_scenario(scenario, self.classifier, self.prune_ratio, self.visibility_temperature)
        clutter = resolve_clutter(self.clutter, scenario)
        if clutter is not None:
            if not isinstance(self.branching, Beam):
                raise ValueError("clutter: the scenario declares sensor.clutter_log_density, and the exhaustive "
                                 "enumeration has no clutter hypothesis; use the beam or clutter='none' (--clutter none)")
            f = lambda a: jnp.asarray(a, dtype=float)  # noqa: E731
            model = eqx.tree_at(lambda m: m.clutter, model, NewObjects(f(clutter), f(math.pi**2)),
                                is_leaf=lambda x: x is None)
        slots = detection_slots(self.max_detections, scenario)
        steps = history_length(self.max_steps, scenario)
        belief = init_belief(priors_from_scenario(scenario), model, self.capacity, steps, slots)
        tau = (None if scenario.discovery is None
               else jnp.asarray(novelty.threshold("Hybrid", self.new_landmark), dtype=float))
        return dataclasses.replace(
            belief, smoothing=self.smoother.init(scenario, steps, slots, belief.num_objects, self.max_steps, self.capacity),
            new_landmark_tau=tau)

    def step(
        self, state: Belief, odometry: Float[Array, "3"], detections: Detections, key: PRNGKeyArray
    ) -> tuple[Belief, StepInfo]:
        """Propagate, split, weigh (Eq. 16), prune, update: Algorithm 1 (:func:`.step.hybrid_step`)."""
        return hybrid_step(self, state, odometry, detections, key)

    def view(self, state: Belief) -> Mixture:
        return Mixture(state.log_weights, state.mean[:, :3], state.cov[:, :3, :3], state.classes, state.history,
                       state.k)

    def trajectory(self, state: Belief):
        """The smoothed ``x_0..x_T`` of the best component (``None`` without smoothing)."""
        if not state.smoothing.smooths:
            return None
        return state.smoothing.trajectory(best_slot(state.log_weights))

    def objects(self, state: Belief):
        """The best component's smoothed objects and their count (``None`` without smoothing)."""
        if not state.smoothing.smooths:
            return None
        best = best_slot(state.log_weights)
        count = jnp.asarray(state.num_objects) if state.num_created is None else state.num_created[best]
        return state.mean[best, 3:].reshape(-1, 3), count

    def loop_closure_access(self):
        """The belief's fields for loop closure during the run (:mod:`.loops`)."""
        from .loops import HybridLoopAccess  # loops imports the belief, not the estimator

        return HybridLoopAccess(self.gn_max_steps)

    def with_batch_axis(self, axis_name: str | None) -> Hybrid:
        return dataclasses.replace(self, batch_axis=axis_name)
