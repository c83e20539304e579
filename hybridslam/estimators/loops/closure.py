"""Loop closure by a joint search over the whole map: a back-end pass over a finished run.

Every estimator here associates one step at a time, gated against its current belief. At a loop
that is not enough: the robot comes back metres off (the hallway's true-association smoother is
5.4 m off at the loop, 1.7 reported sd on average), a known object that far away loses to "a new
object" (thesis Eq. 4.13 against the new-object density), and the re-detections make duplicates of
landmarks already mapped. Yet jointly they are decisive: the duplicates' positions are strongly
correlated with each other and with the old map through the trajectory, so the *pair* (or more) of
re-detected landmarks pins down which old landmarks they are far better than either alone.

:func:`close_loops` takes a run's final associations (the highest-weight component of the last
step), re-solves its whole factor graph (:mod:`hybridslam.inference.smoother`: prior, odometry and
range-bearing factors of every associated detection; geometric only), and searches for *merges*:
an object ``a`` first detected at least ``gap`` steps after the last detection of an older object
``b`` is declared to be ``b``. Each joint set of merges is scored by its log Bayes factor against
"every late object is new", from the Laplace posterior of the unmerged graph (linearized
constraints ``p_a − p_b = 0``):

    log BF = log N(0; A μ, A Σ Aᵀ) − Σ_merged (log ρ_new − log r_a)

``A μ`` stacks the position differences, ``Σ`` is the smoother's marginal covariance of the map,
``ρ_new`` the scenario's new-object density in range-bearing space (``discovery``, Eq. 4.13's null
term), and ``r_a`` the range of the detection that created ``a`` (the Jacobian ``dx dy = r dr dθ``
between the two spaces). The search is a beam over the late objects (each: one of its gated
candidates, class realization equal, or new; injective), exact when the beam holds every
combination. The best ``tries`` sets are each applied, the graph re-solved (Levenberg-Marquardt,
warm-started) and verified: its cost may rise by at most the chi-square ``verify_probability``
quantile of the merged constraints, or the set is dropped and counted. The verified sets are
re-scored with negative information (:mod:`.misses`): each (step, object) pair with no
detection associated to it has likelihood ``1 − detection_probability · P(in view)``, ``P(in view)``
under the solved graph's covariance, and the set gains or loses the change of their sum's log
against the graph before the merge. The best set scoring above ``threshold``
is kept; rounds repeat until none is.

The run's own loop closures are re-opened first (``reopen``): where an object's detections
stop for more than ``gap`` steps and then resume, the later stretch becomes an object of its own,
so a wrong closure made one step at a time can be undone and a right one is merged back. Wrong
associations that are not separated by such a gap are kept. Where the run's object slots cannot
hold the stretches (a whole MRCLAM log: 209 stretches, 60 slots), the pass adds slots: after the
run it is not bound by the run's static shapes.

What it does not do: it runs once, after the run, so the online estimates (``pose_mean``) keep the
estimator's associations; only the final step's top component (its associations, classes,
``trajectory`` and ``objects``) is rewritten.

The pass is split by idea: settings and report in :mod:`.settings`, the candidate search and
its Bayes factor in :mod:`.search`, the re-solve and verification in :mod:`.verify`, the
object bookkeeping (merges, re-opening) in :mod:`.merge`; this module runs them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ...io.result import ComponentRecord, Result
from ...models.scenario import Scenario
from ..smoothers import factors as smoother_factors
from .merge import compact, pauses, reopen, used_slots
from .search import candidates, creating_ranges, log_bayes_factor, object_spans, search
from .settings import Closure
from .misses import uses_marginal
from .verify import Solver, judge, misses

# The pass's settings and outcomes, documented (docs/api.md) as importable from here:
from .settings import LoopClosureReport as LoopClosureReport
from .settings import LoopClosureSettings as LoopClosureSettings
from .settings import MergeScore as MergeScore


@dataclasses.dataclass(frozen=True)
class _Problem:
    """The data of a run as arrays, and the slot history of its final top component."""

    scenario: Scenario
    log: smoother_factors.DataLog
    history: np.ndarray  # (T, Dmax) object per detection, -1 none / padding
    classes: np.ndarray  # (N,) class realization, -1 open
    geo: np.ndarray  # (T, Dmax, 2)


def _problem(scenario: Scenario, component: ComponentRecord) -> _Problem:
    classes = np.asarray(component.classes, dtype=np.int64)
    log = smoother_factors.scenario_log(scenario, len(classes))
    history = np.full(log.mask.shape, -1, dtype=np.int32)
    for j, step in enumerate(scenario.steps):
        assoc = np.asarray(component.associations[j], dtype=np.int64)
        if assoc.shape[0] != len(step.detections):
            raise ValueError(f"result: step {j + 1} lists {assoc.shape[0]} associations for "
                             f"{len(step.detections)} detections of the scenario")
        history[j, : assoc.shape[0]] = assoc
    if history.max(initial=-1) >= len(classes):
        raise ValueError(f"result: an association names object {history.max()}, but the component has "
                         f"{len(classes)} classes")
    return _Problem(scenario, log, history, classes, np.asarray(log.geo))


def _initial_objects(problem: _Problem, history: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Each object back-projected from its first detection at ``poses`` (``x_{j+1}`` for step ``j``)."""
    n = len(problem.classes)
    _, _, creating = object_spans(history, n)
    has = creating >= 0
    j = creating[has] // history.shape[1]
    r, b = problem.geo.reshape(-1, 2)[creating[has]].T
    x = poses[j + 1]
    objects = np.zeros((n, 3))
    objects[has, 0] = x[:, 0] + r * np.cos(x[:, 2] + b)
    objects[has, 1] = x[:, 1] + r * np.sin(x[:, 2] + b)
    return objects


