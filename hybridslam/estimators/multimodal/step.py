"""One step of the multimodal mixture (:meth:`Multimodal.step`): predict, branch into children,
weigh, update, merge and smooth."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from ...inference import discovery, gating
from ...inference.batching import map_live, smoothing_chunk
from ...inference.update import downdate, wrap_angles
from ...models import motion
from ...models.measurement import Detections
from ..base import StepInfo, lacks_object_slots, relevant_children
from ..smoothers.kinds import Smoother, SmootherState
from ..smoothers.factors import history_factors, new_overflow
from .children import finish_child, hypotheses
from .clustering import clustered, spread
from .likelihood import draws
from .state import Details, State, _chunked


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
    filtering = not smoother.smooths
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
    kept, smooth_failed = state.smoothing, jnp.zeros(cfg.capacity, bool)
    if filtering:  # each cluster moment-matched from its members' own Gaussians
        m_mean = jax.vmap(wrap_angles)(c_mean[centres] + shift)
        m_cov = jnp.einsum("kc,cde->kde", wn, c_cov) + scatter
    else:
        # Each merged component's centre has its whole trajectory and map relinearized with every
        # factor of its history (smoothers/kinds.py): K smoothings per step rather than one per child.
        kept = kept.record(state.k, odometry, detections)
        log = kept.log
        assert log is not None  # record writes one

        def smoothed(poses_i, mean_i, cov_i, history_i, created_i, window_i):
            return smoother.smooth(SmootherState(poses_i, log, window_i), history_factors(history_i), state.k + 1,
                                   created_i, state.model.sensor, state.model.motion_cov, False, "sum", mean_i, cov_i)

        # The used centres form a prefix (cluster picks them by weight), so map_live skips the
        # chunks after it; an unused slot gets slot 0's values so that later math on it stays finite.
        used = log_w > -jnp.inf
        parent = ch.parent[centres]
        parents = kept.components(parent)
        assert parents.poses is not None  # a smoother's init gives every component a trajectory
        out = map_live(smoothed, used, parents.poses, c_mean[centres], centre_cov, c_hist[centres],
                       c_created[centres], parents.window,
                       chunk=smoothing_chunk(parents.poses.shape[-2], (c_mean.shape[-1] - 3) // 3))
        out = jax.tree.map(lambda a: jnp.where(used.reshape((-1,) + (1,) * (a.ndim - 1)), a, a[:1]), out)
        # Members keep their (filter) offsets from the centre and take its smoothed covariance: the
        # cluster moment-matched about the centre's smoothed estimate.
        m_mean = jax.vmap(wrap_angles)(out.mean + shift)
        m_cov = out.cov + scatter
        kept = dataclasses.replace(kept, poses=out.poses, window=out.window)
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
        log_overflow=new_overflow(state.smoothing.log, kept.log),
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
        # Without an explanation the components stay, and so do their trajectories (the log records the step).
        smoothing=kept.where(explained, state.smoothing),
    )
    return new_state, info
