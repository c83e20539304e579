"""One inference step of the hybrid belief: Algorithm 1 as one pure function (``Hybrid.step``).

:func:`hybrid_step` is pure; ``jax.vmap`` it over a leading axis of beliefs to run many tracks (or
many parameter settings: the model lives in the belief) at once. Compiles once per (capacity,
history length, detection slots, objects, classes, weigher, classifier type, hard or smooth
visibility, known or unknown map, gating); model parameters are traced. Differentiable in every
continuous input (``docs/gradients.md``).

Unknown maps (``model.discovery``): a child may give a detection a new object (the null /
new-landmark hypothesis, thesis Sec. 3.2.1). Its weight gets that detection's
:func:`~hybridslam.weights.new_object_log_likelihood`; its Gaussian gets the object from
:func:`~hybridslam.discovery.create_object` *before* the Gauss-Newton update, in which that
detection is then no factor: the back-projection already used it, and using it again would count
it twice. (The detection's scores are not used on the new object's orientation either, a small
loss of information: the weight integrates them over the unknown viewpoint instead.)
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import NamedTuple, Protocol, runtime_checkable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.scipy.special import logsumexp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from ...config import x64_enabled
from ...inference.batching import map_distinct, map_live, smoothing_chunk
from ...inference.discovery import create_objects
from ...inference.gating import chi2_gate, contradicted, gate, mahalanobis
from ...inference.merging import merge_equivalent
from ...inference.update import gauss_newton_update
from ...inference.ties import best_slot
from ...models.measurement import Detections
from ...models.motion import propagate
from .. import novelty
from ..base import StepInfo, lacks_object_slots, relevant_children
from ..smoothers.kinds import Smoother, SmootherState
from ..smoothers.factors import history_factors, new_overflow
from .belief import Belief
from .branching import Beam, Branching, beam_children
from .hypotheses import Children, children, hypothesis_table
from .prune import PruneStats, prune
from .weighers import AbstractWeigher, Context
from .weights import class_marginal, new_object_log_likelihood


@runtime_checkable
class HybridSettings(Protocol):
    """The settings :func:`hybrid_step` reads: a :class:`~.estimator.Hybrid` (a structural type, so
    that this module, which the estimator imports, needs no import of it)."""

    @property
    def weights(self) -> AbstractWeigher: ...
    @property
    def branching(self) -> Branching: ...
    @property
    def gate(self) -> int | None: ...
    @property
    def gn_max_steps(self) -> int: ...
    @property
    def smoother(self) -> Smoother: ...
    @property
    def batch_axis(self) -> str | None: ...
    @property
    def merge_threshold(self) -> float | None: ...
    @property
    def gate_probability(self) -> float | None: ...


class HybridDetails(eqx.Module):
    """The hybrid belief's own diagnostics of one step (``StepInfo.details``)."""

    prune: PruneStats
    parent: Int[Array, " K"]  # slot of each new component's parent in the previous belief
    solver_result: optx.RESULTS  # Gauss-Newton outcome per component (Eq. 9)
    ess: Float[Array, " K"]  # normalized effective sample size of each kept weight (1 = exact; NaN if empty)
    smoothings: Int[Array, ""]  # distinct factor graphs smoothed this step (0 with the filter)


def _realize(classes: Int[Array, " N"], assign: Int[Array, " Dmax"], slot_class: Int[Array, " Dmax"], new):
    """Write the classes of newly associated objects (Sec. IV-D); all others are unchanged."""
    target = jnp.where(new, assign, classes.shape[0])  # out of bounds -> dropped
    return classes.at[target].set(slot_class, mode="drop")


def _lacks_object_slots(belief: Belief, detections: Detections) -> Bool[Array, ""]:
    """Whether a parent within ``RELEVANT_NATS`` of the best had no free object slot at this step
    (:func:`~hybridslam.estimators.base.lacks_object_slots`)."""
    assert belief.num_created is not None  # an unknown map's belief
    return lacks_object_slots(detections.mask, belief.num_created, belief.num_objects,
                              relevant_children(belief.log_weights))


