"""Data-association-aware planning on the hybrid belief (DA-BSP, the paper's reference [3]).

A planner does not know the ground truth. To score a candidate action sequence ``a_1..a_H`` it
*predicts* what the robot would observe: it draws a component of the belief by weight, a joint
state (robot pose and objects) from that component's Gaussian, and classes (the component's
realizations, or the class prior where it leaves them open); it moves the drawn robot with the
motion model and the actions, and draws detections from the sensor model (nearest visible
objects, Eq. 10 geometric noise, Eq. 2 classifier scores). Then it runs the belief update
(Algorithm 1) on those predicted observations, with the actions as odometry, and scores the
resulting belief: expected association entropy H(w) (Eq. 8; lower means the association is
resolved) plus, optionally, ``λ · log det Σ`` of the best component's position.

:func:`score_candidates` does all of it for a batch of candidates and several observation
draws each in one ``jax.jit``-compiled ``vmap``: one executable per (candidates, horizon,
draws, belief shape). The batch axis is named, so the step skips component slots that are empty
in every rollout (``Hybrid.batch_axis``). :func:`prepare` shrinks a belief for planning (keep
the best components, room in the history for the horizon) and fixes the planner's own settings
of the predicted updates (a :class:`Plan`: the estimator and the belief). The predicted updates
run the driver's :func:`hybridslam.driver.scan`, like every other path.
The predicted updates filter (``smoother=Filter()``): a planning horizon is a few steps, and the
smoother's cost per candidate and draw would multiply by the whole trajectory for little change in the
scores.
"""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.scipy.special import logsumexp
from jaxtyping import Array, Float, Int, Key, PRNGKeyArray, UInt32

from ..analysis.metrics import association_entropy
from ..driver import Inputs, scan
from ..estimators.hybrid.belief import Belief
from ..estimators.hybrid.estimator import Hybrid
from ..estimators.hybrid.weighers import AbstractWeigher, LaplaceIS, make_weigher
from ..estimators.smoothers import Filter
from ..inference.ties import best_slot
from ..models import geometry, se2
from ..models.measurement import Detections
from ..models.model import with_smooth_visibility

PLAN_AXIS = "candidates"


class Plan(eqx.Module):
    """A belief ready for planning and the settings of its predicted updates (:func:`prepare`)."""

    estimator: Hybrid  # the predicted updates' settings; batch axis PLAN_AXIS
    belief: Belief  # the best components, with room in the history for the horizon

    @property
    def room(self) -> int:
        """Steps the belief can still take."""
        return self.belief.max_steps - int(self.belief.k)


def prepare(
    belief: Belief, horizon: int, capacity: int | None = None, visibility_temperature: float | None = None, *,
    weights: str | AbstractWeigher = LaplaceIS(), gn_max_steps: int = 20, gate: int | None = None,
) -> Plan:
    """A :class:`Plan` for :func:`score_candidates` and :func:`refine_actions`.

    Keeps the ``capacity`` best components of ``belief`` (slots are sorted by weight; the kept
    weights are renormalized) and adds ``horizon`` steps to the history. The predicted updates use
    ``weights`` (a weigher, or its name, e.g. ``"linearized"``), ``gn_max_steps`` (e.g. 2: an
    iterated-EKF update, cheaper and plenty for predictions) and ``gate``. Host-side (shapes change):
    call it once per planning round, outside ``jit``. ``visibility_temperature`` (metres; see
    :func:`hybridslam.models.model.with_smooth_visibility`) switches the predicted updates to the
    smooth object observation model, which :func:`refine_actions` needs for a useful gradient.
    """
    keep = belief.capacity if capacity is None else min(capacity, belief.capacity)
    log_w = belief.log_weights[:keep]
    log_w = jnp.where(log_w > -jnp.inf, log_w - logsumexp(log_w), -jnp.inf)
    # The whole history plus the horizon: the shape stays the same from step to step of a run, so
    # score_candidates compiles once per run.
    history = belief.history[:keep]
    history = jnp.concatenate([history, jnp.full((keep, horizon) + history.shape[2:], -1, history.dtype)], axis=1)
    model = belief.model if visibility_temperature is None else with_smooth_visibility(belief.model, visibility_temperature)
    weigher = make_weigher(weights) if isinstance(weights, str) else weights
    estimator = Hybrid(weights=weigher, capacity=keep, gn_max_steps=gn_max_steps, gate=gate, batch_axis=PLAN_AXIS,
                       smoother=Filter())
    num_created = None if belief.num_created is None else belief.num_created[:keep]
    prepared = Belief(log_w, belief.mean[:keep], belief.cov[:keep], belief.classes[:keep], history, belief.k, model,
                      num_created)
    return Plan(estimator, prepared)


