"""One inference step of the hybrid belief: Algorithm 1 as a single jit-compiled function.

``step(belief, odometry, detections, key)`` is pure; ``jax.vmap`` it over a leading axis of
beliefs to run many tracks (or many parameter settings: the model lives in the belief) at once.
Compiles once per (capacity, history length, detection slots, objects, classes, weight method,
classifier type, hard or smooth visibility, known or unknown map, gating); model parameters are
traced. Differentiable in every continuous input (``docs/gradients.md``).

Unknown maps (``model.discovery``): a child may give a detection a new object (the null /
new-landmark hypothesis, thesis Sec. 3.2.1). Its weight gets that detection's
:func:`~hybridslam.weights.new_object_log_likelihood`; its Gaussian gets the object from
:func:`~hybridslam.discovery.create_object` *before* the Gauss-Newton update, in which that
detection is then no factor: the back-projection already used it, and using it again would count
it twice. (The detection's scores are not used on the new object's orientation either, a small
loss of information: the weight integrates them over the unknown viewpoint instead.)
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.scipy.special import logsumexp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from .batching import map_live
from .belief import Belief, Detections
from .discovery import create_object
from .gating import gate
from .hypotheses import Children, HypothesisTable, children, hypothesis_table
from .motion import propagate
from .prune import PruneStats, prune
from .update import gauss_newton_update
from .weights import (
    laplace_is_log_likelihood,
    linearized_log_likelihood,
    new_object_log_likelihood,
    sampled_log_likelihood,
)


class StepInfo(eqx.Module):
    """Diagnostics of one step."""

    log_evidence: Float[Array, ""]  # log Σ of unnormalized child weights ≈ log P(Z_k | H_k⁻)
    prune: PruneStats
    num_alive: Int[Array, ""]  # components after pruning
    parent: Int[Array, " K"]  # slot of each new component's parent in the previous belief
    solver_result: optx.RESULTS  # Gauss-Newton outcome per component (Eq. 9)
    visibility_ignored: Bool[Array, ""]  # no hypothesis had every detected object in view (0/1 model only)
    ess: Float[Array, " K"]  # normalized effective sample size of each kept weight (1 = exact; NaN if empty)
    is_solver_failures: Int[Array, ""]  # kept components whose laplace-is mode search did not converge


def _realize(classes: Int[Array, " N"], assign: Int[Array, " Dmax"], slot_class: Int[Array, " Dmax"], new):
    """Write the classes of newly associated objects (Sec. IV-D); all others are unchanged."""
    target = jnp.where(new, assign, classes.shape[0])  # out of bounds -> dropped
    return classes.at[target].set(slot_class, mode="drop")


def _create_and_update(sensor, discovery, mean, cov, assign, creates, slot_class, detections: Detections, max_steps):
    """Write the objects a child creates into its Gaussian (:func:`~hybridslam.discovery.create_object`),
    then update it with the detections of its other slots (Eq. 9-10)."""
    for j in range(assign.shape[0]):  # detection slots (static, a few)
        made = create_object(mean, cov, jnp.maximum(assign[j], 0), detections.geo[j], sensor.geometric_cov,
                             discovery.orientation_var)
        mean, cov = (jnp.where(creates[j], new, old) for new, old in zip(made, (mean, cov)))
    return gauss_newton_update(sensor, mean, cov, jnp.where(creates, -1, assign), slot_class, detections, max_steps)


def _new_object_terms(belief: Belief, mean, cov, detections: Detections, kids: Children) -> Float[Array, "K A Mc"]:
    """Σ over a child's creating slots of :func:`~hybridslam.weights.new_object_log_likelihood`."""
    sensor = belief.model.sensor
    lik = jax.vmap(new_object_log_likelihood, (None, 0, 0, None, None))(
        sensor, mean[:, :3], cov[:, :3, :3], detections, belief.model.discovery
    )  # (K, Dmax, M)
    pick = kids.slot_class[..., None] == jnp.arange(lik.shape[-1]).reshape(1, 1, 1, 1, -1)  # (K, A, Mc, Dmax, M)
    picked = jnp.sum(jnp.where(pick, lik[:, None, None], 0.0), axis=-1)
    return jnp.sum(jnp.where(kids.creates[:, :, None, :], picked, 0.0), axis=-1)


