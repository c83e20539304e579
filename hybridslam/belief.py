"""The hybrid belief ``P(X_k, C, β_1:k | H_k)`` as a fixed-capacity mixture (Eq. 4-5).

Component ``i`` is the pair (weight ``w^C_β1:k``, Gaussian ``b[X_k]^C_β1:k``) of Eq. 5. The
continuous state of a component is the joint Gaussian over the current robot pose and all object
poses, laid out as ``[x_k (3), x^o_1 (3), ..., x^o_N (3)]`` (``D = 3 + 3N``); past robot poses are
marginalized out as the filter moves (see README, "Model conventions"). ``classes[i, n]`` is the
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

import dataclasses
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .model import Model
from .scenario import Scenario, StackedSteps

WeightMethod = Literal["sampled", "linearized", "laplace-is"]
WEIGHT_METHODS = ("sampled", "linearized", "laplace-is")


@dataclasses.dataclass(frozen=True)
class Config:
    """Static settings: each fixes a shape or a code path, so changing one recompiles."""

    capacity: int = 64  # K, the most components kept after pruning
    max_detections: int = 2  # detection slots per step (steps are padded to this)
    max_steps: int = 10  # length of the association history kept per component
    num_samples: int = 1000  # n_s of PropWeights (Eq. 16), weights="sampled"
    is_samples: int = 256  # draws per candidate child of weights="laplace-is"
    is_candidates: int = 128  # children (of all parents) that get a Laplace-IS weight, by linearized rank
    # ... and only those within this many nats of the best child's linearized weight (e^-30 ≈ 1e-13:
    # far below the pruning threshold w_max/150 ≈ e^-5); the others would be pruned anyway.
    is_screen_nats: float = 30.0
    weights: WeightMethod = "laplace-is"  # "sampled" is the paper's Eq. 16 estimator (README, Weights)
    gn_max_steps: int = 20  # Gauss-Newton iteration budget of the update (Eq. 9)
    # Association gating (thesis Sec. 3.2.1): each detection may only be associated with the G
    # objects of lowest Mahalanobis distance of its innovation (per component), or a new object.
    # Children outside the gate get weight 0. None: every object (the exact enumeration).
    gate_candidates: int | None = None
    # Name of an enclosing jax.vmap axis over beliefs (set by hybridslam.sweep): lets the step skip
    # work on component slots that are empty in every belief of the batch (batching.map_live).
    batch_axis: str | None = None

    def __post_init__(self):
        for name in ("capacity", "max_detections", "max_steps", "num_samples", "is_samples", "is_candidates", "gn_max_steps"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"Config.{name}: expected a positive int, got {value!r}")
        if not (isinstance(self.is_screen_nats, (int, float)) and self.is_screen_nats > 0):
            raise ValueError(f"Config.is_screen_nats: expected a positive number, got {self.is_screen_nats!r}")
        if self.weights not in WEIGHT_METHODS:
            raise ValueError(f"Config.weights: expected one of {WEIGHT_METHODS}, got {self.weights!r}")
        if self.gate_candidates is not None and not (isinstance(self.gate_candidates, int) and self.gate_candidates >= 1):
            raise ValueError(f"Config.gate_candidates: expected a positive int or None, got {self.gate_candidates!r}")
        if self.batch_axis is not None and not isinstance(self.batch_axis, str):
            raise ValueError(f"Config.batch_axis: expected a vmap axis name (str) or None, got {self.batch_axis!r}")


class Detections(eqx.Module):
    """The detections ``Z_k`` of one step, padded to ``Config.max_detections`` slots."""

    geo: Float[Array, "Dmax 2"]  # [range, bearing]
    scores: Float[Array, "Dmax M"]  # classifier output z^sem (Eq. 1)
    mask: Bool[Array, " Dmax"]  # which slots hold a detection


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
    config: Config = eqx.field(static=True)
    num_created: Int[Array, " K"] | None = None  # objects that exist per component (unknown maps only)

    @property
    def alive(self) -> Bool[Array, " K"]:
        return self.log_weights > -jnp.inf

    @property
    def num_objects(self) -> int:
        return self.classes.shape[-1]

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


def init_belief(priors: Priors, model: Model, config: Config = Config()) -> Belief:
    """The belief before any step: one component of weight 1, every class open (Eq. 3).

    Empty slots hold copies of that component with ``log_weight = -inf`` so that the batched
    computations on them stay finite. With ``model.discovery`` the components start with
    ``priors.num_known`` objects (all ``N`` if it is ``None``).
    """
    n = priors.object_means.shape[0]
    if model.class_prior.shape[0] != n:
        raise ValueError(f"class_prior has {model.class_prior.shape[0]} rows for {n} objects")
    dim = 3 + 3 * n
    mean = jnp.concatenate([priors.robot_mean, priors.object_means.reshape(-1)])
    cov = jnp.zeros((dim, dim), dtype=mean.dtype).at[:3, :3].set(priors.robot_cov)
    for i in range(n):  # n blocks, built once at init (not per component)
        cov = cov.at[3 + 3 * i : 6 + 3 * i, 3 + 3 * i : 6 + 3 * i].set(priors.object_covs[i])
    k = config.capacity
    return Belief(
        # Explicit dtypes: a weakly typed initial belief would retrace the step after step 1.
        log_weights=jnp.full((k,), -jnp.inf, dtype=mean.dtype).at[0].set(0.0),
        mean=jnp.broadcast_to(mean, (k, dim)),
        cov=jnp.broadcast_to(cov, (k, dim, dim)),
        classes=jnp.full((k, n), -1, dtype=jnp.int32),
        history=jnp.full((k, config.max_steps, config.max_detections), -1, dtype=jnp.int32),
        k=jnp.zeros((), dtype=jnp.int32),
        model=model,
        config=config,
        num_created=None if model.discovery is None else jnp.full(
            (k,), n if priors.num_known is None else priors.num_known, dtype=jnp.int32),
    )


def stacked_detections(stacked: StackedSteps) -> Detections:
    """All steps of a scenario as one :class:`Detections` with a leading time axis ``T``."""
    return Detections(
        jnp.asarray(stacked.geo, dtype=float), jnp.asarray(stacked.scores, dtype=float),
        jnp.asarray(stacked.mask),
    )