class World(eqx.Module):
    """One draw of the unknown world from the belief: robot pose, object poses and classes."""

    robot: Float[Array, "3"]
    objects: Float[Array, "N 3"]
    classes: Int[Array, " N"]


def sample_world(belief: Belief, key: PRNGKeyArray) -> World:
    """Draw a component by weight, a joint state from its Gaussian, classes from it or the prior."""
    k_comp, k_state, k_class = jax.random.split(key, 3)
    i = jax.random.categorical(k_comp, belief.log_weights)
    cov = belief.cov[i]
    # An eigen-square-root: the joint covariance can be numerically singular (perfectly known dims).
    vals, vecs = jnp.linalg.eigh(0.5 * (cov + cov.T))
    eps = jax.random.normal(k_state, (cov.shape[0],), cov.dtype)
    state = belief.mean[i] + vecs @ (jnp.sqrt(jnp.maximum(vals, 0.0)) * eps)
    drawn = jax.random.categorical(k_class, jnp.log(belief.model.class_prior))
    classes = jnp.where(belief.classes[i] >= 0, belief.classes[i], drawn)
    return World(state[:3], state[3:].reshape(-1, 3), classes)


def observe(belief: Belief, world: World, pose: Float[Array, "3"], key: PRNGKeyArray) -> Detections:
    """Detections of the nearest visible objects from ``pose`` (at most ``max_detections``).

    Range and bearing get Σ_v noise (Eq. 10), scores are drawn from the classifier model at the
    object's viewpoint and class (Eq. 2). Slots without a visible object are masked.
    """
    sensor = belief.model.sensor
    slots = belief.max_detections
    rb = jax.vmap(geometry.range_bearing, (None, 0))(pose, world.objects)
    seen = jax.vmap(geometry.visible, (0, None, None))(rb, sensor.max_range, sensor.fov)
    order = jnp.argsort(jnp.where(seen, rb[:, 0], jnp.inf))[:slots]
    k_geo, k_sem = jax.random.split(key)
    noise = jax.random.normal(k_geo, (slots, 2), rb.dtype) @ jnp.linalg.cholesky(sensor.geometric_cov).T
    geo = rb[order] + noise
    geo = jnp.stack([jnp.maximum(geo[:, 0], 0.0), se2.wrap(geo[:, 1])], axis=-1)
    views = jax.vmap(geometry.viewpoint, (None, 0))(pose, world.objects[order])
    keys = jax.random.split(k_sem, slots)
    scores = jax.vmap(sensor.classifier.sample)(keys, world.classes[order], views)
    return Detections(geo, scores, seen[order])


def predict_observations(
    belief: Belief, actions: Float[Array, "H 3"], key: PRNGKeyArray
) -> tuple[Float[Array, "H 3"], Detections]:
    """The odometry and detections the robot would get executing ``actions`` in a world drawn from ``belief``.

    The robot moves ``x_k = x_{k-1} ∘ a_k ∘ Exp(w_k)``, ``w_k ~ N(0, Σ_w)`` (the motion model
    of Eq. 11), so the odometry reading is the action itself.
    """
    k_world, k_motion, k_obs = jax.random.split(key, 3)
    world = sample_world(belief, k_world)
    chol_w = jnp.linalg.cholesky(belief.model.motion_cov)
    noise = jax.random.normal(k_motion, actions.shape, actions.dtype) @ chol_w.T

    def move(pose, xs):
        action, w, k = xs
        pose = se2.compose(se2.compose(pose, action), se2.exp(w))
        return pose, observe(belief, world, pose, k)

    keys = jax.random.split(k_obs, actions.shape[0])
    _, detections = jax.lax.scan(move, world.robot, (actions, noise, keys))
    return actions, detections


def rollout(plan: Plan, odometry: Float[Array, "H 3"], detections: Detections, key: PRNGKeyArray) -> Belief:
    """The belief after ``H`` predicted steps of Algorithm 1 (:func:`hybridslam.driver.scan`; pure)."""
    h = odometry.shape[0]
    inputs = Inputs(odometry, detections, jnp.arange(h, dtype=jnp.int32), jnp.full((h, 3), jnp.nan, odometry.dtype),
                    jnp.ones(h, bool))
    final, _ = scan(plan.estimator, plan.belief, inputs, key)
    return final


