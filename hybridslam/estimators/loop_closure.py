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
re-scored with negative information, as the sensor model has it (a detection of every object in the
footprint): each (step, object) pair whose solved object lies inside the footprint of the solved
pose (by ``fov_margin``) with no detection associated to it, more or fewer than before the merge,
adds ``log(1 − detection_probability)`` or takes it away. The best set scoring above ``threshold``
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
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from statistics import NormalDist

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..inference import smoother as sm
from ..io.result import ComponentRecord, Result
from ..io.scenario import Scenario
from ..models.model import model_from_scenario
from . import smoothing
from .gaussian import chi2_gate


@dataclasses.dataclass(frozen=True)
class LoopClosureSettings:
    """``gap``: steps between an old object's last detection and a late object's first (default
    20); ``gate``: squared Mahalanobis distance of a candidate pair's position difference (default
    25, wide: the pass is about drift of several sd); ``candidates``: old objects kept per late object
    (default 8); ``beam``: partial joint assignments kept (default 256); ``threshold``: the least log
    posterior odds to accept (default 0: more likely closed than not); ``revisit_log_odds``: the
    prior log odds, per merge, that a late object is an old one rather than new (default 0: the
    estimators' own model, in which a detection is a new object or a known one with no prior
    preference; a positive value says the robot expects to revisit, e.g. once the map is complete);
    ``verify_probability`` (default 0.999) and ``tries`` (default 8): the sets re-solved and
    verified per round; ``reopen`` (default True): first undo the run's own loop closures, so that
    the search decides them jointly with the rest (module docstring); ``detection_probability``
    (``None``, the default: the scenario's ``sensor.detection_probability``, 0.9 where the file has
    none; 0 leaves negative information out), ``min_miss_probability`` (default 0.1: the least
    probability a miss is given, so a miss costs at most ``log 0.1``. The footprint test is on the
    solved estimate, not on the truth, so an object the estimate puts just inside may be truly
    outside; a sensor that never misses, detection probability 1 (the hallway simulator's), would
    otherwise rule out every merge that adds one miss. Measured: with 0.01 the small hallway loop of
    ``tests/test_online_loop_closure.py`` is no longer closed during the run, 1.76 m off at the end
    against 0.5 m) and ``fov_margin`` (default 0.5 m, 0.2 rad) of the
    negative-information term; ``max_rounds`` (default 5; 0: only re-solve the graph); ``max_steps``: Levenberg-Marquardt
    iterations per solve (default 100)."""

    gap: int = 20
    gate: float = 25.0
    candidates: int = 8
    beam: int = 256
    threshold: float = 0.0
    revisit_log_odds: float = 0.0
    verify_probability: float = 0.999
    max_rounds: int = 5
    tries: int = 8
    reopen: bool = True
    detection_probability: float | None = None
    min_miss_probability: float = 0.1
    fov_margin: tuple[float, float] = (0.5, 0.2)
    max_steps: int = 100

    def __post_init__(self):
        for name in ("gap", "candidates", "beam", "max_rounds", "tries", "max_steps"):
            v, least = getattr(self, name), 0 if name in ("gap", "max_rounds") else 1
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= least):
                raise ValueError(f"LoopClosureSettings.{name}: expected a {'non-negative' if least == 0 else 'positive'}"
                                 f" int, got {v!r}")
        if not math.isfinite(self.revisit_log_odds):
            raise ValueError(f"LoopClosureSettings.revisit_log_odds: expected a finite number, got {self.revisit_log_odds!r}")
        if not (math.isfinite(self.gate) and self.gate > 0):
            raise ValueError(f"LoopClosureSettings.gate: expected a positive number, got {self.gate!r}")
        if not math.isfinite(self.threshold):
            raise ValueError(f"LoopClosureSettings.threshold: expected a finite number, got {self.threshold!r}")
        chi2_gate(self.verify_probability)  # raises on a probability outside (0, 1)
        if self.detection_probability is not None and not 0.0 <= self.detection_probability <= 1.0:
            raise ValueError("LoopClosureSettings.detection_probability: expected a number in [0, 1] or None, got "
                             f"{self.detection_probability!r}")
        if not 0.0 < self.min_miss_probability <= 1.0:
            raise ValueError("LoopClosureSettings.min_miss_probability: expected a number in (0, 1], got "
                             f"{self.min_miss_probability!r}")
        if len(self.fov_margin) != 2 or not all(math.isfinite(m) and m >= 0 for m in self.fov_margin):
            raise ValueError(f"LoopClosureSettings.fov_margin: expected two non-negative numbers, got {self.fov_margin!r}")


    def for_scenario(self, scenario: Scenario) -> LoopClosureSettings:
        """These settings with ``detection_probability`` decided: its own value, else the scenario's
        ``sensor.detection_probability``, else :data:`DEFAULT_DETECTION_PROBABILITY`."""
        if self.detection_probability is not None:
            return self
        p = scenario.detection_probability
        return dataclasses.replace(self, detection_probability=DEFAULT_DETECTION_PROBABILITY if p is None else p)