def _create_and_update(sensor, discovery, mean, cov, assign, creates, slot_class, detections: Detections, max_steps):
    """:func:`~hybridslam.inference.discovery.create_objects`, then the update with the detections of
    the child's other slots (Eq. 9-10)."""
    mean, cov = create_objects(mean, cov, assign, creates, detections.geo, sensor.geometric_cov,
                               discovery.orientation_var)
    return gauss_newton_update(sensor, mean, cov, jnp.where(creates, -1, assign), slot_class, detections, max_steps)


def _new_object_terms(belief: Belief, mean, cov, detections: Detections, kids: Children,
                      near: Bool[Array, "K Dmax"] | None) -> Float[Array, "K A Mc"]:
    """Σ over a child's creating slots of :func:`~hybridslam.weights.new_object_log_likelihood`, and
    over its unmapped ones of the class marginal :func:`~.weights.class_marginal`; ``-inf`` where
    ``near`` (the Mahalanobis rule rules "new" out: :func:`_near_known`)."""
    sensor = belief.model.sensor
    lik = jax.vmap(new_object_log_likelihood, (None, 0, 0, None, None))(
        sensor, mean[:, :3], cov[:, :3, :3], detections, belief.model.discovery
    )  # (K, Dmax, M)
    if near is not None:
        lik = jnp.where(near[..., None], -jnp.inf, lik)
    pick = kids.slot_class[..., None] == jnp.arange(lik.shape[-1]).reshape(1, 1, 1, 1, -1)  # (K, A, Mc, Dmax, M)
    picked = jnp.sum(jnp.where(pick, lik[:, None, None], 0.0), axis=-1)
    unmapped = jnp.sum(jnp.where(kids.unmapped, class_marginal(lik)[:, None, :], 0.0), axis=-1)
    return jnp.sum(jnp.where(kids.creates[:, :, None, :], picked, 0.0), axis=-1) + unmapped[:, :, None]




def _equal_rows(rows: Int[Array, "K L"]) -> Bool[Array, "K K"]:
    """``rows[i] == rows[j]`` everywhere, for every pair: exactly, from one matrix product.

    ``‖a − b‖² = a·a + b·b − 2 a·b`` is zero exactly where ``a = b``: in float64 every product and
    every partial sum of integer entries is an integer below 2⁵³ (association histories: ``L``
    entries of magnitude at most the object count, ``L · N² ≪ 2⁵³``), so no rounding occurs in any
    summation order. The pairwise comparison costs ``K² L`` element operations (a whole MRCLAM
    log's 16 components × 1,700 steps × 21 slots: 3.9 ms a step on a 2-core CPU); the product runs
    at the speed of the matrix unit. Without float64 (``jax_enable_x64`` off) it compares directly."""
    if not x64_enabled():
        return jnp.all(rows[:, None] == rows[None, :], axis=-1)
    x = rows.astype(jnp.float64)
    sq = jnp.sum(x * x, axis=-1)
    return sq[:, None] + sq[None, :] - 2.0 * (x @ x.T) == 0.0


def _same_graph(history: Int[Array, "K T Dmax"], created: Int[Array, " K"], classes: Int[Array, "K N"],
                by_class: bool) -> Bool[Array, "K K"]:
    """Which children have equal factor graphs: equal association histories and object counts, and
    equal class realizations where the semantic factors depend on the state (``by_class``)."""
    same = _equal_rows(history.reshape(history.shape[0], -1)) & (created[:, None] == created[None, :])
    if by_class:
        same &= jnp.all(classes[:, None] == classes[None, :], axis=-1)
    return same


class _Scored(NamedTuple):
    """The weighed children of a step, flat (one row per child), whichever way they were branched."""

    log_w: Float[Array, " C"]  # -inf: impossible
    possible: Bool[Array, " C"]
    prior: Float[Array, " C"]
    log_lik_free: Float[Array, " C"]
    ess: Float[Array, " C"]
    converged: Bool[Array, " C"]
    parent: Int[Array, " C"]
    assign: Int[Array, "C Dmax"]
    creates: Bool[Array, "C Dmax"]
    unmapped: Bool[Array, "C Dmax"]
    new: Bool[Array, "C Dmax"]
    slot_class: Int[Array, "C Dmax"]
    dropped: Int[Array, ""]