def objective(belief: Belief, logdet_weight: Float[Array, ""] | float = 0.0) -> Float[Array, ""]:
    """``H(w) + λ · log det Σ_best``: association entropy (Eq. 8) and the best component's
    2x2 position covariance; lower is better."""
    best = best_slot(belief.log_weights)
    logdet = jnp.linalg.slogdet(belief.cov[best, :2, :2])[1]
    return association_entropy(belief) + logdet_weight * logdet


def _score_one(plan, actions, keys, logdet_weight):
    """Mean objective over the observation draws ``keys`` of one candidate."""

    def one_draw(key):
        k_pred, k_step = jax.random.split(key)
        odometry, detections = predict_observations(plan.belief, actions, k_pred)
        return objective(rollout(plan, odometry, detections, k_step), logdet_weight)

    return jnp.mean(jax.lax.map(one_draw, keys))


CHUNK = 64  # candidates per vmapped batch (XLA:CPU hung on one 256-wide batch of this program)


@eqx.filter_jit
def _score(plan, candidates, keys, logdet_weight):
    score = jax.vmap(_score_one, (None, 0, None, None), axis_name=PLAN_AXIS)
    num = candidates.shape[0]
    size = min(CHUNK, num)
    pad = -num % size
    padded = jnp.concatenate([candidates, jnp.repeat(candidates[:1], pad, axis=0)])
    chunks = padded.reshape((-1, size) + candidates.shape[1:])
    out = jax.lax.map(lambda c: score(plan, c, keys, logdet_weight), chunks)
    return out.reshape(-1)[:num]


def score_candidates(
    plan: Plan,
    candidates: Float[Array, "C H 3"],
    key: PRNGKeyArray,
    num_draws: int = 1,
    logdet_weight: float = 0.0,
) -> Float[Array, " C"]:
    """Expected objective of each candidate action sequence (lower is better), one jitted call.

    ``plan`` comes from :func:`prepare` (room for ``H`` more steps, batch axis named). Every
    candidate is scored on the same ``num_draws`` predicted worlds and noise draws (common random
    numbers): differences between candidates are not sampling noise between draws.
    """
    if not isinstance(plan, Plan):
        raise ValueError("score_candidates: pass a plan from hybridslam.planning.prepare(belief, horizon)")
    horizon = candidates.shape[1]
    if horizon > plan.room:
        raise ValueError(
            f"score_candidates: the belief has room for {plan.room} more steps, "
            f"the candidates have {horizon}; call prepare(belief, horizon={horizon})"
        )
    keys = jax.random.split(key, num_draws)
    dtype = plan.belief.mean.dtype
    return _score(plan, jnp.asarray(candidates, dtype=dtype), keys, jnp.asarray(logdet_weight, float))