DEFAULT_DETECTION_PROBABILITY = 0.9  # a file without sensor.detection_probability


@dataclasses.dataclass(frozen=True)
class Closure:
    """One accepted round: ``merges`` ``(late, old)`` object pairs (indices of the run's final
    component before the pass), its score (``log_bayes_factor``: log posterior odds against no
    merge, the negative-information term included) and the smoother cost before and after."""

    merges: tuple[tuple[int, int], ...]
    log_bayes_factor: float
    cost_before: float
    cost_after: float


@dataclasses.dataclass(frozen=True)
class LoopClosureReport:
    """What :func:`close_loops` did: the accepted rounds; ``considered``: late objects with at least one
    gated candidate, summed over rounds; ``beam_dropped``: partial assignments the beam dropped
    (0: the search was exhaustive); ``rejected``: merge sets whose re-solved graph failed verification (each undone);
    ``failed``: whether a solve did not converge (the last good solution is kept); ``reopened``: the
    run's own loop closures re-opened (``reopen``), each a later stretch of an object's detections
    made a late object of its own (a merge back onto the same object confirms it)."""

    closures: tuple[Closure, ...]
    considered: int
    beam_dropped: int
    rejected: int
    failed: bool
    reopened: int = 0

    @property
    def merged(self) -> int:
        return sum(len(c.merges) for c in self.closures)

    def summary(self) -> str:
        pairs = ", ".join(f"{a}->{b}" for c in self.closures for a, b in c.merges) or "none"
        lines = [f"loop closure: {self.merged} objects merged ({pairs}) in {len(self.closures)} round(s); "
                 f"{self.considered} late objects had candidates; {self.reopened} of the run's own closures re-opened"]
        if self.beam_dropped:
            lines.append(f"warning: the beam dropped {self.beam_dropped} partial assignments (raise the beam: "
                         "LoopClosureSettings.beam, close-loops --beam)")
        if self.rejected:
            lines.append(f"warning: {self.rejected} merge set(s) failed verification and were undone")
        if self.failed:
            lines.append("warning: a smoother solve did not converge; the last converged solution is kept")
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class _Problem:
    """The data of a run as arrays, and the slot history of its final top component."""

    scenario: Scenario
    log: smoothing.DataLog
    history: np.ndarray  # (T, Dmax) object per detection, -1 none / padding
    classes: np.ndarray  # (N,) class realization, -1 open
    geo: np.ndarray  # (T, Dmax, 2)


def _problem(scenario: Scenario, component: ComponentRecord) -> _Problem:
    classes = np.asarray(component.classes, dtype=np.int64)
    log = smoothing.scenario_log(scenario, len(classes))
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


