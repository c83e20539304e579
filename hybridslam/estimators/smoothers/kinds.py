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
state. The graph (prior, odometry and measurement factors) is rebuilt from what the state already
holds: :mod:`.factors`.

This module holds the smoother objects (:class:`Filter`, :class:`Full`, :class:`Lag`,
:class:`Incremental`), what they keep between steps (:class:`SmootherState`) and their step
(:func:`smooth`, :func:`smooth_lag`); :mod:`hybridslam.estimators.smoothers` lists those ``--smoother`` offers.

``Lag(L)`` (``--smoother lag:L``) is the bounded-cost online option: a fixed-lag smoother whose
window holds the last ``L`` steps (poses ``x_{k-L}..x_k``) and the map. When the window slides, its
oldest pose is marginalized (:func:`~hybridslam.inference.smoother.marginalize_first`: the factors
touching it, linearized at the current estimate, become a dense Gaussian prior on the next oldest
pose and the map, :class:`~.factors.WindowPrior`, kept per component). Exact for linear-Gaussian factors, the
standard fixed-lag approximation otherwise; ``Lag(L)`` with ``L`` at least the run's steps is
``Full()``. Poses that left the window keep their last smoothed value in the trajectory.

``Filter()`` keeps the filters (the behaviour before smoothing; planning uses it).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ...inference import smoother as sm
from ...models.scenario import Scenario
from ...models.measurement import Detections, SensorModel
from .factors import (AnyFactors, DataLog, Factors, WindowPrior, data_log, factor_budget, graph,
                              initial_trajectory, initial_window, window_factor_budget, window_graph)


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
    (:func:`hybridslam.estimators.smoothers.parse_smoother` reads it back).

    ``spelling`` is how ``--smoother`` names the class (``"full"``, or ``"lag:L"`` where the text
    carries a positive number of steps, the class's one argument) and ``summary`` what the option's
    help says of it; a smoother is offered once it is listed in :data:`hybridslam.estimators.smoothers.SMOOTHERS`.
    """

    smooths: ClassVar[bool] = True
    whole_trajectory: ClassVar[bool] = False
    spelling: ClassVar[str] = ""
    summary: ClassVar[str] = ""

    @classmethod
    def from_text(cls, text: str) -> AbstractSmoother | None:
        """This class's smoother if ``text`` spells it (``spelling``, with ``L`` a positive int), else ``None``."""
        head, sep, _ = cls.spelling.partition(":")
        if not sep:
            return cls() if head and text == head else None
        rest = text[len(head) + 1:]
        if text.startswith(head + ":") and rest.isdigit() and int(rest) >= 1:
            return cls(int(rest))  # type: ignore[call-arg]  # a spelling with ":L" is a class of one argument
        return None

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

    def window_budget(self, scenario: Scenario, steps: int, max_steps: int | None, slots: int) -> tuple[int, int]:
        """The window graph's factor slots and poses in a state of ``steps`` history rows built for
        ``scenario`` ((0, 0): no window)."""
        del scenario, steps, max_steps, slots
        return 0, 0

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
        log = data_log(scenario, steps, slots, max_objects, factor_budget(scenario, max_steps, slots),
                       *self.window_budget(scenario, steps, max_steps, slots))
        poses = np.asarray(initial_trajectory(scenario, steps))
        if components is not None:
            poses = np.broadcast_to(poses, (components,) + poses.shape)
        return SmootherState(jax.device_put(poses), log, self.init_window(log, components))

    def closing(self) -> AbstractSmoother:
        """The smoother of a run's last step: this one, except :class:`Incremental`'s (the whole
        graph re-solved once, :class:`Closing`). :func:`hybridslam.driver.run` steps the last step
        of a scenario with it."""
        return self

    def smooth(
        self, state: SmootherState, factors: AnyFactors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
        sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
        mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
    ) -> Smoothed:
        """One component's smoothing after ``k`` steps, from what it keeps (``state``: one
        component's :class:`SmootherState`, its ``poses`` ``(T1, 3)``, the shared data log and, with
        :class:`Lag`, its ``window``), its measurement ``factors`` and the filter's ``mean`` and
        ``cov`` over ``[x_k, objects]``: the whole graph (:class:`Full`,
        :func:`~.factors.graph` and :func:`smooth`) or a fixed-lag window (:class:`Lag`,
        :func:`smooth_lag`)."""
        raise ValueError(f"smoother={self.name}: this smoother does not smooth")


def check_smoother(owner: str, value: object) -> None:
    """A ``ValueError`` naming ``owner.smoother`` unless ``value`` is a smoother."""
    if not isinstance(value, AbstractSmoother):
        raise ValueError(f"{owner}.smoother: expected a smoother (an AbstractSmoother: Full(), Lag(L), "
                         f"Incremental(L), Filter()), got {value!r}")


class Filter(AbstractSmoother):
    """No smoothing: the joint Gaussian over ``[x_k, objects]`` of the filter step."""

    smooths: ClassVar[bool] = False
    spelling: ClassVar[str] = "filter"
    summary: ClassVar[str] = "the joint Gaussian over the current pose and the map only"

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

    spelling: ClassVar[str] = "full"
    summary: ClassVar[str] = ("every component keeps its trajectory and relinearizes it at every step, as the papers' "
                              "smoothers do")

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
        self, state: SmootherState, factors: AnyFactors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
        sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
        mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
    ) -> Smoothed:
        """The whole graph (:func:`~.factors.graph`) re-solved (:func:`smooth`)."""
        log, poses = state.require(self)
        g = graph(log, factors, k, num_created, sensor, motion_cov, semantic, mode)
        return smooth(self, g, poses, mean, cov, k, step_tolerance(self, log, k))


