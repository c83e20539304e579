"""The candidate search of the loop-closure pass (:mod:`.closure`): which old objects a late
object may be (:func:`candidates`), the score of a joint set of merges (:func:`log_bayes_factor`) and
the beam over the late objects that finds the best sets (:func:`search`).

An object ``a`` first detected at least ``gap`` steps after the last detection of an older object
``b`` may be ``b`` (class realizations equal or open, position difference within the gate). Each
joint set of merges is scored by its log Bayes factor against "every late object is new", from the
Laplace posterior of the unmerged graph (linearized constraints ``p_a − p_b = 0``):

    log BF = log N(0; A μ, A Σ Aᵀ) − Σ_merged (log ρ_new − log r_a)

``A μ`` stacks the position differences, ``Σ`` is the smoother's marginal covariance of the map,
``ρ_new`` the scenario's new-object density in range-bearing space (``discovery``, Doherty thesis
Eq. 4.13's null term), and ``r_a`` the range of the detection that created ``a`` (the Jacobian
``dx dy = r dr dθ`` between the two spaces). The beam assigns each late object one of its gated
candidates or "new", injectively; it is exact when it holds every combination.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .settings import LoopClosureSettings


def object_spans(history: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def creating_ranges(geo: np.ndarray, history: np.ndarray, n: int) -> np.ndarray:
    """Per object, the range (m) of the detection that created it (1 where none)."""
    _, _, creating = object_spans(history, n)
    return np.where(creating >= 0, geo[..., 0].ravel()[np.maximum(creating, 0)], 1.0)


def candidates(
    mean: np.ndarray, cov: np.ndarray, history: np.ndarray, classes: np.ndarray, num: int, settings: LoopClosureSettings,
) -> dict[int, list[int]]:
    """Per late object, its gated old objects, nearest first (module docstring; ``num`` objects in use)."""
    first, last, _ = object_spans(history, num)
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