# A child whose objects are (almost surely) out of view still ranks by its likelihood when the
# laplace-is candidates are screened, this many nats below any child in view.
_SCREEN_OUT_OF_VIEW = 50.0


def _weigh_children(
    belief: Belief, mean, cov, detections: Detections, table: HypothesisTable, kids: Children,
    prior: Float[Array, "K A Mc"], key: PRNGKeyArray,
):
    """PropWeights (Eq. 16) by ``config.weights``: ``log ψ`` of every child with and without the
    observation model, the normalized ESS of each estimate, and whether each laplace-is mode search
    converged (all True for the other methods). Arrays ``(K, A, Mc)``."""
    cfg, sensor = belief.config, belief.model.sensor
    if cfg.weights == "sampled":
        eps = jax.random.normal(key, (cfg.num_samples, mean.shape[-1]), dtype=mean.dtype)
        weigh = lambda m, c, kid: sampled_log_likelihood(sensor, m, c, detections, eps, table, kid)  # noqa: E731
        log_lik, log_lik_free, ess = map_live(weigh, belief.alive, mean, cov, kids, axis_name=cfg.batch_axis)
        return log_lik, log_lik_free, ess, jnp.ones(ess.shape, bool)
    weigh = lambda m, c, kid: linearized_log_likelihood(sensor, m, c, detections, table, kid,  # noqa: E731
                                                        axis_name=cfg.batch_axis)
    linear, linear_free, ess = map_live(weigh, belief.alive, mean, cov, kids, axis_name=cfg.batch_axis)
    if cfg.weights == "linearized":
        return linear, linear_free, ess, jnp.ones(ess.shape, bool)
    # laplace-is: importance-sample the children that the linearized weights rank best.
    eps = jax.random.normal(key, (cfg.is_samples, 3 + 3 * cfg.max_detections), dtype=mean.dtype)
    rank = jnp.maximum(linear, linear_free - _SCREEN_OUT_OF_VIEW)
    screen = jnp.where(kids.valid & belief.alive[:, None, None], prior + rank, -jnp.inf)
    # Children hopelessly below the best would be pruned anyway: leaving them out lets the Laplace-IS
    # chunks of empty candidates be skipped (most steps have a handful of serious children).
    screen = jnp.where(screen >= jnp.max(screen) - cfg.is_screen_nats, screen, -jnp.inf)
    return laplace_is_log_likelihood(
        sensor, mean, cov, detections, eps, table, kids, screen, cfg.is_candidates, cfg.gn_max_steps,
        axis_name=cfg.batch_axis,
    )


