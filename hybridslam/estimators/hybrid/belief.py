"""The hybrid belief ``P(X_k, C, β_1:k | H_k)`` as a fixed-capacity mixture (Eq. 4-5).

Component ``i`` is the pair (weight ``w^C_β1:k``, Gaussian ``b[X_k]^C_β1:k``) of Eq. 5. The
continuous state of a component is the joint Gaussian over the current robot pose and all object
poses, laid out as ``[x_k (3), x^o_1 (3), ..., x^o_N (3)]`` (``D = 3 + 3N``); past robot poses are
marginalized out as the filter moves (see docs/model.md). ``classes[i, n]`` is the
class realization of object ``n`` or ``-1`` while the component has not associated it yet (lazy
realizations, Sec. IV-D). ``history[i, j]`` is ``β_{j+1}`` (object index per detection slot,
``-1`` for an empty slot).

Unknown maps (``model.discovery`` set): ``N`` is the object capacity; ``num_created[i]`` objects
exist in component ``i`` (the prior ones first, then those its detections created, in creation
order); the other slots are placeholders (mean 0, covariance I, uncorrelated,
:mod:`hybridslam.discovery`) whose class stays ``-1``.

Capacity ``K``, the history length and the detection slots are array shapes: static. How many
components are alive is traced (``log_weights > -inf``), so one compiled step serves a whole run.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ...models.scenario import Scenario
from ...models.model import Model
from ..smoothers.kinds import SmootherState


class Priors(eqx.Module):
    """Gaussian priors of Eq. 3 (the class prior lives in :class:`Model`)."""

    robot_mean: Float[Array, "3"]
    robot_cov: Float[Array, "3 3"]
    object_means: Float[Array, "N 3"]
    object_covs: Float[Array, "N 3 3"]
    # Unknown maps: how many of the N slots hold prior objects (the rest are uncreated placeholders).
    num_known: Int[Array, ""] | None = None


class Belief(eqx.Module):
    """A hybrid belief with capacity ``K`` (see the module docstring for the layout)."""

    log_weights: Float[Array, " K"]  # log w^C_β1:k; -inf marks an empty slot
    mean: Float[Array, "K D"]
    cov: Float[Array, "K D D"]
    classes: Int[Array, "K N"]  # class realization, -1 = open (Sec. IV-D)
    history: Int[Array, "K T Dmax"]  # β_1:k
    k: Int[Array, ""]  # steps taken so far
    model: Model
    num_created: Int[Array, " K"] | None = None  # objects that exist per component (unknown maps only)
    # What the smoother keeps (Hybrid(smoother=Full() or Lag(L))): each component's trajectory
    # x_0..x_T, the data so far, with Lag(L) each component's window prior; empty under Filter().
    smoothing: SmootherState = SmootherState()
    # Unknown maps: τ of new_landmark="mahalanobis:TAU" (thesis Sec. 3.2.1, ..novelty), inf under
    # the density rule; traced, so every rule and τ share one compiled step.
    new_landmark_tau: Float[Array, ""] | None = None

    @property
    def alive(self) -> Bool[Array, " K"]:
        return self.log_weights > -jnp.inf

    @property
    def num_objects(self) -> int:
        return self.classes.shape[-1]

    @property
    def capacity(self) -> int:
        """``K``, the most components kept after pruning."""
        return self.log_weights.shape[0]

    @property
    def max_steps(self) -> int:
        """The length of the association history (steps the belief can take)."""
        return self.history.shape[1]

    @property
    def max_detections(self) -> int:
        """Detection slots per step."""
        return self.history.shape[2]

    @property
    def weights(self) -> Float[Array, " K"]:
        return jnp.exp(self.log_weights)


def priors_from_scenario(scenario: Scenario) -> Priors:
    """The priors of Eq. 3; with ``discovery``, padded to ``max_objects`` slots by uncreated placeholders."""
    f = lambda a: jnp.asarray(a, dtype=float)  # noqa: E731
    means, covs = f(scenario.object_prior_means), f(scenario.object_prior_covs)
    if scenario.discovery is None:
        return Priors(f(scenario.robot_prior_mean), f(scenario.robot_prior_cov), means, covs)
    extra = scenario.discovery.max_objects - scenario.num_objects
    means = jnp.concatenate([means, jnp.zeros((extra, 3))])
    covs = jnp.concatenate([covs, jnp.broadcast_to(jnp.eye(3), (extra, 3, 3))])
    return Priors(f(scenario.robot_prior_mean), f(scenario.robot_prior_cov), means, covs,
                  jnp.asarray(scenario.num_objects, dtype=jnp.int32))


def init_belief(priors: Priors, model: Model, capacity: int, max_steps: int, max_detections: int) -> Belief:
    """The belief before any step: one component of weight 1, every class open (Eq. 3).

    ``capacity`` (K components), ``max_steps`` (the length of the association history) and
    ``max_detections`` (detection slots per step) fix its shapes.

    Empty slots hold copies of that component with ``log_weight = -inf`` so that the batched
    computations on them stay finite. With ``model.discovery`` the components start with
    ``priors.num_known`` objects (all ``N`` if it is ``None``).
    """
    n = priors.object_means.shape[0]
    if model.class_prior.shape[0] != n:
        raise ValueError(f"class_prior has {model.class_prior.shape[0]} rows for {n} objects")
    log_weights, mean, cov, classes, history, k = _initial_arrays(
        priors.robot_mean, priors.robot_cov, priors.object_means, priors.object_covs, capacity, max_steps,
        max_detections)
    return Belief(
        log_weights=log_weights, mean=mean, cov=cov, classes=classes, history=history, k=k, model=model,
        num_created=None if model.discovery is None else jnp.full(
            (capacity,), n if priors.num_known is None else priors.num_known, dtype=jnp.int32),
    )


# One program per shape (traced through when the priors are, e.g. under jax.grad): run eagerly, each
# of these array operations would compile a small program of its own in a fresh process.
@functools.partial(jax.jit, static_argnums=(4, 5, 6))
def _initial_arrays(robot_mean, robot_cov, object_means, object_covs, capacity: int, max_steps: int,
                    max_detections: int):
    n = object_means.shape[0]
    dim = 3 + 3 * n
    mean = jnp.concatenate([robot_mean, object_means.reshape(-1)])
    block = 3 + 3 * jnp.arange(n)[:, None] + jnp.arange(3)[None, :]  # (n, 3): object i's rows
    cov = jnp.zeros((dim, dim), dtype=mean.dtype).at[:3, :3].set(robot_cov)
    cov = cov.at[block[:, :, None], block[:, None, :]].set(object_covs)  # every object's block at once
    k = capacity
    # Explicit dtypes: a weakly typed initial belief would retrace the step after step 1.
    return (jnp.full((k,), -jnp.inf, dtype=mean.dtype).at[0].set(0.0), jnp.broadcast_to(mean, (k, dim)),
            jnp.broadcast_to(cov, (k, dim, dim)), jnp.full((k, n), -1, dtype=jnp.int32),
            jnp.full((k, max_steps, max_detections), -1, dtype=jnp.int32), jnp.zeros((), dtype=jnp.int32))
