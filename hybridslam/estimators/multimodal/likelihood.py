"""Joint assignments, gating and the likelihoods of a joint assignment (Doherty's thesis Eq.
5.9-5.10): exact, screened and Monte Carlo over pose samples with joint compatibility."""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Bool, Float, Int

from ...inference import discovery, gating, sequential
from ...inference.laplace import logsumexp_or_minus_inf
from ...inference.update import wrap_angles
from ...models import geometry
from ...models.classifier import ClassifierModel
from ...models.measurement import Detections, SensorModel, log_visibility, log_visibility_probability
from .state import Params, Structure


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
