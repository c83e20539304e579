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

import functools
import itertools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..models.geometry import geometric_residual, range_bearing, range_bearing_jacobians
from ..models.measurement import Detections, SensorModel


class Innovations(eqx.Module):
    """The linearized range-bearing prediction of every (detection, object) pair of one component.

    Shared by every estimator's gating: the hybrid belief (:func:`gate`) and Doherty's
    (:mod:`hybridslam.estimators.gaussian`, :mod:`hybridslam.estimators.multimodal`).
    """

    residual: Float[Array, "Dmax N 2"]  # z − h(x̄, ō_n), bearing wrapped
    jac_pose: Float[Array, "N 2 3"]  # ∂h/∂x_k at the mean (the same for every detection)
    jac_object: Float[Array, "N 2 3"]  # ∂h/∂o_n at the mean
    d2: Float[Array, "Dmax N"]  # rᵀ S⁻¹ r, S = H P Hᵀ + Σ_v (thesis Eq. 4.14-4.15); +inf if not finite
    cov: Float[Array, "N 2 2"]  # S of each object (the same for every detection)


def _predicted(sensor: SensorModel, x: Float[Array, "3"], obj: Float[Array, "3"], block: Float[Array, "6 6"]):
    """Predicted range-bearing of one object, its Jacobians and its innovation covariance ``S``."""
    jac_x, jac_o = range_bearing_jacobians(x, obj)
    jac = jnp.concatenate([jac_x, jac_o], axis=-1)
    return range_bearing(x, obj), jac_x, jac_o, jac @ block @ jac.T + sensor.geometric_cov


def _mahalanobis2(r: Float[Array, "2"], s: Float[Array, "2 2"]) -> Float[Array, ""]:
    """``rᵀ S⁻¹ r`` of a symmetric 2×2 ``S``, in closed form (an LU solve would compile a pivoting loop)."""
    det = s[0, 0] * s[1, 1] - s[0, 1] * s[1, 0]
    return (s[1, 1] * r[0] ** 2 - (s[0, 1] + s[1, 0]) * r[0] * r[1] + s[0, 0] * r[1] ** 2) / det


def innovations(
    sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], detections: Detections
) -> Innovations:
    """:class:`Innovations` of one component with state ``[x_k, o_1, ..., o_N]`` (mean and covariance)."""
    x, objs = mean[:3], mean[3:].reshape(-1, 3)
    n = objs.shape[0]
    idx = jnp.concatenate([jnp.broadcast_to(jnp.arange(3), (n, 3)), 3 + 3 * jnp.arange(n)[:, None] + jnp.arange(3)[None, :]],
                          axis=1)  # (N, 6): the robot pose and object n
    blocks = jax.vmap(lambda i: cov[i][:, i])(idx)
    pred, jac_x, jac_o, s = jax.vmap(_predicted, (None, None, 0, 0))(sensor, x, objs, blocks)

    def pair(z, p, s_):
        r = geometric_residual(z, p)
        return r, _mahalanobis2(r, s_)

    r, d2 = jax.vmap(jax.vmap(pair, (None, 0, 0)), (0, None, None))(detections.geo, pred, s)
    return Innovations(r, jac_x, jac_o, jnp.where(jnp.isfinite(d2), d2, jnp.inf), s)


def mahalanobis(
    sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], detections: Detections
) -> Float[Array, "Dmax N"]:
    """``d²`` of every (detection, object) pair of one component."""
    return innovations(sensor, mean, cov, detections).d2


# The chi-square quantile of 2 degrees of freedom at 1 - 1e-6 (its tail is exp(-d²/2)): a correct
# association lies beyond it once in a million detections.
CONTRADICTION_D2 = -2.0 * math.log(1e-6)