@dataclasses.dataclass
class _Solved:
    """One solved graph of the pass: associations, the solution and its marginal of ``[x_T, objects]``."""

    history: np.ndarray
    classes: np.ndarray
    num: int
    poses: np.ndarray
    objects: np.ndarray
    cost: float
    mean: np.ndarray
    cov: np.ndarray
    in_view: np.ndarray | None  # (P, N): each pair's probability of being in view (misses.py), if needed


def _start(scenario: Scenario, result: Result, settings: LoopClosureSettings, reopen_closures: bool):
    """The run's graph solved, before any merge: the problem, its solver, the solution, each
    object's index in the run's own numbering, how many closures were re-opened, and convergence."""
    if scenario.discovery is None:
        raise ValueError("close_loops: the scenario has a known map (no discovery); there are no new objects to merge")
    if len(result.steps) != scenario.num_steps or not result.steps:
        raise ValueError(f"close_loops: the result has {len(result.steps)} steps, the scenario {scenario.num_steps}")
    top = result.steps[-1].components[0]
    problem = _problem(scenario, top)
    if reopen_closures:
        # After the run the pass is not bound by the run's object slots: with the slots full (a
        # whole log: 209 stretches for 60 slots) it re-opens into new ones (a multiple of 8, so that
        # a few more or fewer share a compile).
        short = pauses(problem.history, settings.gap) - (len(problem.classes) - used_slots(problem.history))
        if short > 0:
            extra = -(-short // 8) * 8
            problem = _problem(scenario, dataclasses.replace(top, classes=[*top.classes, *[-1] * extra]))
    solver = Solver(problem.scenario, problem.log, settings.max_steps, uses_marginal(settings))
    history, classes = problem.history, problem.classes
    origin = np.arange(len(classes))  # each current object's index in the run's own numbering
    reopened = 0
    if reopen_closures:
        history, classes, origin, reopened = reopen(history, classes, settings.gap)
    poses = result.trajectory if result.trajectory is not None else _online_trajectory(scenario, result)
    poses = np.asarray(poses, float)[: scenario.num_steps + 1]
    num = int(history.max(initial=-1)) + 1
    p, o, cost, mean, cov, ok, in_view = solver(history, poses, _initial_objects(problem, history, poses), num)
    return (problem, solver, _Solved(history, classes, num, p, o, float(cost), mean, cov, in_view), origin,
            reopened, ok)


def _merged(problem: _Problem, solver: Solver, g: _Solved, merges: Sequence[tuple[int, int]], lbf: float,
            settings: LoopClosureSettings, base_misses: float) -> tuple[MergeScore, _Solved, np.ndarray, bool]:
    """``merges`` applied to ``g`` and re-solved (warm-started): the score, the solved graph, the
    old index of each object, and convergence."""
    h2, c2, used = compact(g.history, g.classes, dict(merges))
    p2, o2, cost2, mean2, cov2, ok, in_view2 = solver(h2, g.poses, _pad(g.objects[used], len(g.classes)), len(used))
    extra = misses(problem.scenario, p2, o2, in_view2, h2, len(used), settings) - base_misses
    return (judge(lbf, float(cost2 - g.cost), ok, extra, len(merges), settings),
            _Solved(h2, c2, len(used), p2, o2, float(cost2), mean2, cov2, in_view2), used, ok)


def _base_misses(problem: _Problem, g: _Solved, settings: LoopClosureSettings) -> float:
    return misses(problem.scenario, g.poses, g.objects, g.in_view, g.history, g.num, settings)


def score_merges(scenario: Scenario, result: Result, merges: Sequence[tuple[int, int]],
                 settings: LoopClosureSettings = LoopClosureSettings()) -> MergeScore:
    """The score :func:`close_loops` gives the merge set ``merges`` (``(late, old)`` pairs of objects
    of the result's final top component, as it is: the run's own closures are not re-opened) in its
    first round: e.g. the true merges of a simulated run, to tell a search that missed them from a
    model that does not favour them. Any pair may be given; the search would only consider gated
    ones. Raises on an object index the component does not use or an object named twice."""
    settings = settings.for_scenario(scenario)
    problem, solver, g, *_ = _start(scenario, result, settings, reopen_closures=False)
    merges = tuple((int(a), int(b)) for a, b in merges)
    named = [x for m in merges for x in m]
    if any(not 0 <= x < g.num for x in named) or len(set(named)) != len(named):
        raise ValueError(f"score_merges: merges {merges} must join distinct objects among the run's {g.num}")
    assert scenario.discovery is not None  # checked by _start
    ranges = creating_ranges(problem.geo, g.history, g.num)
    lbf = log_bayes_factor(g.mean, g.cov, merges, scenario.discovery.new_object_log_density, ranges)
    lbf += settings.revisit_log_odds * len(merges)
    return _merged(problem, solver, g, merges, lbf, settings, _base_misses(problem, g, settings))[0]


def close_loops(scenario: Scenario, result: Result, settings: LoopClosureSettings = LoopClosureSettings(),
                ) -> tuple[Result, LoopClosureReport]:
    """The run ``result`` of ``scenario`` with its loops closed (module docstring), and what was done.

    Needs an unknown map (``discovery``: a known map has no late objects to merge) and a result of
    this scenario (associations of every step). The returned result differs from ``result`` only in
    its last step's top component (associations, classes), its ``trajectory`` and ``objects`` and its
    ``estimator`` text. With nothing merged or re-opened, a result that has a ``trajectory`` is returned as
    it is (this pass's graph is geometric only, the run's may be richer); one without (a filter's)
    gets the re-solved trajectory and objects.
    """
    settings = settings.for_scenario(scenario)
    problem, solver, g, origin, reopened, ok = _start(scenario, result, settings, settings.reopen)
    assert scenario.discovery is not None  # checked by _start
    new_log_density = scenario.discovery.new_object_log_density
    failed = not ok
    closures: list[Closure] = []
    considered = dropped = rejected = 0
    for _ in range(settings.max_rounds):
        cands = candidates(g.mean, g.cov, g.history, g.classes, g.num, settings)
        considered += len(cands)
        if not cands:
            break
        ranges = creating_ranges(problem.geo, g.history, g.num)
        ranked, d = search(g.mean, g.cov, cands, new_log_density, ranges, settings.beam,
                           settings.revisit_log_odds)
        dropped += d
        base_misses = _base_misses(problem, g, settings)
        accepted, best_score = None, settings.threshold
        for merges, lbf in ranked[: settings.tries]:
            if not merges:
                continue
            score, g2, used, ok2 = _merged(problem, solver, g, merges, lbf, settings, base_misses)
            if not score.verified:
                rejected += 1
                failed = failed or not ok2
                continue
            if score.log_odds > best_score:
                accepted, best_score = (merges, score, g2, used), score.log_odds
        if accepted is None:
            break
        merges, score, g2, used = accepted
        closures.append(Closure(tuple((int(origin[a]), int(origin[b])) for a, b in merges), score.log_odds,
                                g.cost, g2.cost))
        g, origin = g2, _pad_index(origin[used], len(g.classes))
    report = LoopClosureReport(tuple(closures), considered, dropped, rejected, failed, reopened)
    if not closures and not reopened and result.trajectory is not None:
        return result, report  # nothing changed: the run's own smoother (its factors, its window) stands
    return _rewrite(result, g.history, g.classes, g.poses, g.objects, g.num, report), report


def _pad(objects: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n, 3))
    out[: len(objects)] = objects
    return out