def _near_known(belief: Belief, mean, cov, detections: Detections) -> Bool[Array, "K Dmax"] | None:
    """Under ``new_landmark="mahalanobis:TAU"`` (thesis Sec. 3.2.1, :mod:`..novelty`): per component
    and detection, whether a created object lies within ``d² <= τ``, where "new" is no hypothesis;
    nowhere under the density rule (``τ = inf``; traced: one compiled step for every rule and τ).
    ``None`` on a known map. A step whose every child would break the rule keeps its parents and
    skips its detections (counted), as a step no child explains."""
    tau = belief.new_landmark_tau
    if tau is None or belief.model.discovery is None:
        return None
    d2 = jax.vmap(mahalanobis, (None, 0, 0, None))(belief.model.sensor, mean, cov, detections)  # (K, Dmax, N)
    return jax.vmap(novelty.known_within, (0, 0, None))(d2, belief.num_created, tau)


def _exhaustive(settings, belief: Belief, mean, cov, detections: Detections, candidates, realize, discovery, key):
    """Every child of the static table (:mod:`.hypotheses`), weighed on the ``(K, A, Mc)`` grid."""
    model = belief.model
    num_candidates = candidates.shape[-1] if candidates is not None else belief.num_objects
    table = hypothesis_table(num_candidates, belief.max_detections, model.num_classes if realize else 1, discovery,
                             candidates is not None)
    kids = jax.vmap(children, (None, 0, None, None, None, 0, 0))(
        table, belief.classes, detections.mask, model.class_prior, realize, belief.num_created, candidates
    )
    # `prior` holds every factor of a child's weight that does not depend on the objects' Gaussian
    # (so the laplace-is screen ranks by it too).
    prior = belief.log_weights[:, None, None] + kids.log_prior
    if discovery:
        prior = prior + _new_object_terms(belief, mean, cov, detections, kids,
                                          _near_known(belief, mean, cov, detections))
    ctx = Context(model.sensor, belief.alive, mean, cov, detections, table, kids, prior, settings.gn_max_steps,
                  settings.batch_axis)
    log_lik, log_lik_free, ess, converged = settings.weights.weigh(ctx, key)
    possible = kids.valid & belief.alive[:, None, None]
    # `where`, not `+`: empty slots may carry non-finite likelihoods that must not leak.
    log_w = jnp.where(possible, prior + log_lik, -jnp.inf)
    parent, a, m = (x.reshape(-1) for x in jnp.meshgrid(*(jnp.arange(d) for d in log_w.shape), indexing="ij"))
    flat = lambda x: x.reshape(-1)  # noqa: E731
    return _Scored(flat(log_w), flat(possible), flat(prior), flat(log_lik_free), flat(ess), flat(converged), parent,
                   kids.assign[parent, a], kids.creates[parent, a], kids.unmapped[parent, a], kids.new[parent, a, m],
                   kids.slot_class[parent, a, m], jnp.zeros((), jnp.int32))


def _beam(settings, belief: Belief, mean, cov, detections: Detections, candidates, realize, discovery, key):
    """The children built one detection at a time (:mod:`.branching`), weighed one by one."""
    model = belief.model
    new_terms = None
    if discovery:
        new_terms = jax.vmap(new_object_log_likelihood, (None, 0, 0, None, None))(
            model.sensor, mean[:, :3], cov[:, :3, :3], detections, model.discovery)  # (K, Dmax, M)
        near = _near_known(belief, mean, cov, detections)
        if near is not None:  # the Mahalanobis rule: no "new" where a known object lies within τ
            new_terms = jnp.where(near[..., None], -jnp.inf, new_terms)
    clutter_terms = None
    if model.clutter is not None:  # set by Hybrid.init from its clutter setting (the scenario's by default)
        clutter = model.clutter
        per_class = jax.vmap(new_object_log_likelihood, (None, 0, 0, None, None))(
            model.sensor, mean[:, :3], cov[:, :3, :3], detections, clutter)  # (K, Dmax, M)
        clutter_terms = class_marginal(per_class)  # scores of no known class
    # Known map, no clutter hypothesis: a detection may be skipped where no child names them all.
    skip = model.clutter is None and not discovery
    ch = beam_children(belief, mean, cov, detections, candidates, new_terms, realize, settings.branching.width,
                       settings.batch_axis, clutter_terms, skip)
    log_lik, log_lik_free, ess, converged = settings.weights.weigh_children(
        model.sensor, belief.alive, mean, cov, detections, ch, settings.gn_max_steps, settings.batch_axis, key)
    log_w = jnp.where(ch.valid, ch.prior + log_lik, -jnp.inf)
    return _Scored(log_w, ch.valid, ch.prior, log_lik_free, ess, converged, ch.parent, ch.assign, ch.creates,
                   ch.unmapped, ch.new, ch.slot_class, ch.dropped)


