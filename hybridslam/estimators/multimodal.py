"""Multimodal (sum-mixture, non-Gaussian) semantic SLAM: Doherty's thesis Ch. 5, smoothed or filtered.

The thesis marginalizes each step's association out of the factor graph (Eq. 5.3-5.7) and keeps
the resulting *sum*-mixture factors (Eq. 5.11), weighted by association probabilities that are
estimated by Monte Carlo over pose samples with joint compatibility (Eq. 5.9-5.10); mm-iSAM then
solves the non-Gaussian factor graph with nonparametric belief propagation.

Representation (why a Gaussian sum, not evenly weighted kernels). The belief at step ``k`` is a
fixed-capacity mixture of ``K`` weighted joint Gaussians over
``[x_k, o_0, ..., o_{Nmax-1}]`` (object slots and their creation as in :mod:`hybridslam.discovery`),
each with its own association history ``β_1:k``, number of created objects and per-object class
posterior. Given the prior mixture ``Σ_i w_i N_i`` and the step's sum-mixture factor
``f = Σ_j p_j ρ_j`` (Eq. 5.11), the posterior is exactly ``Σ_ij w_i p_j N_i ρ_j``: a child per
(component ``i``, joint assignment ``j``) with weight ``w_i p_j L_ij``, ``L_ij = ∫ N_i ρ_j``, and
Gaussian ``∝ N_i ρ_j`` found by Gauss-Newton (:func:`hybridslam.update.prior_gauss_newton`). A Gaussian
sum represents a mode with one component however unlikely it is, whereas evenly weighted kernels
(Fig. 5-2) or resampled particles (a Rao-Blackwellized particle filter) represent a mode of weight
``w`` by about ``w·K`` kernels, so a mode below ``1/K`` is lost by sampling noise alone — exactly the
late-mode failure Sec. 5.2.1 warns about. We keep the weights explicit instead.

Reduction without pruning. The children are reduced back to ``K`` by greedy moment-matching
merging (:func:`cluster`, :func:`spread`): the heaviest unclaimed child becomes a centre and claims every child within
a squared Mahalanobis distance ``merge_threshold`` that has the same number of created objects;
``K`` rounds; children left over are merged into their nearest centre. No mass is ever dropped
there, and separated modes stay separate components as long as there are at most ``K`` of them.
A child more than ``RELEVANT_NATS`` (30 nats: relative weight below 1e-13) under the best child
becomes no centre: its mass joins its nearest centre, so the belief carries no component it could
not show.
Only the ``children`` best children (a static count, ranked by the linearized likelihood below,
each named object's in-view probability included) get a Gauss-Newton update and a Monte Carlo
weight: the linearized mass of the rest is reported in ``StepInfo.dropped_mass`` and as a warning,
never silently.

Association probabilities (Eq. 5.9-5.10). ``L_ij`` integrates the joint likelihood of the step's
detections over the pose and the associated objects, ``y = [x_k, o_{d_1}, ...]``, by Monte Carlo:
``L_ij ≈ mean_s N_i(y_s) Π_k p(z_k | y_s, d_k) / q(y_s)`` with reparameterized standard-normal
draws, the same for every child (common random numbers make the children comparable). Joint
compatibility: every detection of an assignment is scored on the *same* sample. A detection of an
object scores the range-bearing density, the object observation model (0/1 footprint) and the
semantic term marginalized over the object's class posterior, ``Σ_c P(z^s | c, viewpoint)
p(c | Z^-)`` (the bracket of Eq. 5.10; the viewpoint comes from the sample, so viewpoint-dependent
classifiers are handled exactly). A "new object" choice scores ``new_object_log_density`` (the null
hypothesis of Sec. 3.2.1) times the semantic term under a uniform class prior, the new object's
unobserved orientation drawn from ``N(0, new_object_orientation_var)``; with the component's object
slots all used it is an *unmapped* object (object ``-1``: weighed the same, not stored, counted in
``StepInfo.unmapped``). ``p_j`` (Eq. 5.9) is the
total mass ``Σ w_i L_ij`` of the children that name the same object tuple, normalized over the
updated children (with one component and every assignment updated: ``L_j / Σ L``).

The proposal ``q`` (option ``proposal``): ``"prior"`` samples the component's marginal over ``y``,
which is Eq. 5.10 as written (pose and landmark samples from the belief). Its variance explodes
when the measurement is much sharper than the prior — a loop closure after drift, or any broad
prior (a 2 m prior against a 0.1 m measurement leaves ~1 useful sample in 400). The default
``"posterior"`` samples the child's Gauss-Newton (Laplace) posterior instead and importance-weights
by ``N_i / q``: the same integral, with weights that stay nearly equal. The tests check it against
brute-force quadrature.

Eq. 5.9 uses the step's detections to compute ``p_j``, and the factor of Eq. 5.11 multiplies the
likelihood ``ρ_j`` once more: the thesis's factor counts the detections twice, which sharpens the
association weights (``association_prior="mc"``, the default, follows the thesis). With
``association_prior="uniform"`` the children are weighted ``w_i L_ij``, the exact Bayes posterior
under a uniform prior over joint assignments.

Gating (Sec. 3.2.1): each detection considers the ``candidates`` created objects nearest in the
linearized Mahalanobis distance of the component's mean, plus the null / new-object hypothesis;
joint assignments are injective tuples of those choices, ranked by their linearized likelihood
(joint innovation density at the mean). By default (``max_assignments``) they are built one
detection at a time by a beam search that scores each extension by its conditional density given
the detections already assigned (:mod:`hybridslam.inference.sequential`: the same joint density,
a 2×2 term per detection); ``max_assignments=None`` enumerates every tuple and scores each at once
(the reference).

Smoothing (``smoother=Full()``, the default, or ``Lag(L)``; :mod:`.smoothing`): the children are
clustered on their filter estimates (above), then each merged component's centre has its whole
trajectory and map (or its window) relinearized with every geometric factor of its association
history, and the component is its cluster moment-matched about the centre's smoothed estimate:
members keep their filter offsets from the centre and take the centre's smoothed covariance (they
are within ``merge_threshold`` of it and created the same objects). A component keeps its centre's
trajectory. This is the static-shape stand-in for mm-iSAM: a Gaussian sum of smoothed hypotheses
where mm-iSAM propagates nonparametric beliefs through one graph. ``K`` smoothings per step, not
one per child (2·K): the used centres form a prefix, and
:func:`~hybridslam.inference.batching.map_live` skips the rest.

The continuous update uses the geometric part only: the class-marginalized semantic factor is a
mixture over classes, not a Gaussian; it enters the weights (above) and each object's class
posterior, which is updated with ``P(z^s | c, viewpoint)`` at the child's posterior mean (new
objects: averaged over their sampled orientations). ``view`` reports per component the argmax class
of every object the component has associated, ``-1`` otherwise.

Settings (:class:`Multimodal`): ``candidates`` (3), ``children`` (``2·capacity``),
``merge_threshold`` (4.0, squared Mahalanobis distance over the whole state), ``association_prior``
(``"mc"`` or ``"uniform"``), ``proposal`` (``"posterior"`` or ``"prior"``), ``samples``
(draws per child, 256), ``clutter`` (``"file"``: the scenario's ``sensor.clutter_log_density``,
none without it).

Clutter (``clutter``, a known map only; on an unknown map the null choice is a new object, and
the file's clutter density is not used): without it every detection is of an object (the
thesis's model), and the null choice of a known map leaves a detection unassociated only where no
injective assignment names them all (ranked below every full assignment, counted in ``skipped``).
With a log density over [range, bearing] the null choice is a clutter detection scored like a new
object's (:func:`_null_log_likelihood`, that density for ``new_object_log_density``; the hybrid
belief's clutter hypothesis), weighed against the assignments by the same Monte Carlo integral,
and counted in ``rejected``: spurious detections (ghosts, a duplicate, one outside every object's
footprint) are explained instead of dragging the pose or emptying the step.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from functools import partial
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ..inference import discovery, gating, sequential
from ..inference.beam import beam_search
from ..inference.laplace import logsumexp_or_minus_inf
from ..inference.update import downdate, prior_gauss_newton_gain, support_of, wrap_angles
from ..io.scenario import Scenario
from ..models import geometry, motion
from ..models.classifier import ClassifierModel
from ..models.measurement import Detections, SensorModel, log_visibility, log_visibility_probability
from ..models.model import Model, model_from_scenario
from ..inference.batching import map_live, smoothing_chunk
from ..inference.ties import best_slot, rank_key
from . import novelty
from .base import (CLUTTER_FROM_FILE, AbstractEstimator, Mixture, StepInfo, check_clutter, detection_slots,
                   history_length, lacks_object_slots, object_slots, relevant_children, resolve_clutter)
from .options import GATE, MAX_CHILDREN, Option, setting
from .smoothing import (DataLog, Filter, Full, Lag, Smoother, WindowPrior, data_log, factor_budget,
                        history_factors, initial_trajectory, initial_window, new_overflow, smooth_step)

NAME = "multimodal"

DEFAULT_SAMPLES = 256
DEFAULT_CANDIDATES = 3
DEFAULT_MERGE_THRESHOLD = 4.0
ASSOCIATION_PRIORS = ("mc", "uniform")
PROPOSALS = ("posterior", "prior")
# jaxlib 0.10.2 on CPU splits a large batched LAPACK call (Cholesky, triangular solve, QR) across
# XLA's intra-op thread pool and blocks a pool thread waiting for it; two such calls running at once
# on a small pool deadlock (seen here: 128 Cholesky factors of 21×21 on 2 cores). Batches of D×D
# work therefore go through lax.map in chunks this small (16 factors of 93×93 were still safe).
LAPACK_CHUNK = 16
SMALL_LAPACK_BATCH = 256  # the same for the 2×2 … 12×12 matrices of gating, screening and sampling


def _chunked(fn, *args, batch_size: int = LAPACK_CHUNK):
    """``jax.vmap(fn)(*args)`` evaluated ``batch_size`` rows at a time (see ``LAPACK_CHUNK``)."""
    return jax.lax.map(lambda a: fn(*a), args, batch_size=batch_size)


@dataclasses.dataclass(frozen=True)
class Structure:
    """What the :class:`Multimodal` settings and the scenario fix about a state (static: each fixes a
    shape or a code path), resolved once by :meth:`Multimodal.init`."""

    capacity: int  # K components
    max_objects: int  # Nmax object slots
    max_detections: int  # Dmax detection slots per step
    max_steps: int  # T, length of the association history
    num_samples: int  # S Monte Carlo draws per component (Eq. 5.10)
    candidates: int  # G gated objects per detection (plus the null hypothesis)
    children: int  # C children that get a Gauss-Newton update
    gn_max_steps: int
    discovery: bool  # whether the null / new-object hypothesis exists
    association_prior: str  # "mc" (thesis Eq. 5.11) or "uniform"
    proposal: str  # "posterior" (importance sampling) or "prior" (Eq. 5.10 as written)
    beam: int | None = None  # joint assignments kept per component while they are built (None: all)
    clutter: bool = False  # a known map's null choice is a clutter detection (scored), not a skip
    mahalanobis_new: bool = False  # new_landmark="mahalanobis:TAU" (Params.new_landmark_tau; .novelty)


class Params(eqx.Module):
    """Traced parameters: changing them never recompiles."""

    new_object_log_density: Float[Array, ""]
    orientation_var: Float[Array, ""]
    merge_threshold: Float[Array, ""]
    clutter_log_density: Float[Array, ""]  # used where Structure.clutter
    new_landmark_tau: Float[Array, ""]  # τ of new_landmark="mahalanobis:TAU" (inf under "density")


class State(eqx.Module):
    """The mixture of joint Gaussians over ``[x_k, o_0..o_{Nmax-1}]`` (see the module docstring)."""

    log_weights: Float[Array, " K"]  # -inf marks an empty slot
    mean: Float[Array, "K D"]
    cov: Float[Array, "K D D"]
    class_log_probs: Float[Array, "K Nmax M"]  # log p(c_n | Z), normalized per object
    observed: Bool[Array, "K Nmax"]  # associated at least once in this component
    num_created: Int[Array, " K"]  # object slots in use (prior objects included)
    history: Int[Array, "K T Dmax"]
    k: Int[Array, ""]
    model: Model
    params: Params
    config: Structure = eqx.field(static=True)
    # Smoothing (smoother=Full() or Lag(L)): each component's trajectory x_0..x_T, the data so far,
    # and with Lag(L) each component's window prior on [x_s, objects].
    poses: Float[Array, "K T1 3"] | None = None
    log: DataLog | None = None
    window: WindowPrior | None = None


class Details(eqx.Module):
    """The multimodal estimator's own diagnostics of one step (``StepInfo.details``), over the ``C``
    children that were updated."""

    parent: Int[Array, " C"]  # the component each child came from
    assoc_objects: Int[Array, "C Dmax"]  # object of each detection; -1 for an empty slot
    assoc_log_probs: Float[Array, " C"]  # log p_j of Eq. 5.9 for that object tuple; -inf infeasible


# --------------------------------------------------------------------------- #
# Joint assignments and gating
# --------------------------------------------------------------------------- #


def gate(d2: Float[Array, "Dmax Nmax"], num_created: Int[Array, ""], candidates: int) -> Int[Array, "Dmax G"]:
    """The ``G`` created objects nearest each detection in Mahalanobis distance (gating, Sec. 3.2.1,
    :func:`hybridslam.gating.nearest`); ranks with no created object left hold ``-1``."""
    ids, d2_ids = gating.nearest(d2, num_created, candidates)
    return jnp.where(d2_ids < jnp.inf, ids, -1)


def assignment_objects(
    choices: Int[Array, "A Dmax"],
    cand: Int[Array, "Dmax G"],
    mask: Bool[Array, " Dmax"],
    num_created: Int[Array, ""],
    n_max: int,
    allow_new: bool,
) -> tuple[Int[Array, "A Dmax"], Bool[Array, "A Dmax"], Bool[Array, " A"]]:
    """Object of every detection under every joint assignment, which detections are new objects,
    and which assignments are joint-compatible (injective).

    Several "new" detections create their own slots in slot order: ``num_created, num_created+1, ...``;
    those beyond the ``n_max`` slots are *unmapped* (object ``-1``, ``new`` set): scored as new
    objects, not stored, counted in ``StepInfo.unmapped`` (as the hybrid belief does).
    Without ``allow_new`` (a known map) the null choice ``G`` leaves its detection unassociated
    (object ``-1``, no factor): :func:`skipped_detections` counts them, and only the assignments
    that skip the fewest are kept (:func:`hypotheses`).
    """
    g = cand.shape[1]
    slots = jnp.arange(mask.shape[0])
    known = (choices < g) & mask[None, :]
    new = (choices == g) & mask[None, :] & allow_new
    cand_id = cand[slots[None, :], jnp.minimum(choices, g - 1)]
    new_id = num_created + jnp.cumsum(new, axis=1) - 1
    objects = jnp.where(known, cand_id, jnp.where(new & (new_id < n_max), new_id, -1)).astype(jnp.int32)
    same = (objects[:, :, None] == objects[:, None, :]) & known[:, :, None] & known[:, None, :]
    distinct = ~jnp.any(same & ~jnp.eye(mask.shape[0], dtype=bool)[None], axis=(1, 2))
    padded_ok = jnp.all(mask[None, :] | (choices == g), axis=1)
    feasible = distinct & padded_ok & ~jnp.any(known & (cand_id < 0), axis=1)
    return objects, new, feasible


def skipped_detections(choices: Int[Array, "A Dmax"], mask: Bool[Array, " Dmax"], g: int,
                       allow_new: bool) -> Int[Array, " A"]:
    """Detections a joint assignment leaves unassociated (the null choice on a known map)."""
    if allow_new:
        return jnp.zeros(choices.shape[:1], jnp.int32)
    return jnp.sum((choices == g) & mask[None, :], axis=1, dtype=jnp.int32)


# --------------------------------------------------------------------------- #
# Likelihoods of a joint assignment (Eq. 5.9-5.10)
# --------------------------------------------------------------------------- #


def class_log_likelihoods(
    classifier: ClassifierModel, scores: Float[Array, " M"], viewpoint: Float[Array, "2"]
) -> Float[Array, " M"]:
    """``log P(z^s | c, viewpoint)`` for every class ``c`` (Eq. 2; thesis Eq. 2.14 for confusion)."""
    r, log_norm = classifier.residuals(scores, viewpoint)
    return log_norm - 0.5 * jnp.sum(r**2, axis=-1)


def semantic_log_marginal(
    classifier: ClassifierModel, scores: Float[Array, " M"], viewpoint: Float[Array, "2"],
    class_log_probs: Float[Array, " M"],
) -> Float[Array, ""]:
    """``log Σ_c P(z^s | c, viewpoint) p(c | Z^-)``: the semantic bracket of Eq. 5.10."""
    return jax.nn.logsumexp(class_log_likelihoods(classifier, scores, viewpoint) + class_log_probs)


def _new_object(x: Float[Array, "3"], geo: Float[Array, "2"], theta: Float[Array, ""]) -> Float[Array, "3"]:
    return jnp.concatenate([discovery.back_project(x, geo), theta[None]])


def _uniform(m: int) -> Float[Array, " M"]:
    return jnp.full((m,), -math.log(m))


def _known_semantic(sensor: SensorModel, x: Float[Array, "3"], obj: Float[Array, "3"], scores: Float[Array, " M"],
                    class_log_probs: Float[Array, " M"]) -> Float[Array, ""]:
    """The semantic term of a detection of a created object seen from ``x`` (Eq. 5.10's bracket)."""
    return semantic_log_marginal(sensor.classifier, scores, geometry.viewpoint(x, obj), class_log_probs)


def _null_log_likelihood(sensor: SensorModel, log_density: Float[Array, ""], x: Float[Array, "3"],
                         geo: Float[Array, "2"], scores: Float[Array, " M"], theta: Float[Array, ""]) -> Float[Array, ""]:
    """A detection of no known object: ``log_density`` over [range, bearing] times the semantic term
    under a uniform class prior, seen from an object back-projected with heading ``theta``. A new
    object (the null hypothesis, Sec. 3.2.1) with ``new_object_log_density``; clutter on a known map
    with ``clutter_log_density`` (as the hybrid belief's clutter hypothesis)."""
    obj = _new_object(x, geo, theta)
    return log_density + _known_semantic(sensor, x, obj, scores, _uniform(sensor.classifier.num_classes))


def joint_log_likelihood(
    sensor: SensorModel,
    params: Params,
    x: Float[Array, "3"],
    slot_objects: Float[Array, "Dmax 3"],
    known: Bool[Array, " Dmax"],
    new: Bool[Array, " Dmax"],
    slot_class_log_probs: Float[Array, "Dmax M"],
    detections: Detections,
    theta: Float[Array, " Dmax"],
    clutter: Bool[Array, " Dmax"] | None = None,
) -> Float[Array, ""]:
    """``log Π_k p(z_k | x, objects, d_k)`` of one joint assignment at one sample (Eq. 5.10's integrand).

    A detection of an object: range-bearing density, object observation model (footprint) and the
    class-marginal semantic term. A new object (the null hypothesis, Sec. 3.2.1):
    ``new_object_log_density`` and the semantic term under a uniform class prior, seen from an object
    back-projected from the detection with orientation ``theta``. A ``clutter`` slot (a known map
    with a clutter hypothesis): the same with ``clutter_log_density``.
    """
    w, geo_norm = sensor.geometric_sqrt_information()

    def of_object(obj, geo, scores, class_lp):
        r = w @ geometry.geometric_residual(geo, geometry.range_bearing(x, obj))
        return geo_norm - 0.5 * r @ r + log_visibility(sensor, x, obj) + _known_semantic(sensor, x, obj, scores, class_lp)

    per_obj = jax.vmap(of_object)(slot_objects, detections.geo, detections.scores, slot_class_log_probs)
    null, density = new, jnp.full(new.shape, params.new_object_log_density)
    if clutter is not None:  # a known map: no slot is new, a null slot is clutter
        null, density = new | clutter, jnp.where(new, density, params.clutter_log_density)
    per_null = jax.vmap(partial(_null_log_likelihood, sensor), (0, None, 0, 0, 0))(
        density, x, detections.geo, detections.scores, theta)
    return jnp.sum(jnp.where(known, per_obj, 0.0)) + jnp.sum(jnp.where(null, per_null, 0.0))


def _sub_indices(objects: Int[Array, " Dmax"], known: Bool[Array, " Dmax"]) -> tuple[Int[Array, " P"], Bool[Array, " P"]]:
    """State indices of ``[x_k, o_{d_1}, ..., o_{d_Dmax}]`` (``P = 3 + 3 Dmax``) and which are placeholders
    (slots not associated with a created object)."""
    obj_idx = 3 + 3 * jnp.maximum(objects, 0)[:, None] + jnp.arange(3)[None, :]
    idx = jnp.concatenate([jnp.arange(3), obj_idx.reshape(-1)])
    dummy = jnp.concatenate([jnp.zeros(3, bool), jnp.repeat(~known, 3)])
    return idx, dummy


def sub_gaussian(
    mean: Float[Array, " D"], cov: Float[Array, "D D"], idx: Int[Array, " P"], dummy: Bool[Array, " P"]
) -> tuple[Float[Array, " P"], Float[Array, "P P"]]:
    """The marginal over ``[x_k, associated objects]``; placeholder entries are ``N(0, 1)`` and
    uncorrelated, so they cancel between any two such Gaussians."""
    return _placeholders(mean[idx], cov[idx][:, idx], dummy)


def _placeholders(mean: Float[Array, " P"], cov: Float[Array, "P P"], dummy: Bool[Array, " P"]):
    m = jnp.where(dummy, 0.0, mean)
    c = jnp.where(dummy[:, None] | dummy[None, :], 0.0, cov)
    return m, c + jnp.diag(dummy.astype(c.dtype))


def screen_log_likelihood(
    sensor: SensorModel,
    params: Params,
    pred: gating.Innovations,
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    class_log_probs: Float[Array, "Nmax M"],
    objects: Int[Array, " Dmax"],
    new: Bool[Array, " Dmax"],
    detections: Detections,
    clutter: Bool[Array, " Dmax"] | None = None,
) -> Float[Array, ""]:
    """Linearized ``log L_ij``: the joint innovation density ``N(r; 0, H Σ Hᵀ + Σ_v)`` of the detections
    of created objects, plus the semantic and null terms at the mean and each created object's
    in-view probability (:func:`_log_in_view`). Used only to pick which children get a Gauss-Newton
    update and an importance-sampled weight."""
    known = (objects >= 0) & ~new
    idx, dummy = _sub_indices(objects, known)
    _, sub_cov = sub_gaussian(mean, cov, idx, dummy)
    slots = jnp.arange(objects.shape[0])
    obj = jnp.maximum(objects, 0)
    r = jnp.where(known[:, None], pred.residual[slots, obj], 0.0).reshape(-1)
    jac = jnp.concatenate([pred.jac_pose[obj], pred.jac_object[obj]], axis=-1)  # (Dmax, 2, 6): ∂h/∂(x_k, o)
    j = jnp.where(known[:, None, None], jac, 0.0)
    h = jnp.zeros((objects.shape[0], 2, sub_cov.shape[0]), cov.dtype)
    h = h.at[:, :, :3].set(j[:, :, :3])
    h = jax.vmap(lambda hk, jk, k: jax.lax.dynamic_update_slice(hk, jk[:, 3:], (0, 3 + 3 * k)))(h, j, slots)
    h = h.reshape(-1, sub_cov.shape[0])
    s = h @ sub_cov @ h.T + jnp.kron(jnp.eye(objects.shape[0], dtype=cov.dtype), sensor.geometric_cov)
    chol = jnp.linalg.cholesky(s)
    u = jsl.solve_triangular(chol, r, lower=True)
    _, geo_norm = sensor.geometric_sqrt_information()
    # Unassociated slots are rows with r = 0 and covariance Σ_v: remove their normalizer.
    geo = -0.5 * u @ u - jnp.sum(jnp.log(jnp.diagonal(chol))) - objects.shape[0] * math.log(2 * math.pi)
    geo = geo - geo_norm * jnp.sum(~known)
    theta = jnp.zeros(objects.shape, cov.dtype)
    x, objs = mean[:3], mean[3:].reshape(-1, 3)
    rest = joint_log_likelihood(sensor, params, x, objs[obj], jnp.zeros_like(known), new,
                                class_log_probs[obj], detections, theta, clutter)
    known_sem = jax.vmap(partial(_known_semantic, sensor, x))(objs[obj], detections.scores, class_log_probs[obj])
    known_sem = known_sem + _log_in_view(sensor, pred, x, objs, obj)
    return geo + rest + jnp.sum(jnp.where(known, known_sem, 0.0))


def _log_in_view(sensor: SensorModel, pred: gating.Innovations, x: Float[Array, "3"], objs: Float[Array, "N 3"],
                 ids: Int[Array, "*B"]) -> Float[Array, "*B"]:
    """``log P(object ids[...] in view)`` under the linearized predictive of its range and bearing
    (:func:`~hybridslam.models.measurement.log_visibility_probability`; ``H P Hᵀ`` is the innovation
    covariance without the sensor noise). The screen's stand-in for the footprint factor that the
    sampled weights (Eq. 5.10) apply at every draw: without it the screen keeps children whose
    objects are out of view, and every one of them then weighs zero."""
    flat = ids.reshape(-1)
    rb = jax.vmap(geometry.range_bearing, (None, 0))(x, objs[flat])
    var = jnp.maximum(jnp.diagonal(pred.cov[flat] - sensor.geometric_cov[None], axis1=-2, axis2=-1), 0.0)
    return jax.vmap(log_visibility_probability, (None, 0, 0))(sensor, rb, var).reshape(ids.shape)


class SlotTerms(eqx.Module):
    """One component's screening inputs, computed once: the linearized predictions, the covariance,
    the gated candidates and the non-Gaussian terms of every (detection, candidate) and "new" choice."""

    pred: gating.Innovations
    cov: Float[Array, "D D"]
    cand: Int[Array, "Dmax G"]
    known: Float[Array, "Dmax G"]  # semantic and in-view terms of a detection of each candidate, at the mean
    new: Float[Array, " Dmax"]  # null-hypothesis term of each detection (new object or clutter), at the mean (theta = 0)


def slot_terms(sensor: SensorModel, params: Params, pred: gating.Innovations, mean: Float[Array, " D"],
               cov: Float[Array, "D D"], class_log_probs: Float[Array, "Nmax M"], cand: Int[Array, "Dmax G"],
               detections: Detections, clutter: bool = False) -> SlotTerms:
    """The :class:`SlotTerms` of one component (the per-detection terms of :func:`screen_log_likelihood`);
    with ``clutter`` the null term is the clutter hypothesis's (a known map)."""
    x, objs = mean[:3], mean[3:].reshape(-1, 3)
    cid = jnp.maximum(cand, 0)
    per_candidate = jax.vmap(partial(_known_semantic, sensor, x), (0, None, 0))
    known = jax.vmap(per_candidate)(objs[cid], detections.scores, class_log_probs[cid])
    known = known + _log_in_view(sensor, pred, x, objs, cid)
    density = params.clutter_log_density if clutter else params.new_object_log_density
    new = jax.vmap(partial(_null_log_likelihood, sensor, density, x))(
        detections.geo, detections.scores, jnp.zeros(detections.mask.shape, mean.dtype))
    return SlotTerms(pred, cov, cand, known, new)


def localized_terms(terms: SlotTerms) -> SlotTerms:
    """``terms`` over the step's candidates only: the state ``[x_k, o_{cand[0,0]}, ..., o_{cand[Dmax-1,G-1]}]``
    (``3 + 3·Dmax·G`` entries, candidates repeated as often as they are named) instead of the whole map.

    The beam's conditioning (:mod:`hybridslam.inference.sequential`) keeps a ``D × 2Dmax`` low-rank
    factor per partial assignment and reads only the rows of the pose and the candidates; every
    update is linear in the covariance, so on a selection ``P Σ Pᵀ`` of its rows and columns (with
    repeats) it gives the selected rows of the full update, the same densities to rounding. On the
    hallway (``D`` = 213, 4 detections, 3 candidates) that is 39 rows instead of 213. Candidate
    ``(j, g)`` becomes local object ``j·G + g`` (``-1`` stays ``-1``).
    """
    dmax, g = terms.cand.shape
    support = jnp.maximum(terms.cand, 0).reshape(-1)  # (Dmax·G,) global objects
    rows = jnp.concatenate([jnp.arange(3), (3 + 3 * support[:, None] + jnp.arange(3)[None, :]).reshape(-1)])
    pred = terms.pred
    local = gating.Innovations(pred.residual[:, support], pred.jac_pose[support], pred.jac_object[support],
                               pred.d2[:, support], pred.cov[support])
    cand = jnp.where(terms.cand >= 0, jnp.arange(dmax * g).reshape(dmax, g), -1)
    return SlotTerms(local, terms.cov[rows][:, rows], cand, terms.known, terms.new)


def slot_log_likelihood(terms: SlotTerms, row: sequential.Conditioned, j: Int[Array, ""], choice: Int[Array, ""],
                        obj: Int[Array, ""], is_new: Bool[Array, ""],
                        is_clutter: Bool[Array, ""] | bool = False) -> Float[Array, ""]:
    """Detection ``j``'s factor of the linearized ``log L_ij`` given the earlier slots of ``row``
    (:mod:`hybridslam.inference.sequential`): the conditional innovation density and semantic term
    of a created object, the null-hypothesis term of a new one or of clutter (``is_clutter``), 0 for
    an empty or skipped slot. Summed over the slots this is :func:`screen_log_likelihood`."""
    g = terms.cand.shape[1]
    # The candidate's own index into terms.pred (obj itself, or its local index: localized_terms).
    gauss = sequential.innovation_log_density(terms.pred, row, j, terms.cand[j, jnp.minimum(choice, g - 1)])
    known = (obj >= 0) & ~is_new
    null = is_new | is_clutter
    return jnp.where(known, gauss + terms.known[j, jnp.minimum(choice, g - 1)], jnp.where(null, terms.new[j], 0.0))


def condition(terms: SlotTerms, mask: Bool[Array, " Dmax"], row: sequential.Conditioned, options: Int[Array, " Dmax"],
              j: Int[Array, ""]) -> sequential.Conditioned:
    """``row`` extended by detection ``j`` (choice ``options[j]``)."""
    g = terms.cand.shape[1]
    choice = options[j]
    obj = terms.cand[j, jnp.minimum(choice, g - 1)]
    return sequential.condition(terms.pred, terms.cov, row, j, obj, mask[j] & (choice < g) & (obj >= 0))


def sampled_log_likelihood(
    sensor: SensorModel,
    params: Params,
    prior: tuple[Float[Array, " P"], Float[Array, "P P"]],
    proposal: tuple[Float[Array, " P"], Float[Array, "P P"]],
    class_log_probs: Float[Array, "Dmax M"],
    objects: Int[Array, " Dmax"],
    new: Bool[Array, " Dmax"],
    detections: Detections,
    eps: Float[Array, "S P"],
    theta: Float[Array, "S Dmax"],
    clutter: Bool[Array, " Dmax"] | None = None,
) -> Float[Array, ""]:
    """Monte Carlo ``log L_ij = log ∫ N_i(y) Π_k p(z_k | y, d_k) dy`` over ``y = [x_k, associated objects]``
    (Eq. 5.10, joint compatibility: every detection is scored on the same sample).

    Samples ``y_s = μ_q + L_q ε_s`` from ``proposal`` ``q``, weighted by ``N_i(y_s) / q(y_s)``: with
    ``q`` the prior marginal this is Eq. 5.10 as written (pose and landmark samples from the belief);
    with ``q`` the child's Laplace posterior it is the same integral by importance sampling, whose
    variance stays small when the measurement is much sharper than the prior (a loop closure).
    """
    known = (objects >= 0) & ~new
    (mu_p, cov_p), (mu_q, cov_q) = prior, proposal
    chol_p, chol_q = jnp.linalg.cholesky(cov_p), jnp.linalg.cholesky(cov_q)
    y = mu_q[None, :] + eps @ chol_q.T
    _, dummy = _sub_indices(objects, known)
    # Placeholder entries are N(0, 1) in both densities; wrapping them as headings would break that.
    diff = y - mu_p[None, :]
    diff = jnp.where(dummy[None, :], diff, jax.vmap(wrap_angles)(diff))
    u = jsl.solve_triangular(chol_p, diff.T, lower=True)
    log_ratio = (-0.5 * jnp.sum(u**2, axis=0) - jnp.sum(jnp.log(jnp.diagonal(chol_p)))
                 + 0.5 * jnp.sum(eps**2, axis=1) + jnp.sum(jnp.log(jnp.diagonal(chol_q))))

    def one(ys, th):
        return joint_log_likelihood(sensor, params, ys[:3], ys[3:].reshape(-1, 3), known, new,
                                    class_log_probs, detections, th, clutter)

    log_lik = jax.vmap(one)(y, theta)
    # -inf where no sample explains the detections (with a zero, not NaN, gradient).
    return logsumexp_or_minus_inf(log_lik + log_ratio) - math.log(eps.shape[0])


def draws(key: jax.Array, cfg: Structure, params: Params) -> tuple[Float[Array, "S P"], Float[Array, "S Dmax"]]:
    """Standard-normal draws for the joint samples, and new objects' orientations ``~ N(0, var)``
    (fixed by ``key``; shared by every child: common random numbers make their weights comparable)."""
    k_state, k_orient = jax.random.split(key)
    dtype = params.orientation_var.dtype
    eps = jax.random.normal(k_state, (cfg.num_samples, 3 + 3 * cfg.max_detections), dtype=dtype)
    theta = jax.random.normal(k_orient, (cfg.num_samples, cfg.max_detections), dtype=dtype)
    return eps, jnp.sqrt(params.orientation_var) * theta


def tuple_log_probs(objects: Int[Array, "C Dmax"], log_mass: Float[Array, " C"]) -> Float[Array, " C"]:
    """``log p_j`` (Eq. 5.9): each child's share of the total mass of the children naming its object tuple.

    Children of different components that associate the detections with the same objects are the
    same association hypothesis. ``-inf`` for children of zero mass. The tuples are compared row
    by row (``C²·Dmax`` comparisons for the few dozen children of a step), so no code of the tuple
    bounds the objects or detection slots.
    """
    same = jnp.all(objects[:, None, :] == objects[None, :, :], axis=-1)  # (C, C): the same object tuple
    shared = logsumexp_or_minus_inf(jnp.where(same, log_mass[None, :], -jnp.inf), axis=1)
    out = shared - jax.nn.logsumexp(log_mass)
    return jnp.where(log_mass > -jnp.inf, out, -jnp.inf)


# --------------------------------------------------------------------------- #
# Hypotheses: children of (component, joint assignment), weighted by Eq. 5.9-5.11
# --------------------------------------------------------------------------- #


class Children(eqx.Module):
    """The ``C`` children that get a Gauss-Newton update, with their weights."""

    parent: Int[Array, " C"]
    objects: Int[Array, "C Dmax"]  # object of each detection, -1 for an empty slot
    new: Bool[Array, "C Dmax"]  # which detections are new objects (stored where objects >= 0, else unmapped)
    mean: Float[Array, "C D"]  # Gauss-Newton posterior (before new objects are written)
    gain: Float[Array, "C D m"]  # its covariance is the parent's, downdated (update.downdate; not carried: C × D × D)
    gain_js: Float[Array, "C m D"]
    result: optx.RESULTS
    log_lik: Float[Array, " C"]  # Monte Carlo log L_ij (Eq. 5.10)
    log_prob: Float[Array, " C"]  # log p_j (Eq. 5.9)
    log_weight: Float[Array, " C"]  # log w_i + log L_ij (+ log p_j with association_prior="mc")
    dropped_mass: Float[Array, ""]  # linearized mass of the children not selected
    beam_dropped: Int[Array, ""]  # partial assignments the beam dropped near the best (0 if exhaustive)


def _residuals(y, args):
    sensor, objects, known, geo = args
    x, objs = y[:3], y[3:].reshape(-1, 3)
    w, _ = sensor.geometric_sqrt_information()

    def one(obj, z):
        return w @ geometry.geometric_residual(z, geometry.range_bearing(x, obj))

    meas = jax.vmap(one)(objs[jnp.maximum(objects, 0)], geo)
    return jnp.where(known[:, None], meas, 0.0).reshape(-1)


def gauss_newton_child(
    state: State, mean: Float[Array, " D"], cov: Float[Array, "D D"], objects: Int[Array, " Dmax"],
    new: Bool[Array, " Dmax"], detections: Detections,
) -> tuple[Float[Array, " D"], Float[Array, "D m"], Float[Array, "m D"], optx.RESULTS]:
    """The Gaussian ``∝ N_i ρ_j`` of one child: Gauss-Newton on the prior and the geometric factors of
    the detections associated with created objects (Eq. 5.11 times one component). Returns the mode
    and the gain ``K`` and ``JΣ`` of its covariance ``Σ − K (JΣ)`` (``m = 2 Dmax``)."""
    known = (objects >= 0) & ~new
    args = (state.model.sensor, objects, known, detections.geo)
    # Kalman form: O(D² m) per iterate, where a dense solve over the whole map would be O(D³).
    return prior_gauss_newton_gain(_residuals, mean, cov, args, state.config.gn_max_steps, support_of(objects))


def hypotheses(
    state: State, mean: Float[Array, "K D"], cov: Float[Array, "K D D"], detections: Detections, key: jax.Array
) -> Children:
    """Gate, enumerate joint assignments, screen them by linearized likelihood, update the ``C``
    best by Gauss-Newton and weigh them by Monte Carlo (Eq. 5.9-5.11). ``mean`` / ``cov`` are the
    components at the current pose (after propagation)."""
    cfg, sensor, params = state.config, state.model.sensor, state.params
    slots = jnp.arange(cfg.max_detections)
    # With a clutter hypothesis a known map's null choice is scored, not ranked as a skip.
    scored_null = cfg.discovery or cfg.clutter

    def clutter_slots(choices, mask):  # (A, Dmax): the known map's null choices, with a clutter hypothesis
        return (choices >= cfg.candidates) & mask[None, :] if cfg.clutter else None

    def per_component(m, c, class_lp, created):
        pred = gating.innovations(sensor, m, c, detections)
        cand = gate(pred.d2, created, cfg.candidates)
        near = jnp.zeros(cfg.max_detections, bool)  # a known object within τ: "new" breaks the rule (.novelty)
        if cfg.mahalanobis_new:
            cand, near = novelty.restrict(cand, pred.d2, params.new_landmark_tau)
        if cfg.beam is not None:  # built one detection at a time, the `beam` best kept (inference.beam), scored sequentially
            terms = slot_terms(sensor, params, pred, m, c, class_lp, cand, detections, cfg.clutter)
            if 3 + 3 * cand.size < m.shape[0]:  # static: the candidates' rows are fewer than the map's
                terms = localized_terms(terms)

            def score(opts, j, row, parent):
                mask = detections.mask & (slots <= j)
                objects, new, feasible = assignment_objects(opts[None], cand, mask, created, cfg.max_objects,
                                                            cfg.discovery)
                is_clutter = cfg.clutter & mask[j] & (opts[j] >= cfg.candidates)
                inc = slot_log_likelihood(terms, row, j, opts[j], objects[0, j], new[0, j], is_clutter)
                # Ranked by the detections left unassociated first (a known map's null choice).
                skips = skipped_detections(opts[None], mask, cfg.candidates, scored_null)[0] + jnp.sum(new[0] & near)
                return jnp.where(feasible[0], parent + inc, -jnp.inf), skips

            start = sequential.start(cfg.beam, terms.cov.shape[0], cfg.max_detections, m.dtype)
            found = beam_search(score, cfg.max_detections, cfg.candidates + 1, cfg.beam, fill=cfg.candidates,
                                carry=start, advance=partial(condition, terms, detections.mask))
            objects, new, feasible = assignment_objects(found.options, cand, detections.mask, created, cfg.max_objects,
                                                        cfg.discovery)
            # A row the beam did not fill is no hypothesis (it may repeat another).
            skips = skipped_detections(found.options, detections.mask, cfg.candidates, scored_null) + jnp.sum(
                new & near[None], axis=1)
            return objects, new, jnp.where(feasible & found.valid, found.score, -jnp.inf), skips, found.dropped
        # Every joint assignment, (G+1)^Dmax rows, each scored at once: the reference.
        choices = jnp.asarray(gating.joint_options(cfg.candidates, cfg.max_detections))
        objects, new, feasible = assignment_objects(choices, cand, detections.mask, created, cfg.max_objects, cfg.discovery)
        clutter = clutter_slots(choices, detections.mask)
        screen = jax.vmap(partial(screen_log_likelihood, sensor, params, pred, m, c, class_lp), (0, 0, None, 0))(
            objects, new, detections, clutter)
        skips = skipped_detections(choices, detections.mask, cfg.candidates, scored_null) + jnp.sum(
            new & near[None], axis=1)
        return objects, new, jnp.where(feasible, screen, -jnp.inf), skips, jnp.zeros((), jnp.int32)

    rows = (cfg.candidates + 1) ** cfg.max_detections if cfg.beam is None else cfg.beam
    per_batch = max(1, SMALL_LAPACK_BATCH // (rows * cfg.max_detections))
    # Dead components (weight -inf; a suffix after every merge) are skipped: their rows stay zero,
    # and their screening weights -inf through ``state.log_weights`` below.
    alive = state.log_weights > -jnp.inf
    objects, new, screen, skips, beam_dropped = map_live(per_component, alive, mean, cov, state.class_log_probs,
                                                         state.num_created, chunk=per_batch)
    # Only the joint assignments that leave the fewest detections unassociated (a known map's step
    # that no injective assignment explains whole; elsewhere every kept one skips none).
    usable = alive[:, None] & (screen > -jnp.inf)
    screen = jnp.where(skips == jnp.min(jnp.where(usable, skips, jnp.iinfo(jnp.int32).max)), screen, -jnp.inf)
    num_assign = rows
    screen_w = (state.log_weights[:, None] + screen).reshape(-1)
    # Ranked by the tie-proof key: of children whose screens tie, the lower index (inference.ties).
    _, sel = jax.lax.top_k(rank_key(screen_w), cfg.children)
    sel_w = screen_w[sel]
    parent, a = sel // num_assign, sel % num_assign
    objects, new = objects[parent, a], new[parent, a]
    # One child at a time: a batch's fixed-point loop runs until its slowest member has converged
    # (hallway: 112 against 117 ms per step with batches of 16; MRCLAM: the same). Each child reads
    # its parent's covariance in place and gives back the rank-m downdate of it (update.downdate): C
    # gathered copies of D×D matrices in and out of the loop cost more than the updates.
    post_mean, gain, gain_js, result = _chunked(
        lambda i, o, n: gauss_newton_child(state, mean[i], cov[i], o, n, detections), parent, objects, new,
        batch_size=1)

    eps, theta = draws(key, cfg, params)

    def weigh(i, qm, k, js, class_lp, obj, nw):
        idx, dummy = _sub_indices(obj, (obj >= 0) & ~nw)
        prior = sub_gaussian(mean[i], cov[i], idx, dummy)
        proposal = (_placeholders(qm[idx], downdate(cov[i], k, js, idx), dummy) if cfg.proposal == "posterior"
                    else prior)
        clutter = detections.mask & (obj < 0) if cfg.clutter else None
        return sampled_log_likelihood(sensor, params, prior, proposal, class_lp[jnp.maximum(obj, 0)], obj, nw,
                                      detections, eps, theta, clutter)

    # A child of weight -inf (top_k's filler) is weighed as associating nothing, on its parent's
    # Gaussian: its weight is -inf either way, but a NaN in its likelihood, masked by the where below,
    # made every reverse-mode gradient NaN (the double where).
    valid = sel_w > -jnp.inf
    log_lik = _chunked(weigh, parent, jnp.where(valid[:, None], post_mean, mean[parent]),
                       jnp.where(valid[:, None, None], gain, 0.0),
                       jnp.where(valid[:, None, None], gain_js, 0.0),
                       state.class_log_probs[parent], jnp.where(valid[:, None], objects, -1),
                       valid[:, None] & new)
    log_lik = jnp.where(valid, log_lik, -jnp.inf)
    log_mass = state.log_weights[parent] + log_lik
    log_prob = tuple_log_probs(objects, log_mass)
    log_weight = log_mass + log_prob if cfg.association_prior == "mc" else log_mass
    dropped = jnp.maximum(-jnp.expm1(jax.nn.logsumexp(sel_w) - jax.nn.logsumexp(screen_w)), 0.0)
    return Children(parent, objects, new, post_mean, gain, gain_js, result, log_lik, log_prob, log_weight, dropped,
                    jnp.sum(jnp.where(alive, beam_dropped, 0), dtype=jnp.int32))


@jax.jit
def association_log_probabilities(state: State, detections: Detections, key: jax.Array) -> Children:
    """The weighed hypotheses of ``detections`` taken at the state's current pose (no propagation)."""
    return hypotheses(state, state.mean, state.cov, detections, key)


# --------------------------------------------------------------------------- #
# Finishing a child: new objects (Sec. 3.2.1) and class posteriors
# --------------------------------------------------------------------------- #


def _class_update(sensor, mean, class_log_probs, observed, objects, new, detections, theta):
    """Bayes' rule on each associated object's class (the semantic term of Eq. 5.10; thesis Eq. 4.17).

    A new object's class starts uniform; its orientation is unobserved, so its evidence averages the
    classifier over the sampled orientations.
    """
    x, objs = mean[:3], mean[3:].reshape(-1, 3)
    n_max, m = class_log_probs.shape
    at_mean = jax.vmap(lambda o, s: class_log_likelihoods(sensor.classifier, s, geometry.viewpoint(x, o)))(
        objs[jnp.maximum(objects, 0)], detections.scores)

    def averaged(geo, scores, th):  # th: (S,)
        obj = jax.vmap(lambda t: _new_object(x, geo, t))(th)
        ll = jax.vmap(lambda o: class_log_likelihoods(sensor.classifier, scores, geometry.viewpoint(x, o)))(obj)
        return jax.nn.logsumexp(ll, axis=0) - math.log(th.shape[0])

    over_orient = jax.vmap(averaged)(detections.geo, detections.scores, theta.T)
    evidence = jnp.where(new[:, None], over_orient, at_mean)  # (Dmax, M)
    hit = (objects[:, None] == jnp.arange(n_max)[None, :]) & (objects[:, None] >= 0)  # (Dmax, Nmax)
    fresh = jnp.any(hit & new[:, None], axis=0)
    prior = jnp.where(fresh[:, None], -math.log(m), class_log_probs)
    post = prior + jnp.sum(jnp.where(hit[:, :, None], evidence[:, None, :], 0.0), axis=0)
    return jax.nn.log_softmax(post, axis=-1), observed | jnp.any(hit, axis=0)


def finish_child(
    state: State, mean: Float[Array, " D"], cov: Float[Array, "D D"], class_log_probs: Float[Array, "Nmax M"],
    observed: Bool[Array, " Nmax"], num_created: Int[Array, ""], objects: Int[Array, " Dmax"],
    new: Bool[Array, " Dmax"], detections: Detections, theta: Float[Array, "S Dmax"],
):
    """Write the child's new objects into their slots (its unmapped ones, object -1, nowhere) and update
    its class posteriors."""
    sensor = state.model.sensor
    stored = new & (objects >= 0)
    mean, cov = discovery.create_objects(mean, cov, objects, stored, detections.geo, sensor.geometric_cov,
                                         state.params.orientation_var)
    class_log_probs, observed = _class_update(sensor, mean, class_log_probs, observed, objects, new, detections, theta)
    return mean, cov, class_log_probs, observed, (num_created + jnp.sum(stored)).astype(num_created.dtype)


# --------------------------------------------------------------------------- #
# Reduction: greedy moment-matching merging (no mode is dropped)
# --------------------------------------------------------------------------- #


def _mahalanobis2(chol: Float[Array, "D D"], centre: Float[Array, " D"], means: Float[Array, "C D"]) -> Float[Array, " C"]:
    diff = jax.vmap(wrap_angles)(means - centre[None, :])
    z = jsl.solve_triangular(chol, diff.T, lower=True)
    return jnp.sum(z**2, axis=0)


def cluster(
    log_w: Float[Array, " C"],
    mean: Float[Array, "C D"],
    cov: Float[Array, "C D D"],
    num_created: Int[Array, " C"],
    threshold: Float[Array, ""],
    capacity: int,
    centre_ok: Bool[Array, " C"] | None = None,
) -> tuple[Int[Array, " K"], Float[Array, " K"], Float[Array, "K C"]]:
    """:func:`clustered` with every child's covariance given."""
    centres, log_weights, wn, _ = clustered(log_w, mean, lambda c: cov[c], cov[:, :3, :3], num_created, threshold,
                                            capacity, centre_ok)
    return centres, log_weights, wn


def clustered(
    log_w: Float[Array, " C"],
    mean: Float[Array, "C D"],
    cov_of: Callable[[Int[Array, ""]], Float[Array, "D D"]],
    pose_cov: Float[Array, "C 3 3"],
    num_created: Int[Array, " C"],
    threshold: Float[Array, ""],
    capacity: int,
    centre_ok: Bool[Array, " C"] | None = None,
) -> tuple[Int[Array, " K"], Float[Array, " K"], Float[Array, "K C"], Float[Array, "K D D"]]:
    """Group ``C`` weighted Gaussians into ``K`` clusters without dropping mass (the merge's first half).

    ``K`` rounds: the heaviest unclaimed child among ``centre_ok`` (default: every live child)
    becomes a centre and claims every unclaimed child with the same number of created objects within
    squared Mahalanobis distance ``threshold`` (centre's metric). Leftovers join the nearest centre:
    moment-matched when their object slots are comparable (same number created), by weight only
    otherwise. Returns the centres (the used ones first), merged log weights (``-inf`` for unused
    slots), the normalized moment weights ``(K, C)`` (zero for a member joined by weight only) and
    the centres' covariances. ``cov_of(c)``: child ``c``'s covariance (only the ``K`` centres' are
    asked for: the children's need not exist as a ``C × D × D`` array); ``pose_cov``: every child's
    pose block.
    """
    live = log_w > -jnp.inf
    centre_ok = live if centre_ok is None else centre_ok & live
    pose_chol = jax.vmap(jnp.linalg.cholesky)(pose_cov)

    def round_(owner, r):
        free = (owner < 0) & live
        c = best_slot(jnp.where(free & centre_ok, log_w, -jnp.inf))  # of tied ones, the first
        # Only the centres' factors are needed: K of them, not C.
        cov_c = cov_of(c)
        d2 = _mahalanobis2(jnp.linalg.cholesky(cov_c), mean[c], mean)
        close = free & (num_created == num_created[c]) & (d2 <= threshold)
        close = close | (jnp.arange(owner.shape[0]) == c)
        return jnp.where(close & jnp.any(free & centre_ok), r, owner), (c, jnp.any(free & centre_ok), d2, cov_c)

    owner, (centres, used, full_d2, centre_cov) = jax.lax.scan(round_, jnp.full(log_w.shape, -1),
                                                               jnp.arange(capacity))
    pose_d2 = jax.vmap(_mahalanobis2, (0, 0, None))(pose_chol[centres], mean[centres, :3], mean[:, :3])
    comparable = used[:, None] & (num_created[centres][:, None] == num_created[None, :])
    has_full = jnp.any(comparable, axis=0)
    nearest = jnp.where(has_full, jnp.argmin(jnp.where(comparable, full_d2, jnp.inf), axis=0),
                        jnp.argmin(jnp.where(used[:, None], pose_d2, jnp.inf), axis=0))
    left = (owner < 0) & live
    owner = jnp.where(left, nearest, owner)
    member = (owner[None, :] == jnp.arange(capacity)[:, None]) & live[None, :]  # (K, C)
    log_weights = logsumexp_or_minus_inf(jnp.where(member, log_w[None, :], -jnp.inf), axis=1)  # empty: -inf
    moment = member & ~(left & ~has_full)[None, :]
    centre_hot = jnp.arange(log_w.shape[0])[None, :] == centres[:, None]
    # A row with no member takes its centre alone; its softmax over nothing (NaN) is never formed, as
    # a NaN masked by the where would make every reverse-mode gradient NaN (the double where).
    has_member = jnp.any(moment, axis=1, keepdims=True)
    wn = jax.nn.softmax(jnp.where(moment, log_w[None, :], jnp.where(has_member, -jnp.inf, 0.0)), axis=1)
    wn = jnp.where(has_member, wn, centre_hot.astype(wn.dtype))
    return centres, log_weights, wn, centre_cov


def spread(
    wn: Float[Array, "K C"], anchor: Float[Array, "K D"], mean: Float[Array, "C D"],
) -> tuple[Float[Array, "K D"], Float[Array, "K D D"]]:
    """The members' weighted mean offset from each cluster's ``anchor`` and their scatter about it.

    The moment-matched cluster is ``anchor + shift`` with covariance ``Σ_c wn_c P_c + scatter``
    (angles wrapped: the offsets are taken on the circle).
    """
    delta = jax.vmap(jax.vmap(wrap_angles))(mean[None, :, :] - anchor[:, None, :])  # (K, C, D)
    shift = jnp.einsum("kc,kcd->kd", wn, delta)
    dev = delta - shift[:, None, :]
    return shift, jnp.einsum("kc,kcd,kce->kde", wn, dev, dev)


# --------------------------------------------------------------------------- #
# The estimator
# --------------------------------------------------------------------------- #


class Multimodal(AbstractEstimator):
    """Sum-mixture semantic SLAM (Doherty's thesis Ch. 5): see the module docstring.

    Settings: ``capacity`` (``K`` components), ``samples`` (Monte Carlo draws per child, Eq. 5.10),
    ``max_assignments`` (joint assignments kept per component while they are built one detection
    at a time, :func:`hybridslam.inference.beam.beam_search`; ``None``: all ``(G+1)^D``),
    ``candidates`` (``G`` gated objects per detection, plus the null hypothesis), ``children``
    (children that get a Gauss-Newton update; ``None``: ``2·capacity``), ``merge_threshold``
    (squared Mahalanobis distance over the whole state), ``association_prior`` (``"mc"``: thesis
    Eq. 5.11; ``"uniform"``), ``proposal`` (``"posterior"`` or ``"prior"``), ``clutter`` (a known
    map's clutter log density; module docstring), ``new_landmark`` (``"density"`` or
    ``"mahalanobis:TAU"``, thesis Sec. 3.2.1: :mod:`.novelty`), ``gn_max_steps``,
    ``classifier``, ``max_detections``, ``max_steps`` and ``smoother`` (:class:`~.smoothing.Full` by
    default: each component's trajectory relinearized at every step, the thesis's mm-iSAM in spirit;
    :class:`~.smoothing.Filter`) as in every estimator.
    """

    capacity: int = eqx.field(default=64, static=True)
    samples: int = eqx.field(default=DEFAULT_SAMPLES, static=True,
                             metadata=setting(note="per child, default {default}", show="num_samples"))
    candidates: int = eqx.field(default=DEFAULT_CANDIDATES, static=True, metadata=setting(GATE))
    children: int | None = eqx.field(default=None, static=True, metadata=setting(
        MAX_CHILDREN, note="children that get a Gauss-Newton update, default 2 x capacity",
        show=lambda e: f"children={2 * e.capacity if e.children is None else e.children}"))
    merge_threshold: float = eqx.field(default=DEFAULT_MERGE_THRESHOLD, static=True, metadata=setting(
        Option("merge_threshold", "squared Mahalanobis distance below which components merge", parse=float,
               command_line=False), show=lambda e: f"merge_threshold={e.merge_threshold}"))
    max_assignments: int | None = eqx.field(default=64, static=True, metadata=setting(show=False))
    association_prior: str = eqx.field(default="mc", static=True, metadata=setting(
        Option("association_prior", "mc (thesis Eq. 5.11) or uniform", parse=str, command_line=False)))
    proposal: str = eqx.field(default="posterior", static=True, metadata=setting(
        Option("proposal", "posterior or prior", parse=str, command_line=False)))
    gn_max_steps: int = eqx.field(default=20, static=True)
    smoother: Smoother = Full()
    classifier: str | ClassifierModel | None = None
    max_detections: int | None = eqx.field(default=None, static=True)
    max_steps: int | None = eqx.field(default=None, static=True)
    clutter: float | str | None = eqx.field(default=CLUTTER_FROM_FILE, static=True,
                                            metadata=setting(note="a known map only"))
    new_landmark: str = eqx.field(default=novelty.DENSITY, static=True)

    name: ClassVar[str] = "multimodal"
    title: ClassVar[str] = "multimodal sum-mixture semantic SLAM"
    reference: ClassVar[str] = "Doherty thesis Ch. 5, Eq. 5.9-5.11"

    def __check_init__(self):
        for field in ("capacity", "samples", "candidates", "gn_max_steps"):
            value = getattr(self, field)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"Multimodal.{field}: must be at least 1, got {value!r}")
        if self.max_assignments is not None and not (isinstance(self.max_assignments, int) and self.max_assignments >= 1):
            raise ValueError(f"Multimodal.max_assignments: must be at least 1 or None, got {self.max_assignments!r}")
        if self.children is not None and not (isinstance(self.children, int) and self.children >= 1):
            raise ValueError(f"Multimodal.children: must be at least 1, got {self.children!r}")
        if self.association_prior not in ASSOCIATION_PRIORS:
            raise ValueError(f"Multimodal.association_prior: must be one of {ASSOCIATION_PRIORS}, "
                             f"got {self.association_prior!r}")
        if self.proposal not in PROPOSALS:
            raise ValueError(f"Multimodal.proposal: must be one of {PROPOSALS}, got {self.proposal!r}")
        if not (isinstance(self.merge_threshold, (int, float)) and self.merge_threshold > 0):
            raise ValueError(f"Multimodal.merge_threshold: must be positive, got {self.merge_threshold!r}")
        check_clutter("Multimodal", self.clutter)
        novelty.parse_new_landmark("Multimodal", self.new_landmark)

    def _clutter(self, scenario: Scenario) -> float | None:
        """The clutter log density used on ``scenario`` (a known map's only; ``None``: none)."""
        if self.clutter == CLUTTER_FROM_FILE and scenario.discovery is not None:
            return None  # an unknown map's null hypothesis is a new object
        return resolve_clutter(self.clutter, scenario)

    def _structure(self, scenario: Scenario) -> Structure:
        n_max = object_slots(scenario)
        clutter = self._clutter(scenario)
        if clutter is not None and scenario.discovery is not None:
            raise ValueError("multimodal: --clutter is for a known map; on an unknown map (a discovery section) a "
                             "detection of no known object creates one (the null hypothesis, thesis Sec. 3.2.1)")
        slots = detection_slots(self.max_detections, scenario)
        candidates = min(self.candidates, n_max)
        assignments = (candidates + 1) ** slots if self.max_assignments is None else self.max_assignments
        children = min(2 * self.capacity if self.children is None else self.children, self.capacity * assignments)
        return Structure(self.capacity, n_max, slots, history_length(self.max_steps, scenario), self.samples, candidates, children,
                         self.gn_max_steps, scenario.discovery is not None, self.association_prior, self.proposal,
                         self.max_assignments, clutter is not None,
                         scenario.discovery is not None and novelty.parse_new_landmark("Multimodal", self.new_landmark) is not None)

    def init(self, scenario: Scenario) -> State:
        """One component of weight 1: the robot and object priors, uncreated slots ``N(0, I)`` (Eq. 3)."""
        cfg = self._structure(scenario)
        model = model_from_scenario(scenario.replace(discovery=None), self.classifier)
        n, n_max, m = scenario.num_objects, cfg.max_objects, scenario.num_classes
        dim = 3 + 3 * n_max
        mean = np.zeros(dim)
        mean[:3] = scenario.robot_prior_mean
        mean[3:3 + 3 * n] = np.asarray(scenario.object_prior_means).reshape(-1)
        cov = np.eye(dim)
        cov[:3, :3] = scenario.robot_prior_cov
        for i in range(n):  # once, at init
            cov[3 + 3 * i:6 + 3 * i, 3 + 3 * i:6 + 3 * i] = scenario.object_prior_covs[i]
        class_lp = np.full((n_max, m), -math.log(m))
        with np.errstate(divide="ignore"):
            class_lp[:n] = np.log(scenario.class_prior)
        disc = scenario.discovery
        put = jax.device_put  # numpy to the device without a compile (eager jnp ops compile one each)
        f = lambda a: put(np.asarray(a, dtype=float))  # noqa: E731
        params = Params(
            f(disc.new_object_log_density if disc else -np.inf),
            f(disc.new_object_orientation_var if disc else 1.0),
            f(float(self.merge_threshold)),
            f(-np.inf if (clutter := self._clutter(scenario)) is None else clutter),
            f(tau if (tau := novelty.parse_new_landmark("Multimodal", self.new_landmark)) is not None else np.inf),
        )
        # The class prior padded to Nmax rows: runs with the same capacities share one compiled step.
        model = eqx.tree_at(lambda mo: mo.class_prior, model, put(np.exp(class_lp)))
        k = cfg.capacity
        smoothing: dict[str, Any] = {} if isinstance(self.smoother, Filter) else dict(
            poses=put(np.broadcast_to(np.asarray(initial_trajectory(scenario, cfg.max_steps)), (k, cfg.max_steps + 1, 3))),
            log=data_log(scenario, cfg.max_steps, cfg.max_detections, n_max,
                         factor_budget(scenario, self.max_steps, cfg.max_detections)))
        if isinstance(self.smoother, Lag):
            smoothing["window"] = initial_window(smoothing["log"], k)
        return State(
            log_weights=put(np.concatenate([[0.0], np.full(k - 1, -np.inf)])),
            mean=put(np.broadcast_to(mean, (k, dim))),
            cov=put(np.broadcast_to(cov, (k, dim, dim))),
            class_log_probs=put(np.broadcast_to(class_lp, (k, n_max, m))),
            observed=put(np.zeros((k, n_max), dtype=bool)),
            num_created=put(np.full((k,), n, dtype=np.int32)),
            history=put(np.full((k, cfg.max_steps, cfg.max_detections), -1, dtype=np.int32)),
            k=put(np.zeros((), dtype=np.int32)),
            model=model,
            params=params,
            config=cfg,
            **smoothing,
        )

    def trajectory(self, state: State):
        """The smoothed ``x_0..x_T`` of the best component (``None`` without smoothing)."""
        return None if state.poses is None else state.poses[best_slot(state.log_weights)]

    def objects(self, state: State):
        """The best component's smoothed objects and their count (``None`` without smoothing)."""
        if state.poses is None:
            return None
        best = best_slot(state.log_weights)
        return state.mean[best, 3:].reshape(-1, 3), state.num_created[best]

    def step(self, state: State, odometry: Float[Array, "3"], detections: Detections,
             key: jax.Array) -> tuple[State, StepInfo]:
        """Propagate (Eq. 5.7's odometry factor), weigh the (component, joint assignment) children by
        Eq. 5.9-5.11, update them and merge them back to ``K`` components."""
        return _step(state, odometry, detections, key, self.smoother)

    def view(self, state: State) -> Mixture:
        """The robot-pose mixture, per-component argmax classes of associated objects (else -1), histories."""
        classes = jnp.where(state.observed, jnp.argmax(state.class_log_probs, axis=-1), -1).astype(jnp.int32)
        # Kept in the state, but a weight that underflows to 0 is no component of the reported belief.
        log_w = jnp.where(jnp.exp(state.log_weights) > 0, state.log_weights, -jnp.inf)
        return Mixture(log_w, state.mean[:, :3], state.cov[:, :3, :3], classes, state.history, state.k)


def _log_or_minus_inf(x):
    """``log x`` with ``-inf`` (and a zero derivative, not an infinite one) where ``x = 0``: an unused
    component's class probabilities (the double where: no NaN gradient)."""
    positive = x > 0
    return jnp.where(positive, jnp.log(jnp.where(positive, x, 1.0)), -jnp.inf)


def _step(state: State, odometry: Float[Array, "3"], detections: Detections, key: jax.Array,
          smoother: Smoother) -> tuple[State, StepInfo]:
    cfg = state.config
    mean, cov = jax.vmap(motion.propagate, (0, 0, None, None))(state.mean, state.cov, odometry, state.model.motion_cov)
    ch = hypotheses(state, mean, cov, detections, key)
    _, theta = draws(key, cfg, state.params)

    def child_full_cov(c):  # child c's covariance, its new objects written
        return discovery.create_objects(ch.mean[c], downdate(cov[ch.parent[c]], ch.gain[c], ch.gain_js[c]),
                                        ch.objects[c], ch.new[c] & (ch.objects[c] >= 0), detections.geo,
                                        state.model.sensor.geometric_cov,
                                        state.params.orientation_var)[1]

    # Every child's covariance only where the filter moment-matches whole clusters; with a smoother
    # only the K centres' are formed (child_full_cov, in the clustering), not C × D × D: the
    # covariances finish_child makes of zeros are then unused, and XLA drops that work.
    filtering = isinstance(smoother, Filter)
    # (One at a time: XLA's batched product with the short inner axis m is slower on CPU: 59 against
    # 46 ms per hallway step.)
    pre_cov = (_chunked(lambda i, k, js: downdate(cov[i], k, js), ch.parent, ch.gain, ch.gain_js, batch_size=1)
               if filtering else jnp.zeros((cfg.children,) + cov.shape[1:], cov.dtype))
    finish = jax.vmap(lambda m, c, class_lp, obs, created, objs, new: finish_child(
        state, m, c, class_lp, obs, created, objs, new, detections, theta))
    c_mean, c_cov, c_class, c_obs, c_created = finish(
        ch.mean, pre_cov, state.class_log_probs[ch.parent], state.observed[ch.parent], state.num_created[ch.parent],
        ch.objects, ch.new)
    c_hist = state.history[ch.parent].at[:, state.k].set(jnp.where(detections.mask[None, :], ch.objects, -1))
    # A child more than RELEVANT_NATS below the best (relative weight < 1e-13) becomes no centre of
    # the merge: its mass joins the nearest centre.
    centre_ok = relevant_children(ch.log_weight)
    pose_cov = jax.vmap(lambda i, k, js: downdate(cov[i], k, js, jnp.arange(3)))(ch.parent, ch.gain, ch.gain_js)
    centres, log_w, wn, centre_cov = clustered(
        ch.log_weight, c_mean, (lambda c: c_cov[c]) if filtering else child_full_cov, pose_cov, c_created,
        state.params.merge_threshold, cfg.capacity, centre_ok)
    shift, scatter = spread(wn, c_mean[centres], c_mean)
    poses, log, smooth_failed = state.poses, state.log, jnp.zeros(cfg.capacity, bool)
    window = state.window
    if isinstance(smoother, Filter):  # each cluster moment-matched from its members' own Gaussians
        m_mean = jax.vmap(wrap_angles)(c_mean[centres] + shift)
        m_cov = jnp.einsum("kc,cde->kde", wn, c_cov) + scatter
    else:
        # Each merged component's centre has its whole trajectory and map relinearized with every
        # factor of its history (smoothing.py): K smoothings per step rather than one per child.
        assert state.log is not None and state.poses is not None  # Full keeps them
        log = state.log.record(state.k, odometry, detections)

        def smoothed(poses_i, mean_i, cov_i, history_i, created_i, window_i):
            return smooth_step(smoother, log, history_factors(history_i), state.k + 1, created_i, state.model.sensor,
                               state.model.motion_cov, False, "sum", poses_i, mean_i, cov_i, window_i)

        # The used centres form a prefix (cluster picks them by weight), so map_live skips the
        # chunks after it; an unused slot gets slot 0's values so that later math on it stays finite.
        used = log_w > -jnp.inf
        parent = ch.parent[centres]
        parent_window = None if state.window is None else jax.tree.map(lambda a: a[parent], state.window)
        out = map_live(smoothed, used, state.poses[parent], c_mean[centres], centre_cov, c_hist[centres],
                       c_created[centres], parent_window,
                       chunk=smoothing_chunk(state.poses.shape[-2], (c_mean.shape[-1] - 3) // 3))
        out = jax.tree.map(lambda a: jnp.where(used.reshape((-1,) + (1,) * (a.ndim - 1)), a, a[:1]), out)
        # Members keep their (filter) offsets from the centre and take its smoothed covariance: the
        # cluster moment-matched about the centre's smoothed estimate.
        m_mean = jax.vmap(wrap_angles)(out.mean + shift)
        m_cov = out.cov + scatter
        poses, window = out.poses, out.window
        smooth_failed = used & (out.result != optx.RESULTS.successful)
    m_cov = 0.5 * (m_cov + jnp.swapaxes(m_cov, 1, 2))
    # Warnings concern hypotheses within RELEVANT_NATS of the best; the rest carry no visible mass.
    relevant = relevant_children(state.log_weights)
    no_room = cfg.discovery & lacks_object_slots(detections.mask, state.num_created, cfg.max_objects, relevant)
    # No child explains the step (e.g. no room for a new object, or no feasible joint assignment): the
    # step's detections are skipped, and counted, and every component stays, propagated, with its
    # weight and no association for this step, rather than the belief lost.
    explained = jnp.any(log_w > -jnp.inf)
    # Solver failures per merged component (the warning says "n of num_components"): a member's
    # Gauss-Newton update or (above) the component's smoothing did not converge.
    child_failed = centre_ok & (ch.result != optx.RESULTS.successful)
    member_failed = jnp.any((wn > 0) & child_failed[None, :], axis=1)
    best = centres[jnp.argmax(log_w)]  # the best merged component's centre (a child)
    unmapped = detections.mask & ch.new[best] & (ch.objects[best] < 0)  # new objects with no free slot
    unassociated = jnp.sum(detections.mask & (ch.objects[best] < 0) & ~unmapped, dtype=jnp.int32)
    # Its associations against its parent's prediction (objects it creates or leaves unmapped aside;
    # clutter explains a detection, a skip does not).
    inconsistent = explained & gating.contradicted(state.model.sensor, mean[ch.parent[best]], cov[ch.parent[best]],
                                                   detections, jnp.where(ch.new[best], -1, ch.objects[best]),
                                                   (ch.objects[best] < 0) & ~unmapped & (not cfg.clutter))
    info = StepInfo(
        k=(state.k + 1).astype(jnp.int32),
        num_components=jnp.where(explained, jnp.sum(log_w > -jnp.inf, dtype=jnp.int32),
                                 jnp.sum(state.log_weights > -jnp.inf, dtype=jnp.int32)),
        dropped_mass=ch.dropped_mass,
        dropped_budget=ch.beam_dropped,
        solver_failures=jnp.sum((log_w > -jnp.inf) & (smooth_failed | member_failed), dtype=jnp.int32),
        # The best component's unassociated detections (a known map's skipped ones, or those its
        # clutter hypothesis explains: rejected), or all of them when nothing explains the step.
        skipped=jnp.where(explained, 0 if cfg.clutter else unassociated, jnp.sum(detections.mask, dtype=jnp.int32)),
        rejected=jnp.where(explained & cfg.clutter, unassociated, 0),
        unmapped=jnp.where(explained, jnp.sum(unmapped, dtype=jnp.int32), 0),
        object_overflow=no_room,
        log_overflow=new_overflow(state.log, log),
        inconsistent=inconsistent,
        details=Details(ch.parent, ch.objects, ch.log_prob),
    )
    keep = lambda new, old: jnp.where(explained, new, old)  # noqa: E731
    new_state = dataclasses.replace(
        state,
        log_weights=keep(log_w - jax.nn.logsumexp(jnp.where(explained, log_w, 0.0)), state.log_weights),
        mean=keep(m_mean, mean),
        cov=keep(m_cov, cov),
        class_log_probs=keep(_log_or_minus_inf(jnp.einsum("kc,cnm->knm", wn, jnp.exp(c_class))),
                             state.class_log_probs),
        observed=keep(jnp.any((wn > 0)[:, :, None] & c_obs[None, :, :], axis=1), state.observed),
        num_created=keep(c_created[centres], state.num_created),
        history=keep(c_hist[centres], state.history.at[:, state.k].set(-1)),
        k=state.k + 1,
        poses=poses if poses is None else keep(poses, state.poses),
        log=log,
        window=window if window is None else jax.tree.map(keep, window, state.window),
    )
    return new_state, info