class Lag(AbstractSmoother):
    """Fixed-lag smoothing: the last ``length`` steps and the map re-solved at every step (at most
    ``max_steps`` Levenberg-Marquardt iterations), older poses marginalized (module docstring).
    The cost of a step is bounded by ``length``, not by the steps taken so far."""

    spelling: ClassVar[str] = "lag:L"
    summary: ClassVar[str] = "only the last L steps and the map, older poses marginalized (bounded cost per step)"

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

    def span(self, steps: int) -> int:
        """The window's steps in a state of ``steps`` history rows: ``length``, or every step where the
        state holds fewer (``lag:50`` on a 3-step file smooths as ``full``)."""
        return min(self.length, steps)

    def window_budget(self, scenario: Scenario, steps: int, max_steps: int | None, slots: int) -> tuple[int, int]:
        span = self.span(steps)
        return window_factor_budget(scenario, max_steps, slots, span), span + 1

    def init_window(self, log: DataLog, components: int | None = None) -> WindowPrior | None:
        return initial_window(log, components)

    def smooth(
        self, state: SmootherState, factors: AnyFactors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
        sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
        mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
    ) -> Smoothed:
        """The fixed-lag window re-solved (:func:`smooth_lag`; the state's ``window`` required)."""
        log, poses = state.require(self)
        if state.window is None:
            raise ValueError("smoother=Lag(...): this state carries no window prior (build it with the estimator's init)")
        return smooth_lag(self, log, factors, k, num_created, sensor, motion_cov, semantic, mode, poses, mean,
                          cov, state.window)


class Incremental(Lag):
    """Exact smoothing at a bounded step cost (``--smoother incremental:L``): every step as
    :class:`Lag` ``(L)`` (the last ``L`` steps relinearized and re-solved, older poses marginalized
    at their linearization point), and the run's last step as :class:`Closing`: the whole graph
    relinearized and re-solved to the solver's tolerance, warm-started from the window's
    trajectory. The result file's trajectory is then the batch solution of the final graph, and the
    steps before cost what ``lag:L``'s do.

    This is the iSAM2 idea with static shapes (Kaess et al. 2012): a variable is relinearized only
    while a new factor can still move it (inside the window) and at the end, when the estimate is
    read. Unlike iSAM2, poses behind the window are not updated by back-substitution between the
    two: a step's online estimate of ``x_k`` is the window's (as ``lag:L``'s), and the whole
    trajectory is exact once, at the end. The last step is a program of its own
    (:func:`hybridslam.driver.run`); a study's batched scan, which has no last step of its own
    per track, refuses it (:func:`hybridslam.studies.batch.check_batchable`).

    ``closing_max_steps``: the Levenberg-Marquardt iterations of the closing solve (from the
    window's trajectory the old poses may move far: each iterate is one solve of the whole chain)."""

    spelling: ClassVar[str] = "incremental:L"
    summary: ClassVar[str] = ("every step as lag:L, and the last step re-solves the whole graph, so the result's "
                              "trajectory is the batch solution (a long log's exact smoothing at lag:L's step cost)")

    closing_max_steps: int = eqx.field(default=100, static=True)

    @property
    def name(self) -> str:
        return f"incremental:{self.length}"

    def __check_init__(self):
        if not (isinstance(self.closing_max_steps, int) and self.closing_max_steps >= 1):
            raise ValueError(f"Incremental.closing_max_steps: expected a positive int, got {self.closing_max_steps!r}")

    def closing(self) -> AbstractSmoother:
        return Closing(max_steps=self.closing_max_steps)


class Closing(Full):
    """:class:`Incremental`'s last step: the whole graph re-solved (:class:`Full`), each component's
    window prior handed back unchanged (the state keeps its shapes, and a step after it, if any,
    slides from there)."""

    def smooth(
        self, state: SmootherState, factors: AnyFactors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
        sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
        mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"],
    ) -> Smoothed:
        out = super().smooth(state, factors, k, num_created, sensor, motion_cov, semantic, mode, mean, cov)
        return dataclasses.replace(out, window=state.window)