def hybrid_step(
    settings: HybridSettings, belief: Belief, odometry: Float[Array, "3"], detections: Detections, key: PRNGKeyArray
) -> tuple[Belief, StepInfo]:
    """Algorithm 1 (see :class:`~.estimator.Hybrid`); ``settings`` are the estimator's static settings."""
    model = belief.model
    realize = model.sensor.classifier.uses_scores
    discovery = model.discovery is not None
    if discovery and belief.num_created is None:
        raise ValueError("belief.num_created: a model with discovery needs a belief built by init_belief with it")
    # No eqx.error_if on a full history: its host callback would keep the step out of JAX's persistent
    # compilation cache. The driver refuses more steps than the history holds before running any.
    k = belief.k

    # Algorithm 1, line 3: propagate every component with the motion model (Eq. 11).
    mean, cov = jax.vmap(propagate, (0, 0, None, None))(belief.mean, belief.cov, odometry, model.motion_cov)

    # Line 2 of PROPWEIGHTS: split each parent into (β_k, new class realizations), and line 5:
    # PropWeights, Eq. 16 (gating, thesis Sec. 3.2.1: the G nearest objects per detection, and
    # with clutter to explain what it leaves, only those inside the chi-square gate).
    candidates = None
    chi2 = settings.gate_probability is not None and model.clutter is not None
    if settings.gate is not None or chi2:
        size = belief.num_objects if settings.gate is None else min(settings.gate, belief.num_objects)
        max_d2 = chi2_gate(settings.gate_probability) if chi2 else math.inf
        candidates = jax.vmap(partial(gate, num_candidates=size, max_d2=max_d2), (None, 0, 0, None, 0))(
            model.sensor, mean, cov, detections, belief.num_created)
    branch = _beam if isinstance(settings.branching, Beam) else _exhaustive
    sc = branch(settings, belief, mean, cov, detections, candidates, realize, discovery, key)
    # No hypothesis puts every detected object in view: the 0/1 visibility model cannot explain
    # this step, so weigh it by the measurement likelihood alone rather than lose the belief.
    visibility_ignored = ~jnp.any(sc.log_w > -jnp.inf) & jnp.any(sc.possible)
    log_w = jnp.where(visibility_ignored, jnp.where(sc.possible, sc.prior + sc.log_lik_free, -jnp.inf), sc.log_w)

    # Line 7: PruneAndNormalize.
    index, new_log_w, stats = prune(log_w, belief.capacity, model.prune_ratio)
    index = jnp.minimum(index, log_w.shape[0] - 1)  # fewer children than slots: prune pads with dead ones
    parent, assign, creates, slot_class = sc.parent[index], sc.assign[index], sc.creates[index], sc.slot_class[index]
    new, unmapped, ess, converged = sc.new[index], sc.unmapped[index], sc.ess[index], sc.converged[index]
    # No child at all (on a known map, more detections than objects that could explain them):
    # the step's detections are skipped, and counted, rather than the belief lost. Each parent stays,
    # propagated, with its weight and no association for this step.
    explained = jnp.any(new_log_w > -jnp.inf)
    slots_k = jnp.arange(belief.capacity)
    new_log_w = jnp.where(explained, new_log_w, belief.log_weights)
    parent = jnp.where(explained, parent, slots_k)
    assign = jnp.where(explained, assign, -1)
    creates = creates & explained
    unmapped = unmapped & explained
    new = new & explained
    slot_class = jnp.where(explained, slot_class, 0)
    ess = jnp.where(explained, ess, 1.0)
    converged = converged | ~explained

    # Line 11: update every kept child with its measurement factors (Eq. 9-10).
    alive = new_log_w > -jnp.inf
    smoothing = settings.smoother.smooths
    if smoothing:
        # The smoother below re-solves each kept child's whole graph, this step's factors included:
        # the filter's update would only be its warm start, so the child starts from its prediction
        # (same solution, measured on the hallway; a fifth less compiling) and objects it creates.
        new_mean, new_cov = mean[parent], cov[parent]
        if discovery:
            create = partial(create_objects, geo=detections.geo, geometric_cov=model.sensor.geometric_cov,
                             orientation_var=model.discovery.orientation_var)
            # The solver's result comes from the smoother below.
            new_mean, new_cov = jax.vmap(create)(new_mean, new_cov, assign, creates)
    elif discovery:
        update = partial(_create_and_update, model.sensor, model.discovery, detections=detections,
                         max_steps=settings.gn_max_steps)
        new_mean, new_cov, result = map_live(update, alive, mean[parent], cov[parent], assign, creates, slot_class,
                                             axis_name=settings.batch_axis)
    else:
        update = partial(gauss_newton_update, model.sensor, detections=detections, max_steps=settings.gn_max_steps)
        new_mean, new_cov, result = map_live(update, alive, mean[parent], cov[parent], assign, slot_class,
                                             axis_name=settings.batch_axis)
    classes = jax.vmap(_realize)(belief.classes[parent], assign, slot_class, new)
    history = belief.history[parent].at[:, k, :].set(assign)
    num_created = None if not discovery else belief.num_created[parent] + jnp.sum(creates, axis=-1, dtype=jnp.int32)
    kept = belief.smoothing
    num_smoothed = jnp.zeros((), jnp.int32)
    if smoothing:
        if kept.log is None:
            raise ValueError(f"Hybrid(smoother={settings.smoother!r}): this belief carries no data log (built by "
                             "init_belief, not Hybrid.init); build it with Hybrid.init(scenario) or use smoother=Filter()")
        # Relinearize each kept component's whole trajectory and map (smoothers/kinds.py), warm-started
        # from its parent's trajectory and its prediction; its marginal over [x_k, objects]
        # becomes the component's Gaussian.
        kept = kept.record(k, odometry, detections)
        log = kept.log
        assert log is not None  # record writes one
        created = num_created if discovery else jnp.full((belief.capacity,), belief.num_objects, jnp.int32)

        # Children with the same associations (and, where the classifier sees the viewpoint, the
        # same classes) have the same graph: one smoothing serves them all.
        by_class = realize and model.sensor.classifier.viewpoint_dependent
        # One smoothing per chunk, so that exactly the distinct graphs are solved and a chunk's
        # Levenberg-Marquardt loop never waits for a slower member (under a vmap over tracks it runs
        # until every track's member is done): the hallway's dense 3P algebra barely batches (one step
        # at fixed states: 10-15% faster than chunks of four), and on the paper setup the 16-file
        # sweep's smoothing cost fell from 0.31 s to nothing measurable (batched work 1.24 s with
        # chunks of four, 1.05 s of two, 0.92 s one by one, the filter 0.90-0.94 s). Only long pose
        # chains (MRCLAM: a 201-step scan, latency-bound) batch better by four.
        parents = kept.components(parent)
        assert parents.poses is not None  # a smoother's init gives every component a trajectory
        poses_, objects_ = parents.poses.shape[-2], belief.num_objects
        chunk = smoothing_chunk(poses_, objects_)

        def smoothed(poses_i, mean_i, cov_i, history_i, classes_i, created_i, window_i):
            factors = history_factors(history_i, classes_i if realize else None)
            return settings.smoother.smooth(SmootherState(poses_i, log, window_i), factors, k + 1, created_i,
                                            model.sensor, model.motion_cov, True, "sum", mean_i, cov_i)

        out, num_smoothed = map_distinct(smoothed, alive, _same_graph(history, created, classes, by_class),
                                         parents.poses, new_mean, new_cov, history, classes, created,
                                         parents.window, chunk=chunk, axis_name=settings.batch_axis)
        new_mean, new_cov, result = out.mean, out.cov, out.result
        kept = dataclasses.replace(kept, poses=out.poses, window=out.window)
    # Empty slots copy the best component so later batched math on them stays finite.
    new_mean = jnp.where(alive[:, None], new_mean, new_mean[:1])
    new_cov = jnp.where(alive[:, None, None], new_cov, new_cov[:1])
    kept = kept.where(alive, kept.components(slice(0, 1)))
    num_merged = jnp.zeros((), jnp.int32)
    if settings.merge_threshold is not None:
        # Copies of one hypothesis (same classes and objects, the same Gaussian) become one, their
        # weights added: the freed slots go to the next step's alternatives (inference.merging).
        same = jnp.all(classes[:, None] == classes[None, :], axis=-1)
        if num_created is not None:
            same &= num_created[:, None] == num_created[None, :]
        new_log_w, _, num_merged = merge_equivalent(new_log_w, new_mean, new_cov, same, settings.merge_threshold)
        alive = new_log_w > -jnp.inf  # a merged slot is empty (its Gaussian stays finite for the batched math)

    new_belief = Belief(
        log_weights=new_log_w,
        mean=new_mean,
        cov=new_cov,
        classes=classes,
        history=history,
        k=k + 1,
        model=model,
        num_created=num_created,
        smoothing=kept,
        new_landmark_tau=belief.new_landmark_tau,
    )
    kept_ess = jnp.where(alive, ess, jnp.nan)
    best = best_slot(new_log_w)
    # The best child's unmapped objects (no free slot) are not unassociated detections.
    num_unmapped = jnp.sum(detections.mask & unmapped[best], dtype=jnp.int32)
    unassociated = jnp.sum(detections.mask & (assign[best] < 0), dtype=jnp.int32) - num_unmapped
    # The best child's associations against its parent's prediction (objects it creates or leaves
    # unmapped aside; clutter explains a detection, a skip does not).
    inconsistent = explained & contradicted(model.sensor, mean[parent[best]], cov[parent[best]], detections,
                                            jnp.where(creates[best], -1, assign[best]),
                                            (assign[best] < 0) & ~unmapped[best] & (model.clutter is None))
    info = StepInfo(
        k=k + 1,
        num_components=jnp.sum(alive, dtype=jnp.int32),
        log_evidence=logsumexp(log_w),
        dropped_capacity=stats.dropped_capacity.astype(jnp.int32),
        dropped_budget=sc.dropped,
        # Unassociated detections of the best component: all of them if no child explains the
        # step; those a known map's beam skipped; those clutter explains (rejected).
        skipped=jnp.where(explained, 0 if model.clutter is not None else unassociated,
                          jnp.sum(detections.mask, dtype=jnp.int32)),
        rejected=unassociated if model.clutter is not None else jnp.zeros((), jnp.int32),
        unmapped=num_unmapped,
        visibility_ignored=visibility_ignored,
        inconsistent=inconsistent,
        solver_failures=jnp.sum(alive & (result != optx.RESULTS.successful), dtype=jnp.int32),
        is_failures=jnp.sum(alive & ~converged, dtype=jnp.int32),
        # The ESS of a visibility-ignored step is that of an estimate the step did not use.
        min_ess=jnp.where(visibility_ignored | ~jnp.any(alive), jnp.nan, jnp.min(jnp.where(alive, kept_ess, jnp.inf))),
        log_overflow=new_overflow(belief.smoothing.log, kept.log),
        object_overflow=_lacks_object_slots(belief, detections) if discovery else jnp.zeros((), bool),
        merged=num_merged,
        details=HybridDetails(stats, parent, result, kept_ess, num_smoothed),
    )
    return new_belief, info
