"""Loop closure during the run: hypotheses added to a mixture estimator's belief between steps.

The back-end pass (:mod:`.closure`) searches a finished run's map for late objects that are
old ones. :class:`OnlineLoopClosure` runs the same search after a step, on the highest-weight
component, and adds what it finds to the belief as a hypothesis of its own, so that the next steps
associate against the closed map:

1. the component's own closures are re-opened (the pass's ``reopen``: each stretch of an object's
   detections after a pause longer than ``gap`` becomes an object of its own), and that graph is
   solved: the reference of every score below;
2. the pass's beam search over merges (late object ``a`` declared to be old object ``b``), each set
   scored by its log Bayes factor against the reference (Laplace, Doherty thesis Eq. 4.13's
   new-object density) plus the negative information of its re-solved graph, and verified by the
   re-solved cost's rise (:mod:`.search`, :mod:`.verify`);
3. the best set that differs from the component itself (which is the reference with every
   stretch merged back), if its log odds against the component exceed ``settings.threshold``,
   becomes a component: its associations with the objects renumbered in
   creation order, re-solved by the estimator's own factor graph, of log weight
   ``log w + (score of the set − score of the component)``.

The component stays, with its weight: the belief carries both and later detections decide, as they
decide every other association. The new one takes an empty slot, else the lowest-weight component
other than its parent (counted in :attr:`OnlineLoopClosure.replaced`), if it is likelier than that
one (else it is counted in :attr:`OnlineLoopClosure.declined`). A set whose associations an
alive component already has is not added again. The search runs on the host between two compiled
steps (``hybridslam.run(..., between_steps=...)``); its solves compile once per run.

Which estimators: those whose :meth:`~..base.AbstractEstimator.loop_closure_access` gives a
:class:`LoopClosureAccess` (the hybrid belief, :mod:`..hybrid.loops`; ``multimodal``,
:mod:`..multimodal.loops`), with a smoother that keeps the whole trajectory (the new component needs
it re-solved), on an unknown map (only an unknown map has late objects). The search reads the
fields both states share (``log_weights (K,)``, ``mean (K, D)``, ``history (K, T, Dmax)``,
``num_created (K,)``, ``k``, ``model``, ``smoothing``: the data log and each component's
trajectory); what differs (how classes are held, which factors the graph has, how a component is
written) is the access's. Ground truth is never read.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ...inference import smoother as sm
from ...models.scenario import Scenario
from ..base import AbstractEstimator
from ..base import LoopClosureAccess as LoopClosureAccess
from ..base import MergedComponent as MergedComponent
from .merge import compact, reopen
from .search import candidates, creating_ranges, log_bayes_factor, search
from .settings import LoopClosureSettings
from .misses import in_view_probability, uses_marginal
from .verify import judge, misses
from ..smoothers.kinds import FINAL_ATOL
from ..smoothers.factors import DataLog, graph, history_factors


@eqx.filter_jit
def _solve(log: DataLog, model, history, classes, num_created, poses, objects, k, semantic: bool, realize: bool,
           max_steps: int, max_range, fov, marginal: bool):
    """A component's whole graph after ``k`` steps (the estimator's own: its semantic factors, class
    realizations where it has them), solved to the final tolerance: the trajectory, the marginal of
    ``[x_k, objects]``, the cost, whether it converged and, where ``marginal``, each (pose, object)
    pair's :func:`~.misses.in_view_probability` (else ``None``; one compile per run)."""
    factors = history_factors(history, classes if realize else None)
    g = graph(log, factors, k, num_created, model.sensor, model.motion_cov, semantic, "sum")
    sol = sm.solve(g, poses, objects, max_steps=max_steps, cost_atol=FINAL_ATOL)
    mean, cov = sm.marginal(sol, k)
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(mean)) & jnp.all(jnp.isfinite(cov))
    return sol.poses, mean, cov, sol.cost, ok, in_view_probability(sol, max_range, fov) if marginal else None