def contradicted(
    sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], detections: Detections,
    objects: Int[Array, " Dmax"], unassociated: Bool[Array, " Dmax"],
) -> Bool[Array, ""]:
    """Whether a component's prediction ``(mean, cov)`` contradicts the step's detections: more than
    half of them are unexplained, either left ``unassociated`` (skipped: no clutter hypothesis, no
    new object) or named (``objects[j] >= 0``) with a ``d²`` beyond :data:`CONTRADICTION_D2`.

    A spurious detection makes one such slot; a robot whose pose belief is wrong (kidnapped, or
    odometry that contradicts the detections) makes most of them. Estimators report it per step
    (``StepInfo.inconsistent``) for their best component: the model's best explanation, kept
    because it has no better one.
    """
    x, objs = mean[:3], mean[3:].reshape(-1, 3)
    obj = jnp.maximum(objects, 0)
    pose = jnp.broadcast_to(jnp.arange(3), (obj.shape[0], 3))
    idx = jnp.concatenate([pose, 3 + 3 * obj[:, None] + jnp.arange(3)[None, :]], axis=1)  # (Dmax, 6)

    def slot_d2(z, o, i):  # d² of one detection against the object it names only, not every object
        pred, _, _, s = _predicted(sensor, x, o, cov[i][:, i])
        return _mahalanobis2(geometric_residual(z, pred), s)

    d2 = jax.vmap(slot_d2)(detections.geo, objs[obj], idx)
    named = detections.mask & (objects >= 0)
    far = named & ~(d2 <= CONTRADICTION_D2)  # a non-finite d² contradicts too
    unexplained = jnp.sum(far | (detections.mask & unassociated))
    return 2 * unexplained > jnp.sum(detections.mask)


def nearest(
    d2: Float[Array, "Dmax N"], num_created: Int[Array, ""] | None, num_candidates: int
) -> tuple[Int[Array, "Dmax G"], Float[Array, "Dmax G"]]:
    """The ``G`` existing objects (index ``< num_created``; all if ``None``) of lowest ``d²`` per
    detection, and their ``d²``: ``+inf`` where fewer than ``G`` objects exist (the index is then
    an uncreated object, which every caller rules out)."""
    if num_created is not None:
        d2 = jnp.where(jnp.arange(d2.shape[1])[None, :] < num_created, d2, jnp.inf)
    neg, ids = jax.lax.top_k(-d2, num_candidates)
    return ids.astype(jnp.int32), -neg


def chi2_gate(probability: float) -> float:
    """The chi-square quantile of 2 degrees of freedom (a range-bearing innovation's ``d²``):
    ``−2 log(1 − p)`` (closed form); the gate of thesis Sec. 3.2.1 at probability ``p``."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"gate_probability: expected a number in (0, 1), got {probability!r}")
    return -2.0 * math.log1p(-probability)


def gate(
    sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], detections: Detections,
    num_created: Int[Array, ""] | None, num_candidates: int, max_d2: float = math.inf,
) -> Int[Array, "Dmax G"]:
    """The hybrid belief's gate: the ``G`` nearest existing objects per detection (:func:`nearest`),
    those beyond the squared Mahalanobis distance ``max_d2`` (a chi-square gate, :func:`chi2_gate`;
    ``inf``: none) replaced by the index ``N``, which names no object.

    With fewer than ``G`` existing objects the tail names uncreated ones; :func:`hybridslam.hypotheses.resolve`
    and the beam rule out both (an object index at or beyond the created ones).
    """
    d2 = mahalanobis(sensor, mean, cov, detections)
    ids, near = nearest(d2, num_created, num_candidates)
    return jnp.where(near <= max_d2, ids, d2.shape[1])


@functools.cache
def joint_options(num_candidates: int, slots: int) -> np.ndarray:
    """Every tuple of per-slot options ``0..G`` (a candidate rank, or ``G``: none of them — the null /
    new-object hypothesis, or an empty slot), shape ``((G+1)^Dmax, Dmax)``, lexicographic. Which
    tuples are joint-compatible (injective) depends on the traced candidates, so each estimator
    checks it against its own gate."""
    rows = list(itertools.product(range(num_candidates + 1), repeat=slots))
    return np.asarray(rows, dtype=np.int32).reshape(-1, slots)