Smoother = AbstractSmoother


class SmootherState(eqx.Module):
    """What a smoother keeps between steps: one field of every estimator state (``smoothing``),
    made by :meth:`AbstractSmoother.init`. Empty (every field ``None``) under :class:`Filter`.

    ``poses``: each component's trajectory ``x_0..x_T`` (``*K``: the estimator's component axis,
    none for a single Gaussian); ``log``: the data so far, shared by the components; ``window``:
    with :class:`Lag`, each component's window prior on ``[x_s, objects]``; ``factors``: the
    single-Gaussian estimators' measurement factors as decided online (a mixture's estimators
    rebuild theirs from each component's association history, :func:`~.factors.history_factors`)."""

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

    def require(self, smoother: AbstractSmoother) -> tuple[DataLog, Float[Array, "*K T1 3"]]:
        """The data log and trajectory ``smoother`` smooths, or a ``ValueError`` where this state
        has none (built without the smoother's :meth:`AbstractSmoother.init`)."""
        if self.log is None or self.poses is None:
            raise ValueError(f"smoother={smoother.name}: this state carries no trajectory or data log (build it "
                             "with the estimator's init(scenario))")
        return self.log, self.poses

    def record(self, k: Int[Array, ""], odometry: Float[Array, "3"], detections: Detections) -> SmootherState:
        """This state with step ``k + 1``'s inputs written to its log (:meth:`DataLog.record`)."""
        if self.log is None:
            raise ValueError("smoothing: this state carries no data log (built by init_belief or without the "
                             "estimator's init); build it with the estimator's init(scenario) or use smoother=Filter()")
        return eqx.tree_at(lambda s: s.log, self, self.log.record(k, odometry, detections))


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
    settings: Lag, log: DataLog, factors: AnyFactors, k: Int[Array, ""], num_created: Int[Array, ""] | int,
    sensor: SensorModel, motion_cov: Float[Array, "3 3"], semantic: bool, mode: sm.Mode,
    poses: Float[Array, "T1 3"], mean: Float[Array, " D0"], cov: Float[Array, "D0 D0"], window: WindowPrior,
) -> Smoothed:
    """One fixed-lag step of a component after ``k`` steps (module docstring): slide the window if
    ``k > length`` (marginalize ``x_{k-1-length}`` at the warm start), re-solve the window, and return
    the marginal over ``[x_k, objects]``, the trajectory with the window written back, and the new
    window prior. Non-finite results fall back as in :func:`smooth` (the window prior then stays the
    old one, moved to the window's new first pose: an approximation, counted as ``nonfinite``)."""
    length = settings.span(poses.shape[0] - 1)
    cost_atol = step_tolerance(settings, log, k)
    start = poses.at[k].set(mean[:3])
    objects = mean[3:].reshape(-1, 3)
    old, new = jnp.maximum(k - 1 - length, 0), jnp.maximum(k - length, 0)
    # Marginalizing x_old reads only the factors touching it: a graph of x_old, x_{old+1} and
    # x_old's detections (the first of the window's rows), not the whole window linearized and masked.
    g_old = window_graph(log, factors, k, old, 1, num_created, sensor, motion_cov, semantic, mode, window,
                         slots=log.mask.shape[1])
    m_mean, _, m_info = sm.marginalize_first_information(g_old, jax.lax.dynamic_slice_in_dim(start, old, 2), objects)
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
                   cost_atol=cost_atol)
    m, c = sm.marginal(sol, k - new)
    finite = lambda *a: jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in a]))  # noqa: E731
    ok = finite(sol.poses, m, c, prior.mean, prior.info)
    result = optx.RESULTS.where(ok, sol.result, optx.RESULTS.nonfinite)
    # No usable marginal: the old prior, moved to the new first pose (crude, cheap, and counted).
    fallback = WindowPrior(window.mean.at[:3].set(start[new]), window.info)
    prior = jax.tree.map(lambda a, b, c: jnp.where(ok, a, jnp.where(slide, b, c)), prior, fallback, window)
    trajectory = jax.lax.dynamic_update_slice_in_dim(start, sol.poses, new, axis=0)
    return Smoothed(jnp.where(ok, trajectory, start), jnp.where(ok, m, mean), jnp.where(ok, c, cov), result, prior)



def step_tolerance(settings: Full | Lag, log: DataLog, k: Int[Array, ""]) -> Float[Array, ""]:
    """The cost tolerance (nats) of the solve after ``k`` steps: ``settings.step_atol`` before the
    scenario's last step, ``FINAL_ATOL`` at it (and after it, for a caller stepping on)."""
    return jnp.where(k >= log.last_step, FINAL_ATOL, settings.step_atol)


def failed(result: optx.RESULTS) -> Bool[Array, "..."]:
    return jnp.asarray(result != optx.RESULTS.successful)