def _pad_index(index: np.ndarray, n: int) -> np.ndarray:
    out = np.full(n, -1, dtype=np.int64)
    out[: len(index)] = index
    return out


def _online_trajectory(scenario: Scenario, result: Result) -> np.ndarray:
    """x_0 (the prior mean) and each step's online top-component mean: the warm start of a filter's result."""
    return np.vstack([np.asarray(scenario.robot_prior_mean, float)]
                     + [np.asarray(s.components[0].pose_mean, float) for s in result.steps])


def _rewrite(result: Result, history: np.ndarray, classes: np.ndarray, poses: np.ndarray, objects: np.ndarray,
             num: int, report: LoopClosureReport) -> Result:
    last = result.steps[-1]
    top = last.components[0]
    counts = [len(a) for a in top.associations]
    assoc = [history[j, :c].astype(np.int64) for j, c in enumerate(counts)]
    keep = max(len(top.classes), num)  # the run's slots, or more where re-opening needed more (_start)
    # parent=None: the rewritten history need not extend the old parent's (writers link it again)
    comp = dataclasses.replace(top, associations=assoc, classes=[int(c) for c in classes[:keep]], parent=None)
    steps = list(result.steps[:-1]) + [dataclasses.replace(last, components=[comp] + list(last.components[1:]))]
    return dataclasses.replace(
        result, steps=steps, trajectory=np.asarray(poses, float), objects=np.asarray(objects, float)[:keep],
        estimator=f"{result.estimator}, loop closure ({report.merged} merged)")
