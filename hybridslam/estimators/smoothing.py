"""Smoothing: every estimator keeps and relinearizes the whole trajectory, as the papers do.

The filters keep, per component, one joint Gaussian over ``[x_k, objects]``: past poses are
marginalized at the estimate they had then, and a loop closure can correct the map and ``x_k`` but
never relinearize the past (the EKF-style inconsistency the hallway study measures). The papers'
estimators are smoothers: the hybrid belief is a posterior over the whole trajectory ``X_k``
(Tchuiev et al. Eq. 4-5, 9-11; their implementation keeps one iSAM2 graph per hypothesis), and
Doherty's estimators run on iSAM / mm-iSAM.

With ``smoother=Full()`` every component also keeps its trajectory ``x_0..x_T``. A step first runs
the estimator's own filter step (association, weights, pruning: unchanged), then re-solves each
kept component's whole factor graph by Levenberg-Marquardt (:mod:`hybridslam.inference.smoother`),
warm-started from its previous trajectory and the filter's new estimate, and replaces the
component's Gaussian over ``[x_k, objects]`` by the smoother's Laplace marginal at the new
solution, so the next step's association and weights (Eq. 16-17) are computed from the smoothed
state. The graph is rebuilt from what the state already holds: the data received so far
(:class:`DataLog`, shared by the components) and each component's association history (and, for
Gaussian PDA and max-mixtures, its per-detection candidates and weights).

* prior factor on ``[x_0, prior objects]`` (the scenario's), and on a discovered object's heading
  only (``N(0, new_object_orientation_var)``: range and bearing do not observe it);
* odometry factors (GTSAM's ``BetweenFactor<Pose2>`` convention) of every step so far;
* a measurement factor per associated detection, from the pose of its step to its object (the
  detection that created an object is a factor too: the smoother has no back-projected prior).

``Filter()`` keeps the filters (the behaviour before smoothing; planning uses it).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ..inference import smoother as sm
from ..io.scenario import Scenario
from ..models.measurement import Detections, SensorModel


class Filter(eqx.Module):
    """No smoothing: the joint Gaussian over ``[x_k, objects]`` of the filter step."""

    name: ClassVar[str] = "filter"


class Full(eqx.Module):
    """The whole trajectory re-solved at every step (``max_steps`` Levenberg-Marquardt iterations at
    most; warm-started, a step usually needs one to three, but the semantic factors of a strongly
    viewpoint-dependent classifier make Gauss-Newton converge linearly and take up to ~15: see
    :mod:`hybridslam.inference.smoother`)."""

    max_steps: int = eqx.field(default=20, static=True)
    name: ClassVar[str] = "full"

    def __check_init__(self):
        if not (isinstance(self.max_steps, int) and self.max_steps >= 1):
            raise ValueError(f"Full.max_steps: expected a positive int, got {self.max_steps!r}")


Smoother = Filter | Full


def parse_smoother(text: str) -> Smoother:
    """``"filter"`` or ``"full"`` (the ``--smoother`` option)."""
    if text == "filter":
        return Filter()
    if text == "full":
        return Full()
    raise ValueError(f"--smoother: expected filter or full, got {text!r}")


class DataLog(eqx.Module):
    """The odometry and detections received so far (steps ``0..k-1``; the rest zeros), and the
    Gaussian prior of the run: shared by every component of a state."""

    odometry: Float[Array, "T 3"]
    geo: Float[Array, "T Dmax 2"]
    scores: Float[Array, "T Dmax M"]
    mask: Bool[Array, "T Dmax"]
    prior_mean: Float[Array, " D0"]  # [x_0, o_0..o_{N-1}]
    prior_sqrt_info: Float[Array, "D0 D0"]

    def record(self, k: Int[Array, ""], odometry: Float[Array, "3"], detections: Detections) -> DataLog:
        """The log with step ``k + 1``'s inputs written in row ``k``."""
        return eqx.tree_at(
            lambda d: (d.odometry, d.geo, d.scores, d.mask), self,
            (self.odometry.at[k].set(odometry), self.geo.at[k].set(detections.geo),
             self.scores.at[k].set(detections.scores), self.mask.at[k].set(detections.mask)),
        )


def data_log(scenario: Scenario, max_steps: int, max_detections: int, max_objects: int) -> DataLog:
    """An empty log for ``scenario`` and the prior of its smoothing problems.

    The prior is the scenario's robot prior and object priors, block-diagonal; an object slot a
    detection may create later gets a prior on its heading only (``N(0, new_object_orientation_var)``).
    """
    n, m = scenario.num_objects, scenario.num_classes
    dim = 3 + 3 * max_objects
    mean = np.zeros(dim)
    info_sqrt = np.zeros((dim, dim))
    mean[:3] = scenario.robot_prior_mean
    info_sqrt[:3, :3] = _sqrt_information(scenario.robot_prior_cov)
    for i in range(n):  # once, host-side
        mean[3 + 3 * i: 6 + 3 * i] = scenario.object_prior_means[i]
        info_sqrt[3 + 3 * i: 6 + 3 * i, 3 + 3 * i: 6 + 3 * i] = _sqrt_information(scenario.object_prior_covs[i])
    var = scenario.discovery.new_object_orientation_var if scenario.discovery is not None else 1.0
    for i in range(n, max_objects):
        info_sqrt[5 + 3 * i, 5 + 3 * i] = 1.0 / np.sqrt(var)
    f = lambda a: jnp.asarray(a, dtype=float)  # noqa: E731
    return DataLog(
        odometry=jnp.zeros((max_steps, 3)), geo=jnp.zeros((max_steps, max_detections, 2)),
        scores=jnp.zeros((max_steps, max_detections, m)), mask=jnp.zeros((max_steps, max_detections), bool),
        prior_mean=f(mean), prior_sqrt_info=f(info_sqrt),
    )


