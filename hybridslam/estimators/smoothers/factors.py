"""The factor graphs the smoothers (:mod:`.kinds`) solve, rebuilt at every step from what an
estimator state already holds: the data received so far (:class:`DataLog`, shared by the
components) and each component's measurement factors (:class:`Factors`: its association history,
and for Gaussian PDA and max-mixtures its per-detection candidates and weights).

The papers' estimators are smoothers over the whole trajectory ``X_k`` (Tchuiev et al. Eq. 4-5,
9-11; Doherty's estimators run on iSAM / mm-iSAM); a component's graph (:func:`graph`) holds

* a prior factor on ``[x_0, prior objects]`` (the scenario's), and on a discovered object's heading
  only (``N(0, new_object_orientation_var)``: range and bearing do not observe it);
* odometry factors (GTSAM's ``BetweenFactor<Pose2>`` convention) of every step so far;
* a measurement factor per associated detection, from the pose of its step to its object (the
  detection that created an object is a factor too: the smoother has no back-projected prior).

A fixed-lag window's graph (:func:`window_graph`) holds the same factors of the poses in the window,
and in place of the run's prior a dense Gaussian prior on its first pose and the map
(:class:`WindowPrior`, what marginalizing the poses that left the window gives).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ...inference import smoother as sm
from ...models.scenario import Scenario
from ...io.scenario import stack_steps
from ...models.measurement import Detections, SensorModel

class DataLog(eqx.Module):
    """The odometry and detections received so far (steps ``0..k-1``; the rest zeros), and the
    Gaussian prior of the run: shared by every component of a state.

    ``rows`` lists the detections received, in arrival order, as flat indices ``t·Dmax + d`` into
    the ``(T, Dmax)`` arrays: the full smoother's graph (:func:`graph`) has one measurement factor
    per entry, not one per padded slot. Its length is the log's factor budget: the scenario's own
    number of detections when the state is sized for that scenario (MRCLAM robot 3: 372 factors
    instead of 200 × 8 slots, a 4× cheaper linearization), else ``T·Dmax``. Detections beyond the
    budget (only a state stepped on other data than the scenario it was built for) are not in the
    graph, and :meth:`overflow` counts them.
    """

    odometry: Float[Array, "T 3"]
    geo: Float[Array, "T Dmax 2"]
    scores: Float[Array, "T Dmax M"]
    mask: Bool[Array, "T Dmax"]
    rows: Int[Array, " F"]  # the first count() entries are filled
    prior_mean: Float[Array, " D0"]  # [x_0, o_0..o_{N-1}]
    prior_sqrt_info: Float[Array, "D0 D0"]
    prior_info: Float[Array, "D0 D0"]  # RᵀR, formed once here rather than once per step
    last_step: Int[Array, ""]  # the scenario's steps: the step solved to kinds.FINAL_ATOL (a padded log has more rows)
    # Detections that arrived beyond the factor slots of the fixed-lag window ending at their step.
    window_excess: Int[Array, ""]
    # A fixed-lag window graph's measurement factor slots (window_factor_budget) and poses (L + 1);
    # 0: one slot per padded detection slot of the window's steps.
    window_factors: int = eqx.field(static=True, default=0)
    window_steps: int = eqx.field(static=True, default=0)

    def record(self, k: Int[Array, ""], odometry: Float[Array, "3"], detections: Detections) -> DataLog:
        """The log with step ``k + 1``'s inputs written in row ``k`` (and its detections appended
        to ``rows``, those beyond the budget dropped and counted by :meth:`overflow`)."""
        dmax = self.mask.shape[1]
        budget = self.rows.shape[0]
        at = jnp.where(detections.mask, self.count() + jnp.cumsum(detections.mask) - 1, budget)
        rows = self.rows.at[at].set(k * dmax + jnp.arange(dmax, dtype=self.rows.dtype), mode="drop")
        mask = self.mask.at[k].set(detections.mask)
        excess = self.window_excess
        if self.window_factors:  # the window ending at step k holds more detections than its slots
            t = jnp.arange(mask.shape[0])
            held = jnp.sum(jnp.where((t > k - self.window_steps) & (t <= k), jnp.sum(mask, axis=1), 0))
            excess += jnp.minimum(jnp.sum(detections.mask), jnp.maximum(held - self.window_factors, 0))
        return eqx.tree_at(
            lambda d: (d.odometry, d.geo, d.scores, d.mask, d.rows, d.window_excess), self,
            (self.odometry.at[k].set(odometry), self.geo.at[k].set(detections.geo),
             self.scores.at[k].set(detections.scores), mask, rows, excess.astype(jnp.int32)),
        )

    def count(self) -> Int[Array, ""]:
        """Detections recorded so far (every one sets its ``mask`` entry)."""
        return jnp.sum(self.mask, dtype=jnp.int32)

    def overflow(self) -> Int[Array, ""]:
        """Detections recorded beyond the factor budget (not in the full smoother's graph), and
        beyond the fixed-lag window's factor slots when they arrived (not in that window's graph)."""
        return jnp.maximum(self.count() - self.rows.shape[0], 0) + self.window_excess


def data_log(scenario: Scenario, max_steps: int, max_detections: int, max_objects: int,
             max_factors: int | None = None, window_factors: int = 0, window_steps: int = 0) -> DataLog:
    """An empty log for ``scenario`` and the prior of its smoothing problems.

    ``max_factors``: the factor budget (:class:`DataLog`), by default ``max_steps · max_detections``
    (room for anything); :func:`factor_budget` gives the scenario's own count where that is safe.
    ``window_factors``: a fixed-lag window's factor slots (:func:`window_factor_budget`; 0: every
    padded slot of the window's steps) and ``window_steps`` its poses, ``L + 1``.
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
    budget = max_steps * max_detections if max_factors is None else max_factors
    if not 1 <= budget <= max_steps * max_detections:
        raise ValueError(f"max_factors: expected 1 to {max_steps * max_detections} (steps × detection slots), "
                         f"got {budget}")
    put = jax.device_put  # numpy to the device without a compile (eager jnp ops each compile one)
    return DataLog(
        odometry=put(np.zeros((max_steps, 3))), geo=put(np.zeros((max_steps, max_detections, 2))),
        scores=put(np.zeros((max_steps, max_detections, m))), mask=put(np.zeros((max_steps, max_detections), bool)),
        rows=put(np.zeros((budget,), np.int32)),
        prior_mean=put(np.asarray(mean, float)), prior_sqrt_info=put(np.asarray(info_sqrt, float)),
        prior_info=put(np.asarray(info_sqrt.T @ info_sqrt, float)),
        last_step=put(np.asarray(scenario.num_steps, dtype=np.int32)), window_excess=put(np.zeros((), np.int32)),
        window_factors=int(window_factors), window_steps=int(window_steps),
    )


