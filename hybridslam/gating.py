"""Association gating: the few objects a detection may be associated with, per component.

Enumerating every injective assignment of a step's detections to ``N`` objects is exponential in
the detections and grows as ``N^Dmax``; in a map of tens of objects it cannot be done. Gating
(thesis Sec. 3.2.1: hypotheses of negligible likelihood are not enumerated) keeps, for each
detection and each parent component, the ``G`` existing objects of lowest Mahalanobis distance of
the geometric innovation

    d² = (z − h(x̄, ō))ᵀ S⁻¹ (z − h(x̄, ō)),    S = H P Hᵀ + Σ_v              (thesis Eq. 4.14-4.15)

(``H``: the Jacobian of range and bearing in the robot pose and the object; ``P``: their joint
prior covariance). The hypothesis table then runs over candidate ranks (:mod:`hypotheses`). Every
child outside the gate gets weight 0: an approximation, exact whenever the left-out children would
have been pruned anyway (their objects are far more than the pruning ratio less likely).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .belief import Detections
from .geometry import geometric_residual, range_bearing
from .measurement import SensorModel


def _predicted(sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], n: Int[Array, ""]):
    """Predicted range-bearing of object ``n`` and its innovation covariance ``S`` (thesis Eq. 4.14)."""
    idx = jnp.concatenate([jnp.arange(3), 3 + 3 * n + jnp.arange(3)])
    y = mean[idx]
    h = lambda v: range_bearing(v[:3], v[3:])  # noqa: E731
    jac = jax.jacfwd(h)(y)
    return h(y), jac @ cov[idx][:, idx] @ jac.T + sensor.geometric_cov


def mahalanobis(
    sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], detections: Detections
) -> Float[Array, "Dmax N"]:
    """``d²`` of every (detection, object) pair of one component."""
    n = mean.shape[0] // 3 - 1
    pred, s = jax.vmap(_predicted, (None, None, None, 0))(sensor, mean, cov, jnp.arange(n))

    def one(z, p, s_):
        d = geometric_residual(z, p)
        return d @ jnp.linalg.solve(s_, d)

    return jax.vmap(jax.vmap(one, (None, 0, 0)), (0, None, None))(detections.geo, pred, s)


def gate(
    sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], detections: Detections,
    num_created: Int[Array, ""] | None, num_candidates: int,
) -> Int[Array, "Dmax G"]:
    """The ``G`` existing objects (index ``< num_created``; all if ``None``) of lowest ``d²`` per detection.

    With fewer than ``G`` existing objects the tail names uncreated ones, which
    :func:`hybridslam.hypotheses.resolve` rules out.
    """
    d2 = mahalanobis(sensor, mean, cov, detections)
    d2 = jnp.where(jnp.isnan(d2), jnp.inf, d2)
    if num_created is not None:
        d2 = jnp.where(jnp.arange(d2.shape[1])[None, :] < num_created, d2, jnp.inf)
    return jax.lax.top_k(-d2, num_candidates)[1].astype(jnp.int32)