def arc_candidates(
    num: int, horizon: int, step_length: float = 1.0, max_turn: float = 0.6, key: PRNGKeyArray | None = None
) -> Float[Array, "C H 3"]:
    """A batch of action sequences: constant-curvature arcs, and (with ``key``) random turns.

    Each action is ``[step_length, 0, turn]``. Without ``key``: ``num`` arcs with turns evenly
    spaced in ``[-max_turn, max_turn]``. With ``key``: the first ``num // 2`` are those arcs, the rest
    have independent uniform turns per step.
    """
    n_arcs = num if key is None else max(num // 2, 1)
    turns = jnp.linspace(-max_turn, max_turn, n_arcs)[:, None] * jnp.ones((1, horizon))
    if key is not None and num > n_arcs:
        turns = jnp.concatenate([turns, jax.random.uniform(key, (num - n_arcs, horizon), minval=-max_turn,
                                                           maxval=max_turn)])
    forward = jnp.full(turns.shape, step_length)
    return jnp.stack([forward, jnp.zeros_like(turns), turns], axis=-1)


# --------------------------------------------------------------------------- #
# Gradient-based refinement of one action sequence
# --------------------------------------------------------------------------- #


def turn_actions(params: Float[Array, " H"], step_length, max_turn) -> Float[Array, "H 3"]:
    """Actions ``[step_length, 0, max_turn · tanh(p_t)]``: any real ``params`` give a feasible turn."""
    turns = max_turn * jnp.tanh(params)
    return jnp.stack([jnp.full_like(turns, step_length), jnp.zeros_like(turns), turns], axis=-1)


def expected_objective(plan: Plan, actions: Float[Array, "H 3"], keys: Key[Array, " S"] | UInt32[Array, "S 2"],
                       logdet_weight=0.0):
    """Mean :func:`objective` over the observation draws ``keys`` (vmapped; a smooth function of
    ``actions`` for a fixed set of detected objects when the sensor uses the smooth visibility)."""

    def one_draw(key):
        k_pred, k_step = jax.random.split(key)
        odometry, detections = predict_observations(plan.belief, actions, k_pred)
        return objective(rollout(plan, odometry, detections, k_step), logdet_weight)

    return jnp.mean(jax.vmap(one_draw, axis_name=PLAN_AXIS)(keys))


class Refined(eqx.Module):
    """What :func:`refine_actions` returns."""

    actions: Float[Array, "H 3"]  # the refined sequence
    initial: Float[Array, ""]  # expected objective of the start sequence (on the same draws)
    final: Float[Array, ""]  # ... and of the refined one
    steps: Int[Array, ""]  # optimizer iterations taken
    result: optx.RESULTS  # the solver's verdict (a failed line search keeps the best point reached)


@eqx.filter_jit
def _refine(plan, params0, keys, step_length, max_turn, logdet_weight, max_steps: int):
    @jax.jit  # traced once: BFGS differentiates its jaxpr, and the two ends below call it again
    def objective_of(params):
        return expected_objective(plan, turn_actions(params, step_length, max_turn), keys, logdet_weight)

    def fn(params, _):
        return objective_of(params)

    solver = optx.BFGS(rtol=1e-4, atol=1e-4)
    sol = optx.minimise(fn, solver, params0, max_steps=max_steps, throw=False)
    # Both ends in one mapped call: one more copy of the rollout in the program, not two.
    initial, final = jax.lax.map(lambda p: fn(p, None), jnp.stack([params0, sol.value]))
    # BFGS only accepts descent steps, but a capped run can stop anywhere: never return worse.
    params = jnp.where(final <= initial, sol.value, params0)
    return Refined(turn_actions(params, step_length, max_turn), initial, jnp.minimum(final, initial),
                   sol.stats["num_steps"], sol.result)


def refine_actions(
    plan: Plan,
    turns: Float[Array, " H"],
    key: PRNGKeyArray,
    *,
    step_length: float = 1.0,
    max_turn: float = 0.6,
    num_draws: int = 4,
    logdet_weight: float = 0.0,
    max_steps: int = 20,
) -> Refined:
    """Refine the turn rates of one action sequence by gradient descent on the expected objective.

    The actions are ``[step_length, 0, turn_t]`` with ``|turn_t| < max_turn`` (a ``tanh``
    parameterization keeps them feasible). The objective is the mean of :func:`objective` (``H(w)
    + λ log det Σ``) over ``num_draws`` predicted worlds and noise draws, fixed for the whole run
    (common random numbers), so it is a deterministic function of the turns; it is minimized by
    :class:`optimistix.BFGS` with exact reverse-mode gradients through the predicted observations,
    the ``H`` belief updates (Gauss-Newton by implicit differentiation) and the weights.

    ``plan`` must come from :func:`prepare` with a ``visibility_temperature``: under the
    paper's 0/1 visibility the weights are piecewise constant in the pose and the gradient says
    little. What stays discrete (and is not differentiated): which objects the predicted robot
    detects, pruning and top-K (``docs/gradients.md``). Start from the best scored candidate of
    :func:`score_candidates` to combine global search with local refinement.
    """
    if not isinstance(plan, Plan):
        raise ValueError("refine_actions: pass a plan from hybridslam.planning.prepare(belief, horizon, ...)")
    belief = plan.belief
    if belief.model.sensor.visibility_temperature is None:
        raise ValueError(
            "refine_actions: the belief uses the hard 0/1 visibility, whose gradient is zero almost everywhere; "
            "call prepare(belief, horizon, visibility_temperature=...) (e.g. 0.5 m)"
        )
    turns = jnp.asarray(turns, dtype=belief.mean.dtype)
    if turns.ndim != 1 or turns.shape[0] > plan.room:
        raise ValueError(f"refine_actions: expected turns of shape (H,) with H <= {plan.room}, got shape {turns.shape}")
    if not 0.0 < max_turn:
        raise ValueError(f"refine_actions: max_turn must be positive, got {max_turn}")
    params0 = jnp.arctanh(jnp.clip(turns / max_turn, -0.999, 0.999))
    keys = jax.random.split(key, num_draws)
    f = lambda v: jnp.asarray(v, dtype=belief.mean.dtype)  # noqa: E731
    return _refine(plan, params0, keys, f(step_length), f(max_turn), f(logdet_weight), max_steps)
