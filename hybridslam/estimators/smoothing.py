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
warm-started from its previous trajectory and the filter's new estimate (the hybrid belief skips
its per-component filter update and starts from the prediction: the solve is the same), and
replaces the component's Gaussian over ``[x_k, objects]`` by the smoother's Laplace marginal at
the new solution, so the next step's association and weights (Eq. 16-17) are computed from the smoothed
state. The graph is rebuilt from what the state already holds: the data received so far
(:class:`DataLog`, shared by the components) and each component's association history (and, for
Gaussian PDA and max-mixtures, its per-detection candidates and weights).

* prior factor on ``[x_0, prior objects]`` (the scenario's), and on a discovered object's heading
  only (``N(0, new_object_orientation_var)``: range and bearing do not observe it);
* odometry factors (GTSAM's ``BetweenFactor<Pose2>`` convention) of every step so far;
* a measurement factor per associated detection, from the pose of its step to its object (the
  detection that created an object is a factor too: the smoother has no back-projected prior).

``Lag(L)`` (``--smoother lag:L``) is the bounded-cost online option: a fixed-lag smoother whose
window holds the last ``L`` steps (poses ``x_{k-L}..x_k``) and the map. When the window slides, its
oldest pose is marginalized (:func:`~hybridslam.inference.smoother.marginalize_first`: the factors
touching it, linearized at the current estimate, become a dense Gaussian prior on the next oldest
pose and the map, :class:`WindowPrior`, kept per component). Exact for linear-Gaussian factors, the
standard fixed-lag approximation otherwise; ``Lag(L)`` with ``L`` at least the run's steps is
``Full()``. Poses that left the window keep their last smoothed value in the trajectory.

``Filter()`` keeps the filters (the behaviour before smoothing; planning uses it).
"""

from __future__ import annotations

import abc

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ..inference import smoother as sm
from ..io.scenario import Scenario, stack_steps
from ..models.measurement import Detections, SensorModel


STEP_ATOL = 1e-2  # nats: the cost tolerance of a smoother step before the last (Full.step_atol)
FINAL_ATOL = 1e-9  # nats: the last step's (the solver's default)


def _check_atol(owner: str, value: float) -> None:
    if not 0.0 <= value < math.inf:
        raise ValueError(f"{owner}.step_atol: expected a non-negative number of nats, got {value!r}")


class AbstractSmoother(eqx.Module):
    """What an estimator does after each step's update: nothing (:class:`Filter`), re-solve each
    component's whole trajectory and map (:class:`Full`) or a fixed-lag window of it (:class:`Lag`).

    The estimators ask the smoother, never its type: :attr:`smooths` (whether a state keeps a
    trajectory and a data log), :attr:`whole_trajectory` (whether every solve covers ``x_0..x_k``),
    :meth:`init_window` (a window prior per component, or none) and :meth:`smooth` (one component's
    smoothing after ``k`` steps). ``str()`` of a smoother is its ``--smoother`` text
    (:func:`parse_smoother` reads it back).
    """

    smooths: ClassVar[bool] = True
    whole_trajectory: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def name(self) -> str:
        """The ``--smoother`` text: ``filter``, ``full`` or ``lag:L``."""

    def __str__(self) -> str:
        return self.name

    def init_window(self, log: DataLog, components: int | None = None) -> WindowPrior | None:
        """Each component's window prior at the start (``components``: a leading axis of that size),
        or ``None`` where the smoother has no window."""
        del log, components
        return None

    def init(self, scenario: Scenario, steps: int, slots: int, max_objects: int, max_steps: int | None,
             components: int | None = None) -> SmootherState:
        """What this smoother keeps before the first step of a state sized for ``scenario``
        (``steps`` history rows, ``slots`` detection slots, ``max_objects`` object slots; ``max_steps``:
        the estimator's option, which fixes the factor budget, :func:`factor_budget`): every
        component's trajectory at the prior mean, an empty :class:`DataLog`, the window priors
        (``components``: a leading axis of that size on the per-component fields). Empty
        (:class:`SmootherState` ``()``) where the smoother does not smooth."""
        if not self.smooths:
            return SmootherState()
        log = data_log(scenario, steps, slots, max_objects, factor_budget(scenario, max_steps, slots))
        poses = np.asarray(initial_trajectory(scenario, steps))
        if components is not None:
            poses = np.broadcast_to(poses, (components,) + poses.shape)
        return SmootherState(jax.device_put(poses), log, self.init_window(log, components))

    def smooth(
        self, log: DataLog, factors: Factors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
        sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
        poses: Float[Array, "T1 3"], mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
        window: WindowPrior | None = None,
    ) -> Smoothed:
        """A component's smoothing after ``k`` steps (:func:`smooth_step`)."""
        raise ValueError(f"smoother={self.name}: this smoother does not smooth")


def check_smoother(owner: str, value: object) -> None:
    """A ``ValueError`` naming ``owner.smoother`` unless ``value`` is a smoother."""
    if not isinstance(value, AbstractSmoother):
        raise ValueError(f"{owner}.smoother: expected Full(), Lag(L) or Filter(), got {value!r}")


class Filter(AbstractSmoother):
    """No smoothing: the joint Gaussian over ``[x_k, objects]`` of the filter step."""

    smooths: ClassVar[bool] = False

    @property
    def name(self) -> str:
        return "filter"


class Full(AbstractSmoother):
    """The whole trajectory re-solved at every step (``max_steps`` Levenberg-Marquardt iterations at
    most; the semantic factors of a strongly viewpoint-dependent classifier make Gauss-Newton
    converge linearly and take up to ~15: see :mod:`hybridslam.inference.smoother`).

    ``step_atol`` (nats) is the cost tolerance of every step but the scenario's last, whose solve
    uses the solver's ``1e-9`` (so the result file's trajectory is the graph's optimum to 1e-6 m).
    A warm-started step gains ``0.47, 2e-4, 4e-7, 1e-8, 1e-10`` nats per iterate on the hallway,
    and ``3e-3, 7e-4, 3e-5`` on real data (MRCLAM: large residuals, linear convergence): ``1e-2``
    stops it within ``√(2·1e-2) ≈ 0.14`` standard deviations of the optimum, where the next step
    resumes (nothing accumulates). iSAM2 is looser still: one Gauss-Newton iterate per update,
    a variable relinearized only when its update exceeds 0.1. On MRCLAM robot 3 the hybrid belief
    takes 60 instead of 85-89 ms per step with ``1e-2`` rather than ``1e-4``, and every error
    (online and smoothed APE, last pose) agrees to 1e-4 m; likewise on the hallway."""

    max_steps: int = eqx.field(default=20, static=True)
    step_atol: float = eqx.field(default=STEP_ATOL, static=True)
    whole_trajectory: ClassVar[bool] = True

    @property
    def name(self) -> str:
        return "full"

    def __check_init__(self):
        if not (isinstance(self.max_steps, int) and self.max_steps >= 1):
            raise ValueError(f"Full.max_steps: expected a positive int, got {self.max_steps!r}")
        _check_atol("Full", self.step_atol)

    def smooth(
        self, log: DataLog, factors: Factors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
        sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
        poses: Float[Array, "T1 3"], mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
        window: WindowPrior | None = None,
    ) -> Smoothed:
        """The whole graph (:func:`graph`) re-solved (:func:`smooth`)."""
        g = graph(log, factors, k, num_created, sensor, motion_cov, semantic, mode)
        return smooth(self, g, poses, mean, cov, k, step_tolerance(self, log, k))


class Lag(AbstractSmoother):
    """Fixed-lag smoothing: the last ``length`` steps and the map re-solved at every step (at most
    ``max_steps`` Levenberg-Marquardt iterations), older poses marginalized (module docstring).
    The cost of a step is bounded by ``length``, not by the steps taken so far."""

    length: int = eqx.field(static=True)
    max_steps: int = eqx.field(default=20, static=True)
    step_atol: float = eqx.field(default=STEP_ATOL, static=True)  # as Full's

    @property
    def name(self) -> str:
        return f"lag:{self.length}"

    def __check_init__(self):
        for field in ("length", "max_steps"):
            value = getattr(self, field)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"Lag.{field}: expected a positive int, got {value!r}")
        _check_atol("Lag", self.step_atol)

    def init_window(self, log: DataLog, components: int | None = None) -> WindowPrior | None:
        return initial_window(log, components)

    def smooth(
        self, log: DataLog, factors: Factors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
        sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
        poses: Float[Array, "T1 3"], mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
        window: WindowPrior | None = None,
    ) -> Smoothed:
        """The fixed-lag window re-solved (:func:`smooth_lag`; ``window`` required)."""
        if window is None:
            raise ValueError("smoother=Lag(...): this state carries no window prior (build it with the estimator's init)")
        return smooth_lag(self, log, factors, k, num_created, sensor, motion_cov, semantic, mode, poses, mean,
                          cov, window)


Smoother = AbstractSmoother


def parse_smoother(text: str) -> Smoother:
    """``"filter"``, ``"full"`` or ``"lag:L"`` with ``L >= 1`` steps (the ``--smoother`` option)."""
    if text == "filter":
        return Filter()
    if text == "full":
        return Full()
    if text.startswith("lag:") and text[4:].isdigit() and int(text[4:]) >= 1:
        return Lag(int(text[4:]))
    raise ValueError(f"--smoother: expected filter, full or lag:L (L a positive number of steps), got {text!r}")


class SmootherState(eqx.Module):
    """What a smoother keeps between steps: one field of every estimator state (``smoothing``),
    made by :meth:`AbstractSmoother.init`. Empty (every field ``None``) under :class:`Filter`.

    ``poses``: each component's trajectory ``x_0..x_T`` (``*K``: the estimator's component axis,
    none for a single Gaussian); ``log``: the data so far, shared by the components; ``window``:
    with :class:`Lag`, each component's window prior on ``[x_s, objects]``; ``factors``: the
    single-Gaussian estimators' measurement factors as decided online (a mixture's estimators
    rebuild theirs from each component's association history, :func:`history_factors`)."""

    poses: Float[Array, "*K T1 3"] | None = None
    log: DataLog | None = None
    window: WindowPrior | None = None
    factors: Factors | None = None

    @property
    def smooths(self) -> bool:
        """Whether this state carries a trajectory (``Full`` or ``Lag``)."""
        return self.poses is not None

    def trajectory(self, component: Int[Array, ""] | int | None = None) -> Float[Array, "*K T1 3"] | None:
        """The smoothed ``x_0..x_T`` of ``component`` (every component's if ``None``), ``None``
        without smoothing."""
        if self.poses is None or component is None:
            return self.poses
        return self.poses[component]

    def components(self, index: Int[Array, " C"] | slice) -> SmootherState:
        """The per-component fields (``poses``, ``window``) of components ``index`` (the data log,
        shared, unchanged): the parents' smoothing state of a step's children."""
        return SmootherState(None if self.poses is None else self.poses[index], self.log,
                             None if self.window is None else jax.tree.map(lambda a: a[index], self.window),
                             self.factors)

    def where(self, keep: Bool[Array, "*K"], other: SmootherState) -> SmootherState:
        """The per-component fields of this state where ``keep`` (per component, or one flag for
        all), else ``other``'s (components of the same number, or one broadcast to all); the data
        log is this state's."""
        pick = lambda a, b: jnp.where(keep.reshape(keep.shape + (1,) * (a.ndim - keep.ndim)), a, b)  # noqa: E731
        return SmootherState(
            None if self.poses is None or other.poses is None else pick(self.poses, other.poses), self.log,
            None if self.window is None or other.window is None else jax.tree.map(pick, self.window, other.window),
            self.factors)

    def record(self, k: Int[Array, ""], odometry: Float[Array, "3"], detections: Detections) -> SmootherState:
        """This state with step ``k + 1``'s inputs written to its log (:meth:`DataLog.record`)."""
        if self.log is None:
            raise ValueError("smoothing: this state carries no data log (built by init_belief or without the "
                             "estimator's init); build it with the estimator's init(scenario) or use smoother=Filter()")
        return eqx.tree_at(lambda s: s.log, self, self.log.record(k, odometry, detections))


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
    last_step: Int[Array, ""]  # the scenario's steps: the step solved to FINAL_ATOL (a padded log has more rows)

    def record(self, k: Int[Array, ""], odometry: Float[Array, "3"], detections: Detections) -> DataLog:
        """The log with step ``k + 1``'s inputs written in row ``k`` (and its detections appended
        to ``rows``, those beyond the budget dropped and counted by :meth:`overflow`)."""
        dmax = self.mask.shape[1]
        budget = self.rows.shape[0]
        at = jnp.where(detections.mask, self.count() + jnp.cumsum(detections.mask) - 1, budget)
        rows = self.rows.at[at].set(k * dmax + jnp.arange(dmax, dtype=self.rows.dtype), mode="drop")
        return eqx.tree_at(
            lambda d: (d.odometry, d.geo, d.scores, d.mask, d.rows), self,
            (self.odometry.at[k].set(odometry), self.geo.at[k].set(detections.geo),
             self.scores.at[k].set(detections.scores), self.mask.at[k].set(detections.mask), rows),
        )

    def count(self) -> Int[Array, ""]:
        """Detections recorded so far (every one sets its ``mask`` entry)."""
        return jnp.sum(self.mask, dtype=jnp.int32)

    def overflow(self) -> Int[Array, ""]:
        """Detections recorded beyond the factor budget (not in the full smoother's graph)."""
        return jnp.maximum(self.count() - self.rows.shape[0], 0)


def data_log(scenario: Scenario, max_steps: int, max_detections: int, max_objects: int,
             max_factors: int | None = None) -> DataLog:
    """An empty log for ``scenario`` and the prior of its smoothing problems.

    ``max_factors``: the factor budget (:class:`DataLog`), by default ``max_steps · max_detections``
    (room for anything); :func:`factor_budget` gives the scenario's own count where that is safe.
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
        last_step=put(np.asarray(scenario.num_steps, dtype=np.int32)),
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
    """The factor graph of a component after ``k`` steps (see the module docstring): one
    measurement factor per detection logged (``log.rows``)."""
    t, dmax = log.mask.shape
    n = (log.prior_mean.shape[0] - 3) // 3
    steps = jnp.arange(t)
    rows = log.rows
    flat = lambda a: a.reshape((t * dmax,) + a.shape[2:])[rows]  # noqa: E731
    step_of = rows // dmax
    reached = (jnp.arange(rows.shape[0]) < log.count()) & (step_of < k)  # (F,): rows name only detections
    log_w = jnp.where(reached[:, None], flat(factors.log_weight), -jnp.inf)
    null = jnp.where(reached, flat(factors.null_log_weight), -jnp.inf)
    residual, data = _measurements(sensor, semantic, flat(log.geo), flat(log.scores), flat(factors.classes))
    motion_sqrt = _sqrt_information_of(motion_cov)
    return sm.FactorGraph(
        prior_mean=log.prior_mean, prior_sqrt_info=log.prior_sqrt_info,
        odometry=log.odometry, odometry_active=steps < k, motion_sqrt_info=motion_sqrt,
        meas_pose=step_of + 1,
        meas_objects=flat(factors.objects), meas_log_weight=log_w, meas_null_log_weight=null,
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
    log: DataLog, factors: Factors, k: Int[Array, ""], start: Int[Array, ""], length: int,
    num_created: Int[Array, ""] | int, sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool,
    mode: sm.Mode, prior: WindowPrior,
) -> sm.FactorGraph:
    """The factor graph of a fixed-lag window after ``k`` steps: poses ``x_start..x_{start+length}``
    (window slots ``0..length``; those after ``x_k`` inactive), ``prior`` on ``[x_start, objects]``,
    the odometry of steps ``start+1..`` and the measurement factors of every pose in the window,
    ``x_start``'s included (they leave with ``x_start`` when it is marginalized)."""
    t, dmax = log.mask.shape
    n = (log.prior_mean.shape[0] - 3) // 3
    rows = start - 1 + jnp.arange(length + 1)  # the log row of each window pose's detections
    take = lambda a: jnp.take(a, jnp.clip(rows, 0, t - 1), axis=0)  # noqa: E731
    reached = ((rows >= 0) & (rows < k))[:, None] & take(log.mask)  # (L+1, Dmax)
    flat = lambda a: a.reshape(((length + 1) * dmax,) + a.shape[2:])  # noqa: E731
    log_w = jnp.where(reached[..., None], take(factors.log_weight), -jnp.inf)
    null = jnp.where(reached, take(factors.null_log_weight), -jnp.inf)
    residual, data = _measurements(sensor, semantic, flat(take(log.geo)), flat(take(log.scores)),
                                   flat(take(factors.classes)))
    odo_rows = start + jnp.arange(length)
    return sm.FactorGraph(
        prior_mean=prior.mean, prior_sqrt_info=None, prior_info=prior.info,
        odometry=jnp.take(log.odometry, jnp.clip(odo_rows, 0, t - 1), axis=0), odometry_active=odo_rows < k,
        motion_sqrt_info=_sqrt_information_of(motion_cov),
        meas_pose=flat(jnp.broadcast_to(jnp.arange(length + 1)[:, None], (length + 1, dmax))),
        meas_objects=flat(take(factors.objects)), meas_log_weight=flat(log_w), meas_null_log_weight=flat(null),
        meas_data=data, pose_active=jnp.arange(length + 1) <= k - start,
        object_active=jnp.arange(n) < num_created, residual_fn=residual, mode=mode,
    )


class Smoothed(eqx.Module):
    """What :func:`smooth` gives one component (``window``: its new window prior, with :class:`Lag`;
    ``active``: with :class:`Full`, each factor row's active component at the solution, as
    :attr:`~hybridslam.inference.smoother.Solution.active`)."""

    poses: Float[Array, "T1 3"]
    mean: Float[Array, " D0"]  # the Laplace marginal over [x_k, objects]
    cov: Float[Array, "D0 D0"]
    result: optx.RESULTS
    window: WindowPrior | None = None
    active: Int[Array, " F"] | None = None


def smooth(
    settings: Full, g: sm.FactorGraph, poses: Float[Array, "T1 3"], mean: Float[Array, " D0"],
    cov: Float[Array, "D0 D0"], k: Int[Array, ""], cost_atol: Float[Array, ""] | float = FINAL_ATOL,
) -> Smoothed:
    """Re-solve a component's graph, warm-started from its trajectory ``poses`` with ``x_k`` and the
    objects taken from ``mean`` (the filter's update, or a prediction), to ``cost_atol`` nats (:func:`step_tolerance`),
    and return its marginal over ``[x_k, objects]``.

    If the solution or its marginal is not finite (a near-singular graph: noise variances of 1e-10
    next to unobserved object headings), the component keeps the ``mean`` and ``cov`` it was given
    (the filter's update; the hybrid belief's prediction) and its previous trajectory with ``x_k``
    from ``mean``, and the result says ``nonfinite``: the step's warning counts it, and nothing
    downstream sees a NaN.
    """
    start = poses.at[k].set(mean[:3])
    sol = sm.solve(g, start, mean[3:].reshape(-1, 3), max_steps=settings.max_steps, cost_atol=cost_atol)
    m, c = sm.marginal(sol, k)
    ok = jnp.all(jnp.isfinite(sol.poses)) & jnp.all(jnp.isfinite(m)) & jnp.all(jnp.isfinite(c))
    result = optx.RESULTS.where(ok, sol.result, optx.RESULTS.nonfinite)
    return Smoothed(jnp.where(ok, sol.poses, start), jnp.where(ok, m, mean), jnp.where(ok, c, cov), result,
                    active=sol.active)


def smooth_lag(
    settings: Lag, log: DataLog, factors: Factors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
    sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
    poses: Float[Array, "T1 3"], mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"], window: WindowPrior,
) -> Smoothed:
    """One fixed-lag step of a component after ``k`` steps (module docstring): slide the window if
    ``k > length`` (marginalize ``x_{k-1-length}`` at the warm start), re-solve the window, and return
    the marginal over ``[x_k, objects]``, the trajectory with the window written back, and the new
    window prior. Non-finite results fall back as in :func:`smooth` (the window prior then stays the
    old one, moved to the window's new first pose: an approximation, counted as ``nonfinite``)."""
    length = settings.length
    start = poses.at[k].set(mean[:3])
    objects = mean[3:].reshape(-1, 3)
    old, new = jnp.maximum(k - 1 - length, 0), jnp.maximum(k - length, 0)
    g_old = window_graph(log, factors, k, old, length, num_created, sensor, motion_cov, semantic, mode, window)
    m_mean, _, m_info = sm.marginalize_first_information(
        g_old, jax.lax.dynamic_slice_in_dim(start, old, length + 1), objects)
    # Objects not created yet carry no factor: keep their own prior rows (a heading prior only),
    # not the identity block the elimination gives inactive variables. Those rows touch no active
    # coordinate (nor do the active rows touch them), so the information splits the same way.
    inactive = jnp.concatenate([jnp.zeros(3, bool), jnp.repeat(~g_old.object_active, 3)])
    m_mean = jnp.where(inactive, window.mean, m_mean)
    m_info = jnp.where(inactive[:, None] | inactive[None, :], window.info, m_info)
    slide = new > old
    prior = jax.tree.map(lambda a, b: jnp.where(slide, a, b), WindowPrior(m_mean, m_info), window)
    g = window_graph(log, factors, k, new, length, num_created, sensor, motion_cov, semantic, mode, prior)
    sol = sm.solve(g, jax.lax.dynamic_slice_in_dim(start, new, length + 1), objects, max_steps=settings.max_steps,
                   cost_atol=step_tolerance(settings, log, k))
    m, c = sm.marginal(sol, k - new)
    finite = lambda *a: jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in a]))  # noqa: E731
    ok = finite(sol.poses, m, c, prior.mean, prior.info)
    result = optx.RESULTS.where(ok, sol.result, optx.RESULTS.nonfinite)
    # No usable marginal: the old prior, moved to the new first pose (crude, cheap, and counted).
    fallback = WindowPrior(window.mean.at[:3].set(start[new]), window.info)
    prior = jax.tree.map(lambda a, b, c: jnp.where(ok, a, jnp.where(slide, b, c)), prior, fallback, window)
    trajectory = jax.lax.dynamic_update_slice_in_dim(start, sol.poses, new, axis=0)
    return Smoothed(jnp.where(ok, trajectory, start), jnp.where(ok, m, mean), jnp.where(ok, c, cov), result, prior)


def smooth_step(
    settings: AbstractSmoother, log: DataLog, factors: Factors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
    sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
    poses: Float[Array, "T1 3"], mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
    window: WindowPrior | None = None,
) -> Smoothed:
    """A component's smoothing after ``k`` steps: the whole graph (:class:`Full`, :func:`graph` and
    :func:`smooth`) or a fixed-lag window (:class:`Lag`, :func:`smooth_lag`; ``window`` required):
    ``settings.smooth(...)``."""
    return settings.smooth(log, factors, k, num_created, sensor, motion_cov, semantic, mode, poses, mean, cov,
                           window)


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


def step_tolerance(settings: Full | Lag, log: DataLog, k: Int[Array, ""]) -> Float[Array, ""]:
    """The cost tolerance (nats) of the solve after ``k`` steps: ``settings.step_atol`` before the
    scenario's last step, ``FINAL_ATOL`` at it (and after it, for a caller stepping on)."""
    return jnp.where(k >= log.last_step, FINAL_ATOL, settings.step_atol)


def failed(result: optx.RESULTS) -> Bool[Array, "..."]:
    return jnp.asarray(result != optx.RESULTS.successful)
