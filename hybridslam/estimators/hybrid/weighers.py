"""PropWeights strategies (Eq. 16): how the hybrid belief estimates the likelihood factor of each child.

A weigher is an ``equinox.Module`` whose fields are its (static) settings, validated when it is
built, with one method :meth:`AbstractWeigher.weigh`. :class:`~hybridslam.estimators.hybrid.Hybrid`
takes one (``Hybrid(weights=LaplaceIS(samples=256))``), the way optimistix solvers take a descent:

* :class:`Sampled` — the paper's Monte-Carlo mean over ``n_s`` draws from the propagated belief;
* :class:`Linearized` — deterministic: the Gaussian marginal likelihood of the linearized
  measurement model (thesis Eq. 4.14-4.15) times the probability that the named objects are in view;
* :class:`LaplaceIS` (the default) — importance sampling from each child's Laplace approximation,
  for the children the linearized weights rank best.

The formulas live in :mod:`.weights`; this module only chooses and configures them.
"""

from __future__ import annotations

import abc
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ...inference.batching import map_live
from ...models.measurement import Detections, SensorModel
from .hypotheses import Children, HypothesisTable
from .branching import FlatChildren
from .weights import (
    laplace_is_children,
    laplace_is_log_likelihood,
    linearized_log_likelihood,
    sampled_children,
    sampled_log_likelihood,
)

# A child whose objects are (almost surely) out of view still ranks by its likelihood when the
# laplace-is candidates are screened, this many nats below any child in view.
_SCREEN_OUT_OF_VIEW = 50.0


class Weights(NamedTuple):
    """Per child ``(K, A, Mc)``: ``log ψ`` with and without the observation model, the normalized
    ESS of each estimate, and whether each laplace-is mode search converged (True otherwise)."""

    log_lik: Float[Array, "K A Mc"]
    log_lik_free: Float[Array, "K A Mc"]
    ess: Float[Array, "K A Mc"]
    converged: Bool[Array, "K A Mc"]


class Context(NamedTuple):
    """What every weigher reads: the propagated parents and the step's children."""

    sensor: SensorModel
    alive: Bool[Array, " K"]
    mean: Float[Array, "K D"]
    cov: Float[Array, "K D D"]
    detections: Detections
    table: HypothesisTable
    kids: Children
    prior: Float[Array, "K A Mc"]  # every factor of a child's weight that does not depend on the Gaussian
    gn_max_steps: int
    batch_axis: str | None


def _positive_int(owner: str, name: str, value) -> None:
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        raise ValueError(f"{owner}.{name}: expected a positive int, got {value!r}")


class AbstractWeigher(eqx.Module):
    """A PropWeights estimator of Eq. 16."""

    name: ClassVar[str]

    @abc.abstractmethod
    def weigh(self, ctx: Context, key: PRNGKeyArray) -> Weights:
        """``log ψ`` of every child of the exhaustive table (see :class:`Weights`)."""

    @abc.abstractmethod
    def weigh_children(self, sensor: SensorModel, alive: Bool[Array, " K"], mean: Float[Array, "K D"],
                       cov: Float[Array, "K D D"], detections: Detections, ch: FlatChildren, gn_max_steps: int,
                       batch_axis: str | None, key: PRNGKeyArray) -> Weights:
        """``log ψ`` of a flat list of children (those a :class:`~.branching.Beam` kept)."""

    @property
    def draws(self) -> int:
        """Monte-Carlo draws per estimate (0 for a deterministic weigher)."""
        return 0


class Sampled(AbstractWeigher):
    """The paper's estimator: the mean over ``samples`` (``n_s``) draws from each parent's propagated
    Gaussian, common random numbers for every child (:func:`.weights.sampled_log_likelihood`)."""

    samples: int = eqx.field(default=1000, static=True)
    name = "sampled"

    def __check_init__(self):
        _positive_int("Sampled", "samples", self.samples)

    @property
    def draws(self) -> int:
        return self.samples

    def weigh(self, ctx: Context, key: PRNGKeyArray) -> Weights:
        eps = jax.random.normal(key, (self.samples, ctx.mean.shape[-1]), dtype=ctx.mean.dtype)
        one = lambda m, c, kid: sampled_log_likelihood(ctx.sensor, m, c, ctx.detections, eps, ctx.table, kid)  # noqa: E731
        log_lik, log_lik_free, ess = map_live(one, ctx.alive, ctx.mean, ctx.cov, ctx.kids, axis_name=ctx.batch_axis)
        return Weights(log_lik, log_lik_free, ess, jnp.ones(ess.shape, bool))

    def weigh_children(self, sensor, alive, mean, cov, detections, ch, gn_max_steps, batch_axis, key) -> Weights:
        eps = jax.random.normal(key, (self.samples, mean.shape[-1]), dtype=mean.dtype)
        log_lik, log_lik_free, ess = sampled_children(sensor, mean, cov, detections, eps, alive, ch.parent,
                                                      ch.measured, ch.slot_class, axis_name=batch_axis)
        return Weights(log_lik, log_lik_free, ess, jnp.ones(ess.shape, bool))