def _sqrt_information(cov: np.ndarray) -> np.ndarray:
    """``R`` with ``RᵀR = Σ⁻¹`` (upper triangular)."""
    return np.linalg.cholesky(np.linalg.inv(cov)).T


def initial_trajectory(scenario: Scenario, max_steps: int) -> Float[Array, "T1 3"]:
    """``x_0`` at the prior mean, the poses not reached yet at the same place (inactive until reached)."""
    return jnp.broadcast_to(jnp.asarray(scenario.robot_prior_mean, dtype=float), (max_steps + 1, 3))


class Factors(eqx.Module):
    """One component's measurement factors: per (step, detection slot), up to ``G`` candidate objects
    with log weights (``-inf``: none) and a null component (max-mixtures)."""

    objects: Int[Array, "T Dmax G"]
    log_weight: Float[Array, "T Dmax G"]
    null_log_weight: Float[Array, "T Dmax"]
    classes: Int[Array, "T Dmax G"]  # class of each candidate for the semantic factor (0 if none)


def history_factors(history: Int[Array, "T Dmax"], classes: Int[Array, " N"] | None = None) -> Factors:
    """One factor per associated detection (``history >= 0``), with the object's class realization."""
    obj = jnp.maximum(history, 0)
    cls = jnp.zeros_like(obj) if classes is None else jnp.maximum(classes[obj], 0)
    return Factors(obj[..., None], jnp.where(history >= 0, 0.0, -jnp.inf)[..., None],
                   jnp.full(history.shape, -jnp.inf), cls[..., None])


def graph(
    log: DataLog, factors: Factors, k: Int[Array, ""], num_created: Int[Array, ""] | int, sensor: SensorModel,
    motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode = "sum",
) -> sm.FactorGraph:
    """The factor graph of a component after ``k`` steps (see the module docstring)."""
    t, dmax = log.mask.shape
    n = (log.prior_mean.shape[0] - 3) // 3
    steps = jnp.arange(t)
    reached = (steps < k)[:, None] & log.mask  # (T, Dmax)
    flat = lambda a: a.reshape((t * dmax,) + a.shape[2:])  # noqa: E731
    log_w = jnp.where(reached[..., None], factors.log_weight, -jnp.inf)
    null = jnp.where(reached, factors.null_log_weight, -jnp.inf)
    if semantic:
        residual: sm.SensorResidual | sm.RangeBearingResidual = sm.SensorResidual(sensor)
        data = sm.DetectionData(flat(log.geo), flat(log.scores), flat(factors.classes))
    else:
        w, _ = sensor.geometric_sqrt_information()
        residual = sm.RangeBearingResidual(w)
        data = flat(log.geo)
    motion_sqrt = jnp.linalg.cholesky(jnp.linalg.inv(motion_cov)).T
    return sm.FactorGraph(
        prior_mean=log.prior_mean, prior_sqrt_info=log.prior_sqrt_info,
        odometry=log.odometry, odometry_active=steps < k, motion_sqrt_info=motion_sqrt,
        meas_pose=flat(jnp.broadcast_to((steps + 1)[:, None], (t, dmax))),
        meas_objects=flat(factors.objects), meas_log_weight=flat(log_w), meas_null_log_weight=flat(null),
        meas_data=data, pose_active=jnp.arange(t + 1) <= k, object_active=jnp.arange(n) < num_created,
        residual_fn=residual, mode=mode,
    )


class Smoothed(eqx.Module):
    """What :func:`smooth` gives one component."""

    poses: Float[Array, "T1 3"]
    mean: Float[Array, " D0"]  # the Laplace marginal over [x_k, objects]
    cov: Float[Array, "D0 D0"]
    result: optx.RESULTS


def smooth(
    settings: Full, g: sm.FactorGraph, poses: Float[Array, "T1 3"], mean: Float[Array, " D0"],
    cov: Float[Array, "D0 D0"], k: Int[Array, ""],
) -> Smoothed:
    """Re-solve a component's graph, warm-started from its trajectory ``poses`` with ``x_k`` and the
    objects taken from the filter's new ``mean``, and return its marginal over ``[x_k, objects]``.

    If the solution or its marginal is not finite (a near-singular graph: noise variances of 1e-10
    next to unobserved object headings), the component keeps the filter's ``mean`` and ``cov`` and
    its previous trajectory with ``x_k`` from the filter, and the result says ``nonfinite``: the
    step's warning counts it, and nothing downstream sees a NaN.
    """
    start = poses.at[k].set(mean[:3])
    sol = sm.solve(g, start, mean[3:].reshape(-1, 3), max_steps=settings.max_steps)
    m, c = sm.marginal(g, sol, k)
    ok = jnp.all(jnp.isfinite(sol.poses)) & jnp.all(jnp.isfinite(m)) & jnp.all(jnp.isfinite(c))
    result = optx.RESULTS.where(ok, sol.result, optx.RESULTS.nonfinite)
    return Smoothed(jnp.where(ok, sol.poses, start), jnp.where(ok, m, mean), jnp.where(ok, c, cov), result)


def failed(result: optx.RESULTS) -> Bool[Array, "..."]:
    return jnp.asarray(result != optx.RESULTS.successful)
