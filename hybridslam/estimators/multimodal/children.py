"""Children of (component, joint assignment), weighted by Eq. 5.9-5.11 of Doherty's thesis, and a
child finished: its Gauss-Newton update, new objects (Sec. 3.2.1) and class posteriors."""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ...inference import discovery, gating, sequential
from ...inference.batching import map_live
from ...inference.beam import beam_search
from ...inference.ties import rank_key
from ...inference.update import downdate, prior_gauss_newton_gain, support_of
from ...models import geometry
from ...models.measurement import Detections
from .. import novelty
from ...inference.gating import chi2_gate
from .likelihood import (_new_object, _placeholders, _sub_indices, assignment_objects, class_log_likelihoods,
                         condition, draws, gate, localized_terms, sampled_log_likelihood,
                         screen_log_likelihood, skipped_detections, slot_log_likelihood, slot_terms,
                         sub_gaussian, tuple_log_probs)
from .state import SMALL_LAPACK_BATCH, State, _chunked


# With a clutter hypothesis (a known map), a detection's candidates are the objects inside the
# chi-square gate of the single-Gaussian estimators' default (gate_probability 0.999: d² ≤ 13.8),
# as the thesis gates (Sec. 3.2.1); a detection with none is clutter. Without clutter every
# detection is some object's, and the nearest ``candidates`` compete whatever their distance.
CLUTTER_GATE = chi2_gate(0.999)


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
        if cfg.clutter:  # the chi-square gate (Sec. 3.2.1): an object beyond it leaves the detection to clutter
            cand, _ = novelty.restrict(cand, pred.d2, CLUTTER_GATE)
        near = jnp.zeros(cfg.max_detections, bool)  # a known object within τ: "new" breaks the rule (.novelty)
        if cfg.discovery:  # τ traced (inf: the density rule, under which this changes nothing)
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
                                carry=start, advance=partial(condition, terms, detections.mask), stop=detections.span())
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