def _linearized(ctx: Context) -> Weights:
    one = lambda m, c, kid: linearized_log_likelihood(ctx.sensor, m, c, ctx.detections, ctx.table, kid,  # noqa: E731
                                                      axis_name=ctx.batch_axis)
    log_lik, log_lik_free, ess = map_live(one, ctx.alive, ctx.mean, ctx.cov, ctx.kids, axis_name=ctx.batch_axis)
    return Weights(log_lik, log_lik_free, ess, jnp.ones(ess.shape, bool))


class Linearized(AbstractWeigher):
    """Deterministic: ``N(r̄; 0, JΣJᵀ + I)`` on the whitened residuals of the child's detections
    jointly, times the in-view probability (:func:`.weights.linearized_log_likelihood`)."""

    name = "linearized"

    def weigh(self, ctx: Context, key: PRNGKeyArray) -> Weights:
        del key
        return _linearized(ctx)

    def weigh_children(self, sensor, alive, mean, cov, detections, ch, gn_max_steps, batch_axis, key) -> Weights:
        del key  # the branching already scored every child by its joint linearized weight
        return Weights(ch.linear, ch.linear_free, jnp.ones(ch.linear.shape), jnp.ones(ch.linear.shape, bool))


class LaplaceIS(AbstractWeigher):
    """Importance sampling from each child's Laplace approximation (:mod:`hybridslam.inference.laplace`).

    The children are ranked by their linearized weight; the best ``candidates`` of them that lie
    within ``screen_nats`` of the best (``e^-15 ≈ 3e-7``: ten nats below the pruning threshold
    ``w_max/150 ≈ e^-5``, room for the linearization's error) get ``samples`` draws each; the rest
    would be pruned anyway. 64 draws per child estimate Eq. 16 about as well as the paper's sampled
    estimator with several thousand (docs/weights.md).
    """

    samples: int = eqx.field(default=64, static=True)
    candidates: int = eqx.field(default=128, static=True)
    screen_nats: float = eqx.field(default=15.0, static=True)
    name = "laplace-is"

    def __check_init__(self):
        _positive_int("LaplaceIS", "samples", self.samples)
        _positive_int("LaplaceIS", "candidates", self.candidates)
        if not (isinstance(self.screen_nats, (int, float)) and self.screen_nats > 0):
            raise ValueError(f"LaplaceIS.screen_nats: expected a positive number, got {self.screen_nats!r}")

    @property
    def draws(self) -> int:
        return self.samples

    def weigh(self, ctx: Context, key: PRNGKeyArray) -> Weights:
        linear = _linearized(ctx)
        slots = ctx.detections.mask.shape[0]
        eps = jax.random.normal(key, (self.samples, 3 + 3 * slots), dtype=ctx.mean.dtype)
        rank = jnp.maximum(linear.log_lik, linear.log_lik_free - _SCREEN_OUT_OF_VIEW)
        screen = jnp.where(ctx.kids.valid & ctx.alive[:, None, None], ctx.prior + rank, -jnp.inf)
        # Children hopelessly below the best would be pruned anyway: leaving them out lets the Laplace-IS
        # chunks of empty candidates be skipped (most steps have a handful of serious children).
        screen = jnp.where(screen >= jnp.max(screen) - self.screen_nats, screen, -jnp.inf)
        return Weights(*laplace_is_log_likelihood(
            ctx.sensor, ctx.mean, ctx.cov, ctx.detections, eps, ctx.table, ctx.kids, screen, self.candidates,
            ctx.gn_max_steps, axis_name=ctx.batch_axis,
        ))

    def weigh_children(self, sensor, alive, mean, cov, detections, ch, gn_max_steps, batch_axis, key) -> Weights:
        slots = detections.mask.shape[0]
        eps = jax.random.normal(key, (self.samples, 3 + 3 * slots), dtype=mean.dtype)
        rank = jnp.maximum(ch.linear, ch.linear_free - _SCREEN_OUT_OF_VIEW)
        screen = jnp.where(ch.valid, ch.prior + rank, -jnp.inf)
        screen = jnp.where(screen >= jnp.max(screen) - self.screen_nats, screen, -jnp.inf)
        return Weights(*laplace_is_children(sensor, mean, cov, detections, eps, ch.parent, ch.measured, ch.slot_class,
                                            screen, self.candidates, gn_max_steps, batch_axis))


WEIGHERS: dict[str, type[AbstractWeigher]] = {"laplace-is": LaplaceIS, "sampled": Sampled, "linearized": Linearized}


def make_weigher(name: str, samples: int | None = None) -> AbstractWeigher:
    """A weigher from its command-line name; ``samples`` sets its draws (``None``: its default)."""
    if name not in WEIGHERS:
        raise ValueError(f"weights: expected one of {', '.join(WEIGHERS)}, got {name!r}")
    cls = WEIGHERS[name]
    if cls is Linearized:
        if samples is not None:
            raise ValueError("--samples: the linearized weights draw no samples")
        return Linearized()
    return cls() if samples is None else cls(samples=samples)