def new_overflow(old: DataLog | None, new: DataLog | None) -> Int[Array, ""]:
    """Detections of the step just recorded (``old`` → ``new``) that the log's factor budget could
    not hold (0 without a log): the steps' ``StepInfo.log_overflow``."""
    if old is None or new is None:
        return jnp.zeros((), jnp.int32)
    return (new.overflow() - old.overflow()).astype(jnp.int32)


def factor_budget(scenario: Scenario, max_steps: int | None, max_detections: int) -> int:
    """The factor budget of a state built for ``scenario``: its number of detections if the state is
    sized for it alone (``max_steps`` None: the estimators' default), else ``steps · max_detections``
    (a shared ``max_steps`` lets other files of other lengths run on the same shapes)."""
    total = sum(len(step.detections) for step in scenario.steps)
    if max_steps is None:
        return max(total, 1)
    return max(max_steps, 1) * max_detections


def window_factor_budget(scenario: Scenario, max_steps: int | None, max_detections: int, length: int) -> int:
    """The measurement factor slots of a window of ``length + 1`` poses in a state built for
    ``scenario``: the most detections in ``length + 1`` consecutive steps of the scenario where the
    state is sized for it alone (``max_steps`` None, as :func:`factor_budget`), else every padded
    slot, ``(length + 1) · max_detections``. A window then linearizes its own detections, not the
    run's busiest step's slots at every pose (MRCLAM unfiltered: 21 slots, about 3 detections a step)."""
    full = (length + 1) * max_detections
    if max_steps is not None:
        return full
    counts = np.array([len(step.detections) for step in scenario.steps] or [0])
    sums = np.convolve(counts, np.ones(min(length + 1, counts.size), int), mode="valid")
    return int(min(max(int(sums.max()), 1), full))