def _step(
    belief: Belief, odometry: Float[Array, "3"], detections: Detections, key: PRNGKeyArray
) -> tuple[Belief, StepInfo]:
    cfg, model = belief.config, belief.model
    realize = model.sensor.classifier.uses_scores
    discovery = model.discovery is not None
    if discovery and belief.num_created is None:
        raise ValueError("belief.num_created: a model with discovery needs a belief built by init_belief with it")
    gated = cfg.gate_candidates is not None
    num_candidates = min(cfg.gate_candidates or 1, belief.num_objects)
    # Without semantics no class is ever realized: one (dummy) class combination suffices.
    table = hypothesis_table(num_candidates if gated else belief.num_objects, cfg.max_detections,
                             model.num_classes if realize else 1, discovery, gated)
    k = eqx.error_if(
        belief.k, belief.k >= cfg.max_steps,
        "belief history is full: build the belief with Config(max_steps=...) >= the number of steps",
    )

    # Algorithm 1, line 3: propagate every component with the motion model (Eq. 11).
    mean, cov = jax.vmap(propagate, (0, 0, None, None))(belief.mean, belief.cov, odometry, model.motion_cov)

    # Line 2 of PROPWEIGHTS: split each parent into (β_k, new class realizations).
    candidates = None
    if gated:
        candidates = jax.vmap(gate, (None, 0, 0, None, 0, None))(
            model.sensor, mean, cov, detections, belief.num_created, num_candidates
        )
    kids = jax.vmap(children, (None, 0, None, None, None, 0, 0))(
        table, belief.classes, detections.mask, model.class_prior, realize, belief.num_created, candidates
    )

    # Line 5: PropWeights, Eq. 16. `prior` holds every factor of a child's weight that does not
    # depend on the objects' Gaussian (so the laplace-is screen ranks by it too).
    prior = belief.log_weights[:, None, None] + kids.log_prior
    if discovery:
        prior = prior + _new_object_terms(belief, mean, cov, detections, kids)
    log_lik, log_lik_free, ess, is_converged = _weigh_children(belief, mean, cov, detections, table, kids, prior, key)
    possible = kids.valid & belief.alive[:, None, None]
    # `where`, not `+`: empty slots may carry non-finite likelihoods that must not leak.
    log_w = jnp.where(possible, prior + log_lik, -jnp.inf)
    # No hypothesis puts every detected object in view: the 0/1 visibility model cannot explain
    # this step, so weigh it by the measurement likelihood alone rather than lose the belief.
    visibility_ignored = ~jnp.any(log_w > -jnp.inf) & jnp.any(possible)
    log_w = jnp.where(visibility_ignored, jnp.where(possible, prior + log_lik_free, -jnp.inf), log_w)

    # Line 7: PruneAndNormalize.
    index, new_log_w, stats = prune(log_w.reshape(-1), cfg.capacity, model.prune_ratio)
    parent, a, m = jnp.unravel_index(index, log_w.shape)
    assign, creates = kids.assign[parent, a], kids.creates[parent, a]
    slot_class = kids.slot_class[parent, a, m]

    # Line 11: update every kept child with its measurement factors (Eq. 9-10).
    alive = new_log_w > -jnp.inf
    if discovery:
        update = partial(_create_and_update, model.sensor, model.discovery, detections=detections,
                         max_steps=cfg.gn_max_steps)
        args = (mean[parent], cov[parent], assign, creates, slot_class)
    else:
        update = partial(gauss_newton_update, model.sensor, detections=detections, max_steps=cfg.gn_max_steps)
        args = (mean[parent], cov[parent], assign, slot_class)
    new_mean, new_cov, result = map_live(update, alive, *args, axis_name=cfg.batch_axis)
    # Empty slots copy the best component so later batched math on them stays finite.
    new_mean = jnp.where(alive[:, None], new_mean, new_mean[:1])
    new_cov = jnp.where(alive[:, None, None], new_cov, new_cov[:1])

    new_belief = Belief(
        log_weights=new_log_w,
        mean=new_mean,
        cov=new_cov,
        classes=jax.vmap(_realize)(belief.classes[parent], assign, slot_class, kids.new[parent, a, m]),
        history=belief.history[parent].at[:, k, :].set(assign),
        k=k + 1,
        model=model,
        config=cfg,
        num_created=None if not discovery else belief.num_created[parent] + jnp.sum(creates, axis=-1, dtype=jnp.int32),
    )
    info = StepInfo(
        logsumexp(log_w), stats, jnp.sum(alive), parent, result, visibility_ignored,
        jnp.where(alive, ess[parent, a, m], jnp.nan), jnp.sum(alive & ~is_converged[parent, a, m]),
    )
    return new_belief, info


step = jax.jit(_step)
step.__doc__ = """Advance a belief by one step (Algorithm 1): propagate, split, weigh (Eq. 16), prune, update.

Args:
    belief: the belief after step ``k - 1``.
    odometry: ``u_k``, shape ``(3,)``, a measurement of ``between(x_{k-1}, x_k)``.
    detections: the step's detections, padded to ``belief.config.max_detections`` slots.
    key: PRNG key for the Monte-Carlo draws (unused by ``weights="linearized"``).

Returns:
    ``(belief, info)``: the belief after step ``k`` and a :class:`StepInfo`.
"""