def compact(history: np.ndarray, classes: np.ndarray, merges: dict[int, int],
            num: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Apply ``merges`` (late -> old; the old object takes the late one's class where its own is
    open) and renumber the objects in order of first detection (with ``num``, the objects below it
    that no detection names come first, in index order: a prior map's undetected objects, kept):
    the new history, classes (padded with -1 to the same length) and the old index of each new one."""
    h, cls = history.copy(), classes.copy()
    for a, b in merges.items():
        h[history == a] = b
        if cls[b] < 0:
            cls[b] = classes[a]
    detected = list(dict.fromkeys(int(s) for s in h.ravel() if s >= 0))  # row-major: order of first detection
    named = set(detected)
    used = [s for s in range(num or 0) if s not in named and s not in merges] + detected
    new_of = np.full(len(classes), -1, dtype=np.int64)
    new_of[used] = np.arange(len(used))
    out = np.where(h >= 0, new_of[np.maximum(h, 0)], -1).astype(np.int32)
    out_cls = np.full(len(classes), -1, dtype=np.int64)
    out_cls[: len(used)] = cls[used]
    return out, out_cls, np.asarray(used, dtype=np.int64)


@eqx.filter_jit
def _solve_graph(log: smoothing.DataLog, model, history, poses, objects, num_created, max_steps: int):
    """Solve the whole graph of ``history`` and take the marginal of ``[x_T, objects]`` (one compile per shape)."""
    t = log.mask.shape[0]
    g = smoothing.graph(log, smoothing.history_factors(history), jnp.asarray(t), num_created, model.sensor,
                        model.motion_cov, semantic=False)
    sol = sm.solve(g, poses, objects, max_steps=max_steps)
    mean, cov = sm.marginal(sol, t)
    return sol.poses, sol.objects, sol.cost, mean, cov, sol.result == optx.RESULTS.successful


class _Solver:
    """:func:`_solve_graph` for one run (the history is an argument: merges do not recompile)."""

    def __init__(self, problem: _Problem, max_steps: int):
        self._model = model_from_scenario(problem.scenario.replace(discovery=None))
        self._log, self._max_steps = problem.log, max_steps

    def __call__(self, history, poses, objects, num_created):
        out = jax.device_get(_solve_graph(self._log, self._model, jnp.asarray(history), jnp.asarray(poses),
                                          jnp.asarray(objects), jnp.asarray(num_created), self._max_steps))
        return tuple(np.asarray(x) for x in out[:5]) + (bool(out[5]),)


def _span(history: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per object (``n``): the step of its first and of its last detection (-1: none), and the flat
    index ``j * Dmax + i`` of its first detection (-1: none)."""
    flat = history.ravel()
    seen = np.flatnonzero(flat >= 0)  # row-major: in time order
    objects, at = np.unique(flat[seen], return_index=True)
    creating = np.full(n, -1)
    creating[objects] = seen[at]
    last = np.full(n, -1)
    np.maximum.at(last, flat[seen], seen // history.shape[1])
    first = np.where(creating >= 0, creating // history.shape[1], -1)
    return first, last, creating


def _initial_objects(problem: _Problem, history: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Each object back-projected from its first detection at ``poses`` (``x_{j+1}`` for step ``j``)."""
    n = len(problem.classes)
    _, _, creating = _span(history, n)
    has = creating >= 0
    j = creating[has] // history.shape[1]
    r, b = problem.geo.reshape(-1, 2)[creating[has]].T
    x = poses[j + 1]
    objects = np.zeros((n, 3))
    objects[has, 0] = x[:, 0] + r * np.cos(x[:, 2] + b)
    objects[has, 1] = x[:, 1] + r * np.sin(x[:, 2] + b)
    return objects


def creating_ranges(geo: np.ndarray, history: np.ndarray, n: int) -> np.ndarray:
    """Per object, the range (m) of the detection that created it (1 where none)."""
    _, _, creating = _span(history, n)
    return np.where(creating >= 0, geo[..., 0].ravel()[np.maximum(creating, 0)], 1.0)


def candidates(
    mean: np.ndarray, cov: np.ndarray, history: np.ndarray, classes: np.ndarray, num: int, settings: LoopClosureSettings,
) -> dict[int, list[int]]:
    """Per late object, its gated old objects, nearest first (module docstring; ``num`` objects in use)."""
    first, last, _ = _span(history, num)
    idx = 3 + 3 * np.arange(num)[:, None] + np.arange(2)  # (num, 2): each object's x, y in [x_T, objects]
    p = mean[idx]
    c = cov[idx[:, :, None, None], idx[None, None]]  # (a, 2, b, 2)
    block = np.einsum("aiaj->aij", c)
    cross = c.transpose(0, 2, 1, 3)  # (a, b, 2, 2): Cov(p_a, p_b)
    s = block[:, None] + block[None, :] - cross - cross.transpose(1, 0, 2, 3)  # ... − Cov(p_b, p_a)
    d = p[:, None] - p[None, :]
    ok = (last[None, :] >= 0) & (first[:, None] - last[None, :] > settings.gap) & (first[None, :] < first[:, None])
    ok &= (classes[:num, None] < 0) | (classes[None, :num] < 0) | (classes[:num, None] == classes[None, :num])
    s = np.where(ok[..., None, None], s, np.eye(2))  # pairs left out: any invertible matrix
    d2 = np.einsum("abi,abi->ab", d, np.linalg.solve(s, d[..., None])[..., 0])
    ok &= d2 < settings.gate
    out: dict[int, list[int]] = {}
    for a in np.flatnonzero(ok.any(axis=1)):
        near = np.flatnonzero(ok[a])
        out[int(a)] = [int(b) for b in near[np.argsort(d2[a, near], kind="stable")][: settings.candidates]]
    return out


def log_bayes_factor(mean: np.ndarray, cov: np.ndarray, merges: Sequence[tuple[int, int]],
                     new_log_density: float, ranges: np.ndarray) -> float:
    """``log BF`` of the merges against none (module docstring): ``ranges[a]``, the range (m) of the
    detection that created late object ``a``; ``new_log_density`` in log (1 / (m rad))."""
    if not merges:
        return 0.0
    rows = np.array([3 + 3 * s + c for a, _ in merges for s, c in ((a, 0), (a, 1))])
    cols = np.array([3 + 3 * s + c for _, b in merges for s, c in ((b, 0), (b, 1))])
    d = mean[rows] - mean[cols]
    s = cov[np.ix_(rows, rows)] + cov[np.ix_(cols, cols)] - cov[np.ix_(rows, cols)] - cov[np.ix_(cols, rows)]
    chol = np.linalg.cholesky(s)
    z = np.linalg.solve(chol, d)
    log_n = -0.5 * z @ z - np.sum(np.log(np.diag(chol))) - 0.5 * len(d) * math.log(2 * math.pi)
    return float(log_n - sum(new_log_density - math.log(max(ranges[a], 1e-9)) for a, _ in merges))


def search(mean: np.ndarray, cov: np.ndarray, cands: dict[int, list[int]], new_log_density: float,
           ranges: np.ndarray, beam: int, log_odds: float = 0.0) -> tuple[list[tuple[tuple[tuple[int, int], ...], float]], int]:
    """The best injective merge set (each late object: a candidate or new) by :func:`log_bayes_factor`
    plus ``log_odds`` per merge (the prior), a beam over the late objects in order; returns the kept
    sets, best first, each with its log posterior odds against no merge, and how many partial sets
    the beam dropped.

    Each partial set carries the Cholesky factor ``L`` of its stacked differences' covariance and
    ``z = L⁻¹ A μ``, so that adding a merge is one 2-row extension of the factor (the conditional
    Gaussian of the new difference given the set's): the same score as :func:`log_bayes_factor`, to
    rounding. Every extension of every partial set by every candidate of a late object is one batched
    computation (sets of fewer merges padded with identity rows)."""
    n_obj = (len(mean) - 3) // 3
    # The beam: scores (B,), factors (B, M, M), z (B, M), the stacked rows of each set's late and old
    # objects (B, M; padding: row 0, masked), the objects each set has taken (B, N), the sets.
    score = np.zeros(1)
    chol, z = np.zeros((1, 0, 0)), np.zeros((1, 0))
    late, old, used = np.zeros((1, 0), int), np.zeros((1, 0), int), np.zeros((1, 0), bool)
    taken = np.zeros((1, n_obj), bool)
    sets: list[tuple[tuple[int, int], ...]] = [()]
    dropped = 0
    for a in sorted(cands):
        ia = np.array([3 + 3 * a, 4 + 3 * a])
        bs = np.array(cands[a], dtype=int)
        ib = np.stack([3 + 3 * bs, 4 + 3 * bs], axis=-1)  # (G, 2)
        d = mean[ia][None] - mean[ib]  # (G, 2)
        s_ee = (cov[np.ix_(ia, ia)][None] + cov[ib[:, :, None], ib[:, None, :]] - cov[ia[None, :, None], ib[:, None, :]]
                - cov[ib[:, :, None], ia[None, None, :]])  # (G, 2, 2)
        v = cov[:, ia][None] - cov[:, ib].transpose(1, 0, 2)  # (G, D, 2): Cov(·, p_a − p_b)
        c = (v[:, late] - v[:, old]) * used[None, :, :, None]  # (G, B, M, 2): Cov(set, new)
        if chol.shape[-1]:  # one factorization per set for every candidate: (B, M, G·2)
            rhs = c.transpose(1, 2, 0, 3).reshape(c.shape[1], c.shape[2], -1)
            lc = np.linalg.solve(chol, rhs).reshape(c.shape[1], c.shape[2], c.shape[0], 2).transpose(2, 0, 1, 3)
        else:
            lc = c  # (G, B, M, 2)
        schur = s_ee[:, None] - np.swapaxes(lc, -1, -2) @ lc  # (G, B, 2, 2)
        r = d[:, None] - np.einsum("gbmi,bm->gbi", lc, z)
        ok = ~taken[:, bs].T  # (G, B): injective
        ok &= (schur[..., 0, 0] > 0) & (schur[..., 0, 0] * schur[..., 1, 1] - schur[..., 0, 1] * schur[..., 1, 0] > 0)
        ls = np.linalg.cholesky(np.where(ok[..., None, None], schur, np.eye(2)))
        ze = np.linalg.solve(ls, r[..., None])[..., 0]
        per_merge = log_odds - (new_log_density - math.log(max(ranges[a], 1e-9)))
        inc = (-0.5 * np.sum(ze * ze, -1) - np.log(ls[..., 0, 0]) - np.log(ls[..., 1, 1]) - math.log(2 * math.pi)
               + per_merge)
        grown = np.concatenate([score, np.where(ok & np.isfinite(inc), score[None] + inc, -np.inf).ravel()])
        order = np.argsort(-grown, kind="stable")
        order = order[np.isfinite(grown[order])]
        dropped += max(len(order) - beam, 0)
        order = order[:beam]
        keep, ext = order[order < len(score)], order[order >= len(score)] - len(score)
        g, bi = np.divmod(ext, len(score))
        m = chol.shape[-1]
        grow = len(ext) > 0
        size = m + 2 if grow else m
        new_chol = np.broadcast_to(np.eye(size), (len(order), size, size)).copy()
        new_z, new_late = np.zeros((len(order), size)), np.zeros((len(order), size), int)
        new_old, new_used = np.zeros((len(order), size), int), np.zeros((len(order), size), bool)
        src = np.concatenate([keep, bi])
        new_chol[:, :m, :m], new_z[:, :m] = chol[src], z[src]
        new_late[:, :m], new_old[:, :m], new_used[:, :m] = late[src], old[src], used[src]
        if grow:
            e = slice(len(keep), None)
            new_chol[e, m:, :m] = np.swapaxes(lc[g, bi], -1, -2)
            new_chol[e, m:, m:] = ls[g, bi]
            new_z[e, m:] = ze[g, bi]
            new_late[e, m:], new_old[e, m:], new_used[e, m:] = ia, ib[g], True
        new_taken = taken[src].copy()
        new_taken[np.arange(len(keep), len(order)), bs[g]] = True
        score = np.concatenate([score[keep], grown[len(score):][ext]])
        sets = [sets[i] for i in keep] + [sets[i] + ((a, int(bs[j])),) for j, i in zip(g, bi)]
        chol, z, late, old, used, taken = new_chol, new_z, new_late, new_old, new_used, new_taken
    ranked = sorted(zip(score, range(len(sets))), key=lambda x: -x[0])
    return [(sets[i], float(sc)) for sc, i in ranked], dropped


@dataclasses.dataclass(frozen=True)
class MergeScore:
    """How the pass judges one merge set (:func:`score_merges`): ``log_bayes_factor`` against no
    merge (Laplace, from the unmerged graph; ``revisit_log_odds`` per merge included), the
    ``negative_information`` term of the re-solved graph (log-likelihood change of the misses),
    ``log_odds``, their sum (what :func:`close_loops` compares with ``threshold``), ``cost_rise``
    (smoother cost after the merge minus before, re-solved) and whether it passes verification
    (``verified``: converged, and ``2 · cost_rise`` within the chi-square ``verify_probability``
    quantile)."""

    log_bayes_factor: float
    negative_information: float
    cost_rise: float
    verified: bool

    @property
    def log_odds(self) -> float:
        return self.log_bayes_factor + self.negative_information


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
        short = pauses(problem.history, settings.gap) - (len(problem.classes) - _used(problem.history))
        if short > 0:
            extra = -(-short // 8) * 8
            problem = _problem(scenario, dataclasses.replace(top, classes=[*top.classes, *[-1] * extra]))
    solver = _Solver(problem, settings.max_steps)
    history, classes = problem.history, problem.classes
    origin = np.arange(len(classes))  # each current object's index in the run's own numbering
    reopened = 0
    if reopen_closures:
        history, classes, origin, reopened = reopen(history, classes, settings.gap)
    poses = result.trajectory if result.trajectory is not None else _online_trajectory(scenario, result)
    poses = np.asarray(poses, float)[: scenario.num_steps + 1]
    num = int(history.max(initial=-1)) + 1
    p, o, cost, mean, cov, ok = solver(history, poses, _initial_objects(problem, history, poses), num)
    return problem, solver, _Solved(history, classes, num, p, o, float(cost), mean, cov), origin, reopened, ok


def _merged(problem: _Problem, solver: _Solver, g: _Solved, merges: Sequence[tuple[int, int]], lbf: float,
            settings: LoopClosureSettings, base_misses: int) -> tuple[MergeScore, _Solved, np.ndarray, bool]:
    """``merges`` applied to ``g`` and re-solved (warm-started): the score, the solved graph, the
    old index of each object, and convergence."""
    h2, c2, used = compact(g.history, g.classes, dict(merges))
    p2, o2, cost2, mean2, cov2, ok = solver(h2, g.poses, _pad(g.objects[used], len(g.classes)), len(used))
    extra = misses(problem.scenario, p2, o2, h2, len(used), settings) - base_misses
    return (judge(lbf, float(cost2 - g.cost), ok, extra, len(merges), settings),
            _Solved(h2, c2, len(used), p2, o2, float(cost2), mean2, cov2), used, ok)


def negative_information(extra_misses: int, settings: LoopClosureSettings) -> float:
    """The log-likelihood of ``extra_misses`` more (step, object) pairs in view yet undetected
    (fewer: negative), ``log(max(1 − detection_probability, min_miss_probability))`` each (module
    docstring; ``detection_probability`` ``None`` counts as :data:`DEFAULT_DETECTION_PROBABILITY`)."""
    p = DEFAULT_DETECTION_PROBABILITY if settings.detection_probability is None else settings.detection_probability
    if not p:
        return 0.0
    return extra_misses * math.log(max(1.0 - p, settings.min_miss_probability))


def judge(log_bayes_factor: float, cost_rise: float, converged: bool, extra_misses: int, merged: int,
          settings: LoopClosureSettings) -> MergeScore:
    """A merge set's :class:`MergeScore` from its parts: verified when its re-solve converged and
    ``2 · cost_rise`` lies within the chi-square ``verify_probability`` quantile of its ``2 · merged``
    constraints (2 at least), and :func:`negative_information` of its extra misses."""
    verified = converged and 2.0 * cost_rise <= chi2_quantile(max(2 * merged, 2), settings.verify_probability)
    return MergeScore(log_bayes_factor, negative_information(extra_misses, settings), cost_rise, bool(verified))


def _base_misses(problem: _Problem, g: _Solved, settings: LoopClosureSettings) -> int:
    if not settings.detection_probability:
        return 0
    return misses(problem.scenario, g.poses, g.objects, g.history, g.num, settings)


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


def reopen(history: np.ndarray, classes: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Split every object at each pause of more than ``gap`` steps between its detections (module
    docstring): the new history, classes, each object's original index, and how many objects were
    added. Unchanged (0 added) if the objects would not fit in ``len(classes)`` slots
    (:func:`pauses` counts the objects it would add)."""
    h, cls, origin, added = _split(history, classes, gap)
    if _used(history) + added > len(classes):
        return history, classes, np.arange(len(classes)), 0
    return h, cls, origin, added


def pauses(history: np.ndarray, gap: int) -> int:
    """How many stretches of an object's detections follow a pause of more than ``gap`` steps: the
    objects :func:`reopen` adds, given the slots."""
    return _split(history, np.full(_used(history), -1), gap)[3]


def _used(history: np.ndarray) -> int:
    """The object slots a history names (objects are numbered from 0 in order of creation)."""
    return int(history.max(initial=-1)) + 1


def _split(history: np.ndarray, classes: np.ndarray, gap: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """:func:`reopen`'s split, with the stretches past ``len(classes)`` numbered but not recorded."""
    n = len(classes)
    h = history.copy()
    origin, cls = list(range(n)), list(classes)
    last: dict[int, int] = {}
    current: dict[int, int] = {}
    slot = int(history.max(initial=-1)) + 1
    added = 0
    for j, i in zip(*np.nonzero(history >= 0)):
        s = int(history[j, i])
        if s in last and j - last[s] > gap:
            current[s] = slot
            if slot < n:
                origin[slot], cls[slot] = s, classes[s]
            slot, added = slot + 1, added + 1
        last[s] = int(j)
        h[j, i] = current.get(s, s)
    return h, np.asarray(cls), np.asarray(origin), added


def chi2_quantile(dof: int, probability: float) -> float:
    """The chi-square ``probability`` quantile with ``dof`` degrees of freedom (Wilson-Hilferty; exact for 2)."""
    if dof == 2:
        return chi2_gate(probability)
    z = NormalDist().inv_cdf(probability)
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3


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


def misses(scenario: Scenario, poses: np.ndarray, objects: np.ndarray, history: np.ndarray, num: int,
            settings: LoopClosureSettings) -> int:
    """Negative information: (step, object) pairs where the solved object lies inside the sensor's
    footprint from the solved pose, by ``fov_margin`` (m, rad) at least, yet no detection of that step
    was associated with it."""
    t = history.shape[0]
    d = objects[None, :num, :2] - poses[1: t + 1, None, :2]  # (T, N, 2)
    rng = np.hypot(d[..., 0], d[..., 1])
    bearing = np.angle(np.exp(1j * (np.arctan2(d[..., 1], d[..., 0]) - poses[1: t + 1, None, 2])))
    inside = (rng < scenario.max_range - settings.fov_margin[0]) & (np.abs(bearing) < scenario.fov / 2 - settings.fov_margin[1])
    seen = np.zeros((t, num), bool)
    rows, cols = np.nonzero(history >= 0)
    seen[rows, history[rows, cols]] = True
    return int(np.sum(inside & ~seen))