def scenario_log(scenario: Scenario, max_objects: int) -> DataLog:
    """:func:`data_log` with every step of ``scenario`` already recorded (a whole run, for batch
    solves after the fact: the oracle smoother, the loop-closure pass)."""
    stacked = stack_steps(scenario)
    dmax = stacked.mask.shape[1]
    log = data_log(scenario, scenario.num_steps, dmax, max_objects, factor_budget(scenario, None, dmax))
    rows = np.flatnonzero(stacked.mask.reshape(-1))  # row-major: arrival order
    rows = np.concatenate([rows, np.zeros(log.rows.shape[0] - rows.size, int)]).astype(np.int32)
    return eqx.tree_at(lambda d: (d.odometry, d.geo, d.scores, d.mask, d.rows), log,
                       tuple(jnp.asarray(a) for a in (stacked.odometry, stacked.geo, stacked.scores, stacked.mask, rows)))


class WindowPrior(eqx.Module):
    """A fixed-lag window's Gaussian prior on ``[x_s, o_0..o_{N-1}]`` (``s``: the window's first
    pose): ``½ dᵀΛd`` with ``d = y ⊖ mean`` and ``Λ = info``, what the marginalization gives
    (:func:`~hybridslam.inference.smoother.marginalize_first_information`). Only ``Λ`` is carried,
    not also its factor ``R``: each ``D₀ × D₀`` matrix per component is copied several times a
    step (sliced into the smoothing, written back, kept or not), 3-5 ms a step on the hallway.
    Before the window first slides it is the run's prior (:class:`DataLog`)."""

    mean: Float[Array, "*K D0"]
    info: Float[Array, "*K D0 D0"]


def initial_window(log: DataLog, components: int | None = None) -> WindowPrior:
    """The run's prior as every component's window prior (``components``: a leading axis of that size)."""
    if components is None:
        return WindowPrior(log.prior_mean, log.prior_info)
    lead = lambda a: jnp.broadcast_to(a, (components,) + a.shape)  # noqa: E731
    return WindowPrior(lead(log.prior_mean), lead(log.prior_info))


def _sqrt_information(cov: np.ndarray) -> np.ndarray:
    """``R`` with ``RᵀR = Σ⁻¹`` (upper triangular)."""
    return np.linalg.cholesky(np.linalg.inv(cov)).T


