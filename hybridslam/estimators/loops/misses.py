"""Negative information of a loop-closure hypothesis: the log-likelihood of the (step, object) pairs
that were in the sensor's footprint yet not detected.

The papers' sensor model detects every object (Tchuiev et al. Eq. 10 has no miss); the loop-closure
search (:mod:`.closure`, :mod:`.online`) adds the detection model of multi-target tracking
(Bar-Shalom's ``P_D``, the validation literature's negative information): an object inside the
footprint at step ``t`` is detected with probability ``p_d``, so a pair with no detection
associated to it has likelihood ``1 − p_d · P(in view)``. A merge that moves an object into the
path of poses that did not see it pays for each such pair.

``P(in view)`` is read one of two ways (``LoopClosureSettings.misses``):

- ``"marginal"`` (:func:`in_view_probability`): under the Laplace posterior of the solved graph,
  the range and bearing of object ``j`` from pose ``x_t`` linearized in ``(x_t, o_j)`` jointly (their
  cross-covariance included, :func:`~hybridslam.inference.smoother.covariances`), and the footprint
  ``range < max_range``, ``|bearing| < fov / 2`` taken as independent in the two;
- ``"point"`` (:func:`point_in_view`): 1 where the solved object lies inside the solved pose's
  footprint by ``fov_margin`` (m, rad), else 0.

Each pair's likelihood is floored at ``min_miss_probability``: a sensor that never misses
(``p_d = 1``) would otherwise rule out any hypothesis with one miss.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtr
from jaxtyping import Array, Float

from ...inference import smoother as sm
from ...models.scenario import Scenario
from ...models.geometry import range_bearing, range_bearing_jacobians
from .settings import LoopClosureSettings


def in_view_probability(solution: sm.Solution, max_range: Float[Array, ""] | float,
                        fov: Float[Array, ""] | float) -> Float[Array, "P N"]:
    """``P(o_j inside the footprint of x_t)`` for every pose ``t`` and object slot ``j`` (m, rad):
    ``Φ((R − r̂)/σ_r) · (Φ((F/2 − b̂)/σ_b) − Φ((−F/2 − b̂)/σ_b))``, ``(r̂, b̂)`` the range and bearing
    at the solution and ``σ`` from ``J Σ Jᵀ`` over ``(x_t, o_j)`` (module docstring). A field of
    view of ``2π`` or more passes every bearing. Jit-able; inactive slots' values are meaningless."""
    cov = sm.covariances(solution)
    p, n = solution.poses.shape[0], solution.objects.shape[0]
    half = jnp.asarray(fov) / 2

    def one(x, o, s_xx, s_xo, s_oo):
        mean = range_bearing(x, o)  # Eq. 10's h^geo
        jac = jnp.concatenate(range_bearing_jacobians(x, o), axis=1)  # (2, 6): pose, object
        joint = jnp.block([[s_xx, s_xo], [s_xo.T, s_oo]])
        var = jnp.maximum(jnp.diagonal(jac @ joint @ jac.T), 1e-12)
        sd = jnp.sqrt(var)
        in_range = ndtr((max_range - mean[0]) / sd[0])
        in_bearing = jnp.where(half >= math.pi, 1.0,
                               ndtr((half - mean[1]) / sd[1]) - ndtr((-half - mean[1]) / sd[1]))
        return in_range * in_bearing

    s_po = cov.pose_object.reshape(p, 3, n, 3)
    j = jnp.arange(n)
    s_oo = cov.objects.reshape(n, 3, n, 3)[j, :, j, :]  # each object's own block, (N, 3, 3)
    per_object = jax.vmap(one, in_axes=(None, 0, None, 0, 0))  # over j
    return jax.vmap(per_object, in_axes=(0, None, 0, 0, None))(
        solution.poses, solution.objects, cov.poses, jnp.moveaxis(s_po, 2, 1), s_oo)


def uses_marginal(settings: LoopClosureSettings) -> bool:
    """Whether :func:`in_view_probability` is needed: the marginal test with a detection probability
    (``settings`` decided by ``for_scenario``). A solve skips it otherwise."""
    return settings.misses == "marginal" and bool(settings.detection_probability)


def point_in_view(scenario: Scenario, poses: np.ndarray, objects: np.ndarray,
                  margin: tuple[float, float]) -> np.ndarray:
    """1 where object ``j`` lies inside the footprint of pose ``t`` by ``margin`` (m, rad) at the
    estimate, else 0: ``(P, N)``."""
    d = objects[None, :, :2] - poses[:, None, :2]
    rng = np.hypot(d[..., 0], d[..., 1])
    bearing = np.angle(np.exp(1j * (np.arctan2(d[..., 1], d[..., 0]) - poses[:, None, 2])))
    inside = (rng < scenario.max_range - margin[0]) & (np.abs(bearing) < scenario.fov / 2 - margin[1])
    return inside.astype(float)


def miss_log_likelihood(in_view: np.ndarray, history: np.ndarray, num: int, settings: LoopClosureSettings) -> float:
    """``Σ log max(1 − p_d · P(in view), min_miss_probability)`` over the pairs (step ``t = 1..T``,
    object ``j < num``) with no detection of step ``t`` associated to ``j``: ``in_view (≥ T+1, ≥ num)``
    indexed by pose (``x_t`` for step ``t``), ``history (T, D)`` the associations (``-1`` none).
    ``settings.detection_probability`` must be decided (``for_scenario``); 0 gives 0."""
    p = settings.detection_probability
    if not p:
        return 0.0
    t = history.shape[0]
    q = np.asarray(in_view, float)[1: t + 1, :num]
    seen = np.zeros((t, num), bool)
    rows, cols = np.nonzero((history >= 0) & (history < num))
    seen[rows, history[rows, cols]] = True
    log_miss = np.log(np.maximum(1.0 - p * np.clip(q, 0.0, 1.0), settings.min_miss_probability))
    return float(np.sum(np.where(seen, 0.0, log_miss)))
