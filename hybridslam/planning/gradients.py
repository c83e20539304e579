"""Differentiable objectives of a hybrid belief, and a differentiable multi-step rollout.

The step (Algorithm 1) is differentiable in its continuous inputs: the odometry ``u_k``, the model
parameters (classifier ``alpha``/``K`` or a learned model's weights, ``Σ_w``, ``Σ_v``, visibility
temperatures) and the belief's weights, means and covariances (hence the priors of Eq. 3).
What is differentiated is the belief *given* its discrete structure: which children survive
pruning and in which slot, which children the laplace-is screen keeps, and which component is
the best are choices, held fixed (gradients of the surviving components are exact). The paper's
0/1 visibility has zero gradient almost everywhere; use the smooth object observation model
(:func:`hybridslam.with_smooth_visibility`) when visibility should carry gradient. See
``docs/gradients.md``.

Every functional here takes one :class:`~hybridslam.belief.Belief` and returns a scalar; all
are jit- and vmap-able.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.special import logsumexp
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..analysis.marginals import association_probabilities
from ..driver import Inputs, Trace, scan
from ..inference.ties import best_slot
from ..estimators.hybrid.belief import Belief
from ..estimators.hybrid.estimator import Hybrid
from ..models.measurement import Detections


def expected_association_entropy(belief: Belief) -> Float[Array, ""]:
    """``H = −Σ_β P(β_1:k | H_k) log P(β_1:k | H_k)`` (Eq. 8): the expectation, over the belief's
    association hypotheses, of their surprise.

    Equal to :func:`hybridslam.association_entropy`, without its clamp at 0 (which only hides
    rounding), so it is smooth wherever the surviving components do not change.
    """
    p = association_probabilities(belief)
    alive = belief.alive
    w = jnp.where(alive, belief.weights, 0.0)
    return -jnp.sum(jnp.where(alive, w * jnp.log(jnp.where(alive, p, 1.0)), 0.0))


def hypothesis_neg_log_weight(belief: Belief, history: Int[Array, "T Dmax"]) -> Float[Array, ""]:
    """``−log P(β_1:t = history | H_k)`` (Eq. 8): the negative log total weight of the components
    whose association history starts with ``history`` (``t`` steps, ``-1`` for an empty slot).

    ``+inf`` (with a zero gradient) if no surviving component has that history.
    """
    t = history.shape[0]
    if t > belief.history.shape[1]:
        raise ValueError(f"history: {t} steps, but the belief keeps only {belief.history.shape[1]}")
    match = belief.alive & jnp.all(belief.history[:, :t] == history[None], axis=(1, 2))
    some = jnp.any(match)
    log_w = jnp.where(match & some, belief.log_weights, jnp.where(some, -jnp.inf, 0.0))
    return jnp.where(some, -logsumexp(log_w), jnp.inf)


def best_pose_log_det(belief: Belief, position_only: bool = False) -> Float[Array, ""]:
    """``log det Σ`` of the robot pose ``x_k`` (3×3; the 2×2 position block if ``position_only``) of
    the highest-weight component. Which component is best is a discrete choice (not differentiated)."""
    best = best_slot(belief.log_weights)
    d = 2 if position_only else 3
    chol = jnp.linalg.cholesky(belief.cov[best, :d, :d])
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))


def expected_position_error(
    belief: Belief, true_position: Float[Array, "2"], squared: bool = False
) -> Float[Array, ""]:
    """Expected error of the robot position against ``true_position`` (the first two entries of a pose).

    ``squared=False``: ``Σ_i w_i ‖μ_i − p‖``, the weight-averaged error of the component means
    (the ``err_wavg`` metric, Sec. V). ``squared=True``: the mixture expectation
    ``E‖x_k − p‖² = Σ_i w_i (‖μ_i − p‖² + tr Σ_i)`` (position block), which also rewards a
    smaller covariance and is smooth everywhere.
    """
    w = jnp.where(belief.alive, belief.weights, 0.0)
    diff = belief.mean[:, :2] - jnp.asarray(true_position)[None, :2]
    sq = jnp.sum(diff**2, axis=-1)
    if squared:
        per = sq + jnp.trace(belief.cov[:, :2, :2], axis1=-2, axis2=-1)
    else:
        nonzero = sq > 0.0  # double where: ‖·‖ has no gradient at 0, and must not give NaN
        per = jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)
    return jnp.sum(jnp.where(belief.alive, w * per, 0.0))


def rollout(
    estimator: Hybrid, belief: Belief, odometry: Float[Array, "T 3"], detections: Detections, key: PRNGKeyArray
) -> tuple[Belief, Trace]:
    """Run ``T`` steps of Algorithm 1 with the driver's ``lax.scan``: pure and differentiable.

    ``detections`` has a leading time axis (see :func:`hybridslam.stacked_detections`); step ``k``
    of the rollout draws with ``fold_in(key, belief.k + k - 1)``, as :func:`hybridslam.run` does, so
    a rollout from the initial belief reproduces a run with the same key. Returns the final belief
    and the per-step :class:`~hybridslam.driver.Trace`. Not jitted itself: jit (or ``jax.grad``) the
    function that calls it.
    """
    t = odometry.shape[0]
    steps = belief.k + jnp.arange(t, dtype=jnp.int32)
    inputs = Inputs(odometry, detections, steps, jnp.full((t, 3), jnp.nan, odometry.dtype), jnp.ones(t, bool))
    return scan(estimator, belief, inputs, key)