def _sqrt_information_of(cov: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """``R = chol(Σ⁻¹)ᵀ`` (``RᵀR = Σ⁻¹``), the inverse from ``Σ``'s Cholesky factor: an LU inverse
    would compile a pivoting loop into every step."""
    chol = jnp.linalg.cholesky(cov)
    return jnp.linalg.cholesky(jax.scipy.linalg.cho_solve((chol, True), jnp.eye(3, dtype=cov.dtype))).T


def initial_trajectory(scenario: Scenario, max_steps: int) -> Float[Array, "T1 3"]:
    """``x_0`` at the prior mean, the poses not reached yet at the same place (inactive until reached)."""
    return jax.device_put(np.broadcast_to(np.asarray(scenario.robot_prior_mean, dtype=float), (max_steps + 1, 3)))


class FactorRows(NamedTuple):
    """Measurement factors of ``F`` listed detections: what a graph takes from :class:`Factors` or
    :class:`HistoryFactors` (their ``rows``)."""

    objects: Int[Array, "F G"]
    log_weight: Float[Array, "F G"]
    null_log_weight: Float[Array, " F"]
    classes: Int[Array, "F G"]


class Factors(eqx.Module):
    """One component's measurement factors: per (step, detection slot), up to ``G`` candidate objects
    with log weights (``-inf``: none) and a null component (max-mixtures)."""

    objects: Int[Array, "T Dmax G"]
    log_weight: Float[Array, "T Dmax G"]
    null_log_weight: Float[Array, "T Dmax"]
    classes: Int[Array, "T Dmax G"]  # class of each candidate for the semantic factor (0 if none)

    def rows(self, cells: Int[Array, " F"]) -> FactorRows:
        """The factors of the detections at flat indices ``cells`` (``step · Dmax + slot``)."""
        take = lambda a: a.reshape((-1,) + a.shape[2:])[cells]  # noqa: E731
        return FactorRows(take(self.objects), take(self.log_weight), take(self.null_log_weight), take(self.classes))


class HistoryFactors(eqx.Module):
    """One factor per associated detection (``history >= 0``), with the object's class realization
    (``classes``; none: class 0): the hybrid belief's and ``multimodal``'s factors, read off a
    component's association history.

    The same rows as :class:`Factors` would hold, made only for the detections a graph lists
    (:meth:`rows`): a component's smoothing gathers a window's few hundred detections from its
    history rather than building four arrays over every (step, slot) of the log first (a whole
    MRCLAM log: 1,700 × 21 entries per component and smoothing)."""

    history: Int[Array, "T Dmax"]
    classes: Int[Array, " N"] | None = None

    def rows(self, cells: Int[Array, " F"]) -> FactorRows:
        """The factors of the detections at flat indices ``cells`` (``step · Dmax + slot``)."""
        assigned = self.history.reshape(-1)[cells]
        obj = jnp.maximum(assigned, 0)
        cls = jnp.zeros_like(obj) if self.classes is None else jnp.maximum(self.classes[obj], 0)
        return FactorRows(obj[:, None], jnp.where(assigned >= 0, 0.0, -jnp.inf)[:, None],
                          jnp.full(assigned.shape, -jnp.inf), cls[:, None])


AnyFactors = Factors | HistoryFactors


def history_factors(history: Int[Array, "T Dmax"], classes: Int[Array, " N"] | None = None) -> HistoryFactors:
    """One factor per associated detection of ``history`` (:class:`HistoryFactors`)."""
    return HistoryFactors(history, classes)


def graph(
    log: DataLog, factors: AnyFactors, k: Int[Array, ""], num_created: Int[Array, ""] | int, sensor: SensorModel,
    motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode = "sum",
) -> sm.FactorGraph:
    """The factor graph of a component after ``k`` steps (see the module docstring): one
    measurement factor per detection logged (``log.rows``)."""
    t, dmax = log.mask.shape
    n = (log.prior_mean.shape[0] - 3) // 3
    steps = jnp.arange(t)
    rows = log.rows
    flat = lambda a: a.reshape((t * dmax,) + a.shape[2:])[rows]  # noqa: E731
    step_of = rows // dmax
    reached = (jnp.arange(rows.shape[0]) < log.count()) & (step_of < k)  # (F,): rows name only detections
    listed = factors.rows(rows)
    log_w = jnp.where(reached[:, None], listed.log_weight, -jnp.inf)
    null = jnp.where(reached, listed.null_log_weight, -jnp.inf)
    residual, data = _measurements(sensor, semantic, flat(log.geo), flat(log.scores), listed.classes)
    motion_sqrt = _sqrt_information_of(motion_cov)
    return sm.FactorGraph(
        prior_mean=log.prior_mean, prior_sqrt_info=log.prior_sqrt_info,
        odometry=log.odometry, odometry_active=steps < k, motion_sqrt_info=motion_sqrt,
        meas_pose=step_of + 1,
        meas_objects=listed.objects, meas_log_weight=log_w, meas_null_log_weight=null,
        meas_data=data, pose_active=jnp.arange(t + 1) <= k, object_active=jnp.arange(n) < num_created,
        residual_fn=residual, mode=mode, prior_info=log.prior_info,
        independent_objects=True,  # the run's prior (data_log) is block-diagonal
    )


def _measurements(
    sensor: SensorModel, semantic: bool, geo: Float[Array, "F 2"], scores: Float[Array, "F M"],
    classes: Int[Array, "F G"],
) -> tuple[sm.SensorResidual | sm.RangeBearingResidual, sm.DetectionData | Float[Array, "F 2"]]:
    """The residual function and per-factor data of the measurement factors (semantic or geometric only)."""
    if semantic:
        return sm.SensorResidual(sensor), sm.DetectionData(geo, scores, classes)
    w, _ = sensor.geometric_sqrt_information()
    return sm.RangeBearingResidual(w), geo


def window_graph(
    log: DataLog, factors: AnyFactors, k: Int[Array, ""], start: Int[Array, ""], length: int,
    num_created: Int[Array, ""] | int, sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool,
    mode: sm.Mode, prior: WindowPrior, slots: int | None = None,
) -> sm.FactorGraph:
    """The factor graph of a fixed-lag window after ``k`` steps: poses ``x_start..x_{start+length}``
    (window slots ``0..length``; those after ``x_k`` inactive), ``prior`` on ``[x_start, objects]``,
    the odometry of steps ``start+1..`` and the measurement factors of every pose in the window,
    ``x_start``'s included (they leave with ``x_start`` when it is marginalized).

    ``slots``: the measurement factor slots (default: the log's window budget); the window's
    detections beyond them are left out (``length=1, slots=Dmax``: the factors touching
    ``x_start``, which come first, and none of ``x_{start+1}``'s beyond them: what marginalizing
    ``x_start`` reads, :func:`~hybridslam.inference.smoother.first_pose_factors`)."""
    t, dmax = log.mask.shape
    n = (log.prior_mean.shape[0] - 3) // 3
    first = start - 1  # the log row of window pose 0's detections
    # The window's detections are a run of the log's rows (arrival order is step order): its
    # factor slots take them from the first one of step `first` on, `fw` of them (the budget holds
    # every window of the scenario: window_factor_budget), the slots after them inactive.
    fw = slots or log.window_factors or (length + 1) * dmax
    f = log.rows.shape[0]
    listed = jnp.minimum(log.count(), f)  # the rows filled
    at = jnp.sum((jnp.arange(f) < listed) & (log.rows // dmax < first)) + jnp.arange(fw)
    cell = log.rows[jnp.clip(at, 0, f - 1)]  # flat (step, slot) index
    step = cell // dmax
    reached = (at < listed) & (step >= first) & (step <= first + length) & (step < k)
    take = lambda a: a.reshape((t * dmax,) + a.shape[2:])[cell]  # noqa: E731
    taken = factors.rows(cell)
    log_w = jnp.where(reached[:, None], taken.log_weight, -jnp.inf)
    null = jnp.where(reached, taken.null_log_weight, -jnp.inf)
    residual, data = _measurements(sensor, semantic, take(log.geo), take(log.scores), taken.classes)
    odo_rows = start + jnp.arange(length)
    return sm.FactorGraph(
        prior_mean=prior.mean, prior_sqrt_info=None, prior_info=prior.info,
        odometry=jnp.take(log.odometry, jnp.clip(odo_rows, 0, t - 1), axis=0), odometry_active=odo_rows < k,
        motion_sqrt_info=_sqrt_information_of(motion_cov),
        meas_pose=jnp.where(reached, step - first, 0).astype(jnp.int32),
        meas_objects=taken.objects, meas_log_weight=log_w, meas_null_log_weight=null,
        meas_data=data, pose_active=jnp.arange(length + 1) <= k - start,
        object_active=jnp.arange(n) < num_created, residual_fn=residual, mode=mode,
    )



def active_history(log: DataLog, factors: Factors, k: Int[Array, ""], active: Int[Array, " F"],
                   history: Int[Array, "T Dmax"]) -> Int[Array, "T Dmax"]:
    """``history`` with every detection of the full graph after ``k`` steps (:func:`graph`'s rows)
    associated with the object of its active component ``active`` (``-1`` where the null component,
    or none, is active).

    A max-mixture's associations at a solution (Doherty thesis Eq. 4.16: each factor is its
    likeliest component there): the graph rebuilt from them has that solution as a stationary point,
    which a history of the components chosen online (at earlier, since relinearized, estimates) need
    not have. Detections beyond the log's budget keep their entries."""
    t, dmax = log.mask.shape
    rows = log.rows
    reached = (jnp.arange(rows.shape[0]) < log.count()) & (rows // dmax < k)
    objects = factors.objects.reshape(t * dmax, -1)[rows]  # (F, G)
    g = objects.shape[-1]
    on_object = (active >= 0) & (active < g)
    chosen = jnp.take_along_axis(objects, jnp.clip(active, 0, g - 1)[:, None], axis=1)[:, 0]
    chosen = jnp.where(on_object, chosen, -1).astype(history.dtype)
    flat = history.reshape(-1).at[jnp.where(reached, rows, t * dmax)].set(chosen, mode="drop")
    return flat.reshape(history.shape)