def _renumber(history: np.ndarray, classes: np.ndarray, objects: np.ndarray, num: int, merges: dict[int, int]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """:func:`_renumbered`, and the old index of each object in use (:func:`~.merge.compact`)."""
    h, cls, used = compact(history, classes, merges, num)
    out = np.zeros((len(classes), 3))
    out[: len(used)] = objects[used]
    return h.astype(history.dtype), cls.astype(classes.dtype), out, len(used), used


def _renumbered(history: np.ndarray, classes: np.ndarray, objects: np.ndarray, num: int,
                merges: dict[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """``merges`` (late -> old) applied to a component's first ``num`` object slots by
    :func:`~.merge.compact` (creation order, as the step keeps them: a prior map's undetected
    objects first, then by first detection): the history, classes, object poses ``(N, 3)`` (freed
    slots: placeholders at 0) and how many objects remain."""
    return _renumber(history, classes, objects, num, merges)[:4]


def _sources(used: np.ndarray, merges: dict[int, int], origin: np.ndarray) -> tuple[tuple[int, ...], ...]:
    """Per renumbered object (``used``: its index in the re-opened numbering), the parent's objects
    it joins: its own origin and those of the objects merged into it (``origin``: re-opened -> parent)."""
    return tuple(tuple(sorted({int(origin[u])} | {int(origin[a]) for a, b in merges.items() if b == u}))
                 for u in used)


class ClosureHypothesis(NamedTuple):
    """A hypothesis :class:`OnlineLoopClosure` added, against its parent component, in the parent's
    object numbering (its own earlier closures not re-opened)."""

    step: int  # after this step (1-based)
    merges: tuple[tuple[int, int], ...]  # (a, b): object a's detections (or a re-opened stretch) are b's
    splits: tuple[int, ...]  # objects whose detections after a pause longer than the gap became objects
    log_odds: float  # against the parent: the new component's log weight is the parent's + this

    def __str__(self) -> str:
        changes = [f"{a}->{b}" for a, b in self.merges] + [f"{o} split" for o in self.splits]
        return f"step {self.step}: {', '.join(changes)} (log odds {self.log_odds:.2f})"


def _closure(k: int, merges, origin: np.ndarray, stretches: range, odds: float) -> ClosureHypothesis:
    """What a merge set (in the re-opened numbering) changes against the parent: merges between
    different objects, and the re-opened stretches it leaves as objects of their own (a stretch
    merged back into its own object changes nothing)."""
    merged = {a for a, _ in merges}
    return ClosureHypothesis(step=k,
                             merges=tuple((int(origin[a]), int(origin[b])) for a, b in merges
                                          if origin[a] != origin[b]),
                             splits=tuple(sorted({int(origin[s]) for s in stretches if s not in merged})),
                             log_odds=float(odds))


def _back_projected(history: np.ndarray, geo: np.ndarray, poses: np.ndarray, objects: np.ndarray,
                    slots: range) -> np.ndarray:
    """``objects`` with each of ``slots`` placed at its first detection seen from ``poses``
    (``x_{j+1}`` for step ``j``): the warm start of objects a re-opening made."""
    out = objects.copy()
    for s in slots:
        j, d = (int(x[0]) for x in np.nonzero(history == s))
        r, bearing = geo[j, d]
        x = poses[j + 1]
        out[s, :2] = x[:2] + r * np.array([np.cos(x[2] + bearing), np.sin(x[2] + bearing)])
    return out


@dataclasses.dataclass
class OnlineLoopClosure:
    """``between_steps`` for :func:`hybridslam.run` (module docstring): after every step from
    ``settings.gap + 1`` on, search the top component's map for loop closures and add the best
    verified merge set as a hypothesis (every ``every`` steps). ``closures`` lists what was added
    (:class:`ClosureHypothesis`: what it changes against its parent); ``replaced`` counts components
    dropped to make room; ``declined`` counts the best sets not added because a full belief held
    only likelier components (possible only with a negative ``settings.threshold``); ``seconds`` the
    time the searches took.

    ``settings.threshold`` is the least log odds of the new hypothesis against its parent (the top
    component). The default, 0, adds only a closure likelier than the component it came from; a
    negative one keeps the hybrid belief's promise of holding the right answer before it is the
    likeliest: ``-log(prune_ratio)`` (-5.01 for the default 150) adds any closure the belief's
    pruning would keep (docs/studies/hallway.md measures both).
    """

    estimator: AbstractEstimator  # one with a LoopClosureAccess and a whole-trajectory smoother: checked
    scenario: Scenario
    settings: LoopClosureSettings = LoopClosureSettings()
    every: int = 1
    closures: list[ClosureHypothesis] = dataclasses.field(default_factory=list)
    replaced: int = 0
    declined: int = 0
    seconds: float = 0.0  # wall time spent searching, summed over the steps

    def __post_init__(self) -> None:
        access = self.estimator.loop_closure_access()
        smoother = getattr(self.estimator, "smoother", None)
        if access is None or smoother is None or not smoother.whole_trajectory:
            raise ValueError("OnlineLoopClosure: needs the hybrid belief or multimodal with the full smoother "
                             f"(smoother=Full()), got {self.estimator.name}"
                             + (f" with smoother={smoother.name}" if smoother is not None else ""))
        self._access: LoopClosureAccess = access
        if not (isinstance(self.every, int) and self.every >= 1):
            raise ValueError(f"OnlineLoopClosure.every: expected a positive int, got {self.every!r}")
        if self.scenario.discovery is None:
            raise ValueError("OnlineLoopClosure: the scenario has a known map (no discovery); there are no new "
                             "objects to merge")

    def __call__(self, k: int, belief):
        """The belief after step ``k`` (1-based), with a loop-closure hypothesis added if one is found."""
        if k <= self.settings.gap or k % self.every:
            return belief
        t0 = time.perf_counter()
        try:
            return self._search(belief)
        finally:
            self.seconds += time.perf_counter() - t0

    def _search(self, belief):
        """:meth:`__call__`'s work (module docstring, steps 1-3)."""
        b = jax.device_get(belief)
        k = int(b.k)
        log_w = np.asarray(b.log_weights)
        i = int(np.argmax(log_w))
        settings = self.settings.for_scenario(self.scenario)
        access = self._access
        history, num = np.asarray(b.history[i]), int(b.num_created[i])
        classes = access.classes(b, i)
        mean, poses = np.asarray(b.mean[i]), np.asarray(b.smoothing.poses)[i]
        geo = np.asarray(b.smoothing.log.geo)
        semantic, realize = access.factors(b)
        assert self.scenario.discovery is not None  # checked on construction
        density = self.scenario.discovery.new_object_log_density
        marginal = uses_marginal(settings)

        def solve(h, c, n, p, objects):
            out = _solve(belief.smoothing.log, belief.model, jnp.asarray(h), jnp.asarray(c),
                         jnp.asarray(n, jnp.int32), jnp.asarray(p), jnp.asarray(objects), jnp.asarray(k), semantic,
                         realize, access.max_steps, jnp.asarray(self.scenario.max_range, float),
                         jnp.asarray(self.scenario.fov, float), marginal)
            p2, m2, c2, cost, ok, in_view = jax.device_get(out)
            objects2 = np.asarray(m2)[3:].reshape(-1, 3)
            missed = misses(self.scenario, np.asarray(p2), objects2, in_view, h[:k], n, settings)
            return np.asarray(p2), np.asarray(m2), np.asarray(c2), float(cost), bool(ok), missed

        # The component's own closures re-opened (the pass's reopen): each stretch of an object's
        # detections after a pause longer than the gap becomes an object of its own.
        h_r, c_r, origin, added = reopen(history, classes, settings.gap)
        num_r = num + added
        objects_r = _back_projected(h_r, geo, poses, mean[3:].reshape(-1, 3), range(num, num_r))
        p_r, mean_r, cov_r, cost_r, ok_r, misses_r = solve(h_r, c_r, num_r, poses, objects_r)
        if not ok_r:
            return belief
        ranges = creating_ranges(geo[:k], h_r[:k], num_r)
        cands = candidates(mean_r, cov_r, h_r[:k], c_r, num_r, settings)
        ranked, _ = search(mean_r, cov_r, cands, density, ranges, settings.beam, settings.revisit_log_odds)
        # The parent is the re-opened graph with every stretch merged back: its log odds against it.
        back = tuple((s, int(origin[s])) for s in range(num, num_r))
        parent_odds = 0.0
        if back:
            *_, misses_0 = solve(history, classes, num, poses, mean[3:].reshape(-1, 3))
            parent_odds = (log_bayes_factor(mean_r, cov_r, back, density, ranges)
                           + settings.revisit_log_odds * len(back)
                           + misses_0 - misses_r)
        alive = np.flatnonzero(log_w > -np.inf)
        best = None
        for merges, lbf in ranked[: settings.tries]:
            if set(merges) == set(back):
                continue  # the parent itself
            h2, c2, o2, n2, used = _renumber(h_r, c_r, mean_r[3:].reshape(-1, 3), num_r, dict(merges))
            if any(np.array_equal(h2, np.asarray(b.history[j])) for j in alive):
                continue  # an alive component already holds these associations
            p2, mean2, cov2, cost2, ok2, misses2 = solve(h2, c2, n2, p_r, o2)
            score = judge(lbf, cost2 - cost_r, ok2, misses2 - misses_r, len(merges), settings)
            if not score.verified:
                continue
            odds = score.log_odds - parent_odds
            if odds > settings.threshold and (best is None or odds > best[0]):
                best = (odds, merges, MergedComponent(h2, c2, n2, p2, mean2, cov2,
                                                      _sources(used, dict(merges), origin)))
        if best is None or len(log_w) < 2:  # a belief of one component has no room for a second hypothesis
            return belief
        odds, merges, component = best
        inserted = self._insert(belief, i, log_w[i] + odds, component)
        if inserted is not belief:
            self.closures.append(_closure(k, merges, origin, range(num, num_r), odds))
        return inserted

    def _insert(self, belief, parent: int, log_weight: float, component: MergedComponent):
        """``belief`` with the merged component in an empty slot, else in the weakest but the parent's
        if it is likelier than that one; else ``belief`` itself, the set counted as declined (the belief
        keeps its most probable components; only a negative ``threshold`` lets such a set this far)."""
        log_w = np.asarray(belief.log_weights).copy()
        dead = np.flatnonzero(log_w == -np.inf)
        if dead.size:
            j = int(dead[0])
        else:
            order = np.argsort(log_w)
            j = int(order[0] if order[0] != parent else order[1])
            if log_weight <= log_w[j]:
                self.declined += 1
                return belief
            self.replaced += 1
        log_w[j] = log_weight
        log_w = log_w - np.logaddexp.reduce(log_w[log_w > -np.inf])
        return self._access.write(belief, j, log_w, component, parent)


def write_fields(state, slot: int, fields, values) -> Any:
    """``state`` with row ``slot`` of each array that ``fields(state)`` names set to its entry of
    ``values``, and an array wrapped by :func:`whole` taking its field's place whole (on the host: a
    device-side ``.at[j].set`` would compile a program per field on first use)."""
    host = jax.device_get(fields(state))
    out = []
    for array, value in zip(host, values):
        if isinstance(value, _Whole):
            out.append(jnp.asarray(value.array))
            continue
        array = np.array(array)
        array[slot] = value
        out.append(jnp.asarray(array))
    return eqx.tree_at(fields, state, tuple(out))


class _Whole(NamedTuple):
    """A field :func:`write_fields` replaces whole (the log weights), not one row of."""

    array: np.ndarray


def whole(array: np.ndarray) -> _Whole:
    """Mark ``array`` as a whole field for :func:`write_fields`."""
    return _Whole(array)
