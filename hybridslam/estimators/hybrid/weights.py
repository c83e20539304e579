"""PropWeights: the likelihood factor of each child's weight (Eq. 15-17, Algorithm 1 PROPWEIGHTS).

For a parent with propagated Gaussian ``b⁻`` and a child ``(β_k, C)``,

    w_child ∝ w_parent · ∫ P(Z_k | x_k, X^o, C, β_k) · P(β_k | x_k, X^o) · b⁻(x_k, X^o) dx_k dX^o.   (Eq. 16)

Three estimators of the integral, returning ``log ψ`` for every child on the ``(A, Mc)`` grid of
:mod:`hypotheses` (per parent; all parents at once for ``laplace-is``):

* :func:`sampled_log_likelihood` — the paper's Monte-Carlo mean over ``n_s`` draws from ``b⁻``.
  All children (and all parents) share the same standard-normal draws (common random numbers).
  Per draw we build one table of log-likelihoods for every (detection, object, class); a child is
  then a sum of table entries, so no trigonometry is evaluated per child.
* :func:`linearized_log_likelihood` — deterministic: the Gaussian marginal likelihood of the
  linearized measurement model (thesis Eq. 4.14-4.15, ``C = H Σ Hᵀ + Γ``) for all of the child's
  detections jointly, times the probability that the named objects are in view under the
  linearized predictive of range and bearing.
* :func:`laplace_is_log_likelihood` — importance sampling from each child's Laplace approximation
  (:mod:`hybridslam.laplace`), for the children the linearized weights rank best.

The object observation model ``P(β_k | x_k, X^o)`` is the sensor's (:func:`~hybridslam.measurement.log_visibility`):
the paper's 0/1 footprint by default, or its smooth relaxation, which makes every weight a smooth
function of the belief and the model (``docs/gradients.md``). With fixed draws ``eps`` (from the
step's key) the Monte-Carlo estimates are smooth too: the samples are reparameterized.

Unknown maps: a detection that creates a new object is no factor of the integral (its object is
not in ``b⁻``); its whole contribution is :func:`new_object_log_likelihood`, a term of the child's
weight that does not depend on the Gaussian, the same for every estimator. A new object is in view
by construction, so it adds no visibility factor either.

Each returns ``(log ψ, log ψ ignoring visibility, ESS)`` (laplace-is adds whether each mode search
converged). The second is a fallback for a step
whose detections no hypothesis can explain (every child needs an object out of view: a model
violation, e.g. a false detection); :func:`~hybridslam.step.step` uses it only then, and says so
in ``StepInfo.visibility_ignored``.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.scipy.special import logsumexp
from jaxtyping import Array, Bool, Float, Int

from ...inference.batching import fold_live, map_live
from ...inference.laplace import laplace_is
from ...models import se2
from ...models.geometry import range_bearing, range_bearing_jacobians
from ...models.measurement import (
    Detections,
    SensorModel,
    detection_residuals,
    log_visibility,
    log_visibility_probability,
    slot_residuals,
)
from ...models.model import NewObjects
from ...models.unrolled import cholesky_whiten, gaussian_terms, sum_last
from .hypotheses import EMPTY, NEW, Children, HypothesisTable

CHUNK = 4  # parents per chunk of sampled tables (sampled_children)
ROW_CHUNK = 16  # hypothesis-table rows per chunk of linearized children (see linearized_log_likelihood)


def _split(state: Float[Array, " D"]) -> tuple[Float[Array, "3"], Float[Array, "N 3"]]:
    return state[:3], state[3:].reshape(-1, 3)


def _child_log_means(t: Float[Array, "S Dmax N M"], table: HypothesisTable, kids: Children) -> Float[Array, "A Mc"]:
    """``log (1/S) Σ_s exp(Σ_j t[s, j, n_j, c_j])`` for every child, from one :func:`log_mean_exp_outer`.

    A slot reads column ``n·M + c`` of its (object, class); empty slots are the step's masked
    detections, the same for every valid child, so their rows are 0 and any code reads the same
    value. Gated, a slot's columns are its candidates' only (rank ``r`` for object ``n``). A slot
    that creates a new object is no factor: it reads an extra column holding one constant ``c_j``
    in every sample, subtracted afterwards; ``c_j`` is the slot's largest entry, so that no real
    entry is pushed into underflow by the shift of :func:`log_mean_exp_outer`.
    """
    s, dmax, _, m = t.shape
    rank = jnp.asarray(table.assign)[:, None, :]
    if kids.candidates is not None:
        t = jnp.take_along_axis(t, kids.candidates[None, :, :, None], axis=2)
    flat = t.reshape(s, dmax, -1)
    codes = jnp.where(rank >= 0, rank * m + kids.slot_class, 0)
    shift = None
    if np.any(table.assign == NEW):
        top = jnp.max(flat, axis=(0, 2))
        c = jax.lax.stop_gradient(jnp.where(jnp.isfinite(top), top, 0.0))  # the result does not depend on it
        flat = jnp.concatenate([flat, jnp.broadcast_to(c[None, :, None], (s, dmax, 1))], axis=-1)
        codes = jnp.where(rank == NEW, flat.shape[-1] - 1, codes)
        shift = jnp.sum(jnp.where(rank == NEW, c[None, None, :], 0.0), axis=-1)
    out = log_mean_exp_outer(flat)[tuple(codes[..., j] for j in range(dmax))]
    return out if shift is None else out - shift


def _detection_log_likelihoods(sensor, x, obj, z_geo, scores):
    r_geo, r_sem, log_norm = detection_residuals(sensor, x, obj, z_geo, scores)
    return log_norm - 0.5 * (sum_last(r_geo**2) + sum_last(r_sem**2))


def log_likelihood_table(
    sensor: SensorModel, state: Float[Array, " D"], detections: Detections
) -> tuple[Float[Array, "Dmax N M"], Float[Array, " N"]]:
    """``log P(z_j | x, x^o_n, c)`` for every (detection, object, class), and ``log P(object n in view)``
    (``0``/``-inf`` for the hard footprint, finite for the smooth one).

    Trigonometry depends on (robot, object) only; ``vmap`` keeps it unbatched over detections,
    so it is evaluated ``N`` times per state.
    """
    x, objs = _split(state)
    f = jax.vmap(_detection_log_likelihoods, (None, None, 0, None, None))  # objects
    f = jax.vmap(f, (None, None, None, 0, 0))  # detections
    table = f(sensor, x, objs, detections.geo, detections.scores)
    return table, jax.vmap(log_visibility, (None, None, 0))(sensor, x, objs)


def log_mean_exp_outer(tables: Float[Array, "S Dmax B"]) -> Float[Array, "*B"]:
    """``log (1/S) Σ_s exp(Σ_j tables[s, j, i_j])`` for every index tuple ``(i_1, ..., i_Dmax)``.

    Exact log-domain reduction written as one contraction: each (sample, slot) row is shifted by
    its max before ``exp`` and the shifts are restored per sample, so only ``S·Dmax·B``
    exponentials are taken instead of ``S·B^Dmax``. An entry underflows to ``-inf`` only when it is
    ``e^-700`` below the best entry of the same table — far below any pruning threshold.
    """
    s, dmax, _ = tables.shape
    row_max = jnp.max(tables, axis=-1)  # (S, Dmax)
    feasible = jnp.all(row_max > -jnp.inf, axis=-1)
    safe = jnp.where(row_max > -jnp.inf, row_max, 0.0)
    scaled = jnp.exp(tables - safe[..., None])
    shift = jnp.where(feasible, jnp.sum(safe, axis=-1), -jnp.inf)
    top = jnp.max(shift)
    omega = jnp.exp(shift - jnp.where(top > -jnp.inf, top, 0.0))
    letters = "abcdefghijklmnopqrtuvwxyz"[:dmax]
    spec = "s," + ",".join(f"s{c}" for c in letters) + "->" + letters
    total = jnp.einsum(spec, omega, *(scaled[:, j] for j in range(dmax)))
    positive = total > 0.0
    # Double where: an entry that is exactly 0 (log -inf) must give a zero gradient, not NaN.
    return jnp.where(positive, top + jnp.log(jnp.where(positive, total, 1.0)) - math.log(s), -jnp.inf)


def sampled_log_likelihood(
    sensor: SensorModel,
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    detections: Detections,
    eps: Float[Array, "S D"],
    table: HypothesisTable,
    kids: Children,
) -> tuple[Float[Array, "A Mc"], Float[Array, "A Mc"], Float[Array, "A Mc"]]:
    """``log ψ`` of Eq. 16 as the mean over samples ``mean + L eps`` (``cov = L Lᵀ``), per child.

    A child's per-sample log-likelihood is a sum over its slots of table entries, so the mean
    over samples of every combination of (object, class) per slot is one
    :func:`log_mean_exp_outer`; each child then reads its entry.
    """
    samples = mean[None, :] + eps @ jnp.linalg.cholesky(cov).T  # reparameterized: smooth in mean and cov
    lik, log_view = jax.vmap(log_likelihood_table, (None, 0, None))(sensor, samples, detections)
    occupied = detections.mask[None, :, None, None]
    with_view = jnp.where(occupied, lik + log_view[:, None, :, None], 0.0)
    without_view = jnp.where(occupied, lik, 0.0)
    log_psi, log_psi_free = (_child_log_means(t, table, kids) for t in (with_view, without_view))
    # ESS / n_s of the Monte-Carlo terms: (Σ w)² / (n_s Σ w²) = exp(2 log mean w − log mean w²).
    log_mean_sq = _child_log_means(2.0 * with_view, table, kids)
    ess = jnp.where(log_psi > -jnp.inf, jnp.exp(2.0 * log_psi - log_mean_sq), 0.0)
    return log_psi, log_psi_free, ess


def sampled_children(
    sensor: SensorModel,
    mean: Float[Array, "K D"],
    cov: Float[Array, "K D D"],
    detections: Detections,
    eps: Float[Array, "S D"],
    alive: Bool[Array, " K"],
    parent: Int[Array, " C"],
    measured: Int[Array, "C Dmax"],
    slot_class: Int[Array, "C Dmax"],
    axis_name: str | None = None,
) -> tuple[Float[Array, " C"], Float[Array, " C"], Float[Array, " C"]]:
    """:func:`sampled_log_likelihood` (the paper's Eq. 16) for a flat list of ``C`` children (as in
    :func:`laplace_is_children`): the per-sample tables of each parent, then each child's mean over
    samples of the product of its slots' entries. The same draws ``eps`` serve every parent."""

    def parent_tables(m, c):
        samples = m[None, :] + eps @ jnp.linalg.cholesky(c).T
        return jax.vmap(log_likelihood_table, (None, 0, None))(sensor, samples, detections)  # (S,Dmax,N,M), (S,N)

    def terms(lik, log_view, p, objs, classes):
        """Child's per-sample log likelihood with and without the visibility term, (S,) each."""
        occ = objs >= 0
        o = jnp.maximum(objs, 0)
        slots = jnp.arange(objs.shape[0])
        free = jnp.sum(jnp.where(occ[None, :], lik[p][:, slots, o, classes], 0.0), axis=-1)
        return free + jnp.sum(jnp.where(occ[None, :], log_view[p][:, o], 0.0), axis=-1), free

    # Each live chunk of parents writes its tables into one buffer; a dead chunk writes nothing
    # (map_live would stack a zero-filled chunk for it: 3 MB per track and step at n_s = 1000).
    def fold(acc, first, m, c):
        return jax.tree.map(lambda buf, t: jax.lax.dynamic_update_slice_in_dim(buf, t, first, axis=0), acc,
                            jax.vmap(parent_tables)(m, c))

    shapes = jax.eval_shape(parent_tables, mean[0], cov[0])
    size = -(-mean.shape[0] // CHUNK) * CHUNK
    init = jax.tree.map(lambda a: jnp.zeros((size,) + a.shape, a.dtype), shapes)
    lik, log_view = fold_live(fold, init, alive, mean, cov, chunk=CHUNK, axis_name=axis_name)
    with_view, free = jax.vmap(terms, (None, None, 0, 0, 0))(lik, log_view, parent, measured, slot_class)
    log_psi, log_psi_free = jax.vmap(_log_mean)(with_view), jax.vmap(_log_mean)(free)
    ess = jnp.where(log_psi > -jnp.inf, jnp.exp(2.0 * log_psi - jax.vmap(_log_mean)(2.0 * with_view)), 0.0)
    return log_psi, log_psi_free, ess


def _log_mean(terms: Float[Array, " S"]) -> Float[Array, ""]:
    """``log mean exp(terms)``; ``-inf`` (zero gradient) when every term is ``-inf``."""
    some = jnp.any(terms > -jnp.inf)
    return jnp.where(some, logsumexp(jnp.where(some, terms, 0.0)) - math.log(terms.shape[0]), -jnp.inf)


def _log_visibility_probability(sensor: SensorModel, local: Float[Array, "6"], local_cov: Float[Array, "6 6"]):
    """``log P(object in view)`` under the linearized Gaussian predictive of its range/bearing;
    ``local = [x, object]`` and its covariance (range and bearing depend on nothing else)."""
    jac = jnp.concatenate(range_bearing_jacobians(local[:3], local[3:]), axis=1)  # (2, 6), closed form (Eq. 10)
    return log_visibility_probability(sensor, range_bearing(local[:3], local[3:]), jnp.diagonal(jac @ local_cov @ jac.T))


class LinearTables(NamedTuple):
    """What the linearized weights of every child of one parent are made of (thesis Eq. 4.14-4.15).

    Rows are (object ``objs[i]``, class ``c``) pairs: ``r_bar[j, i, c]`` is the whitened residual of
    detection ``j`` at the propagated mean, ``gram`` the covariance ``J Σ Jᵀ`` of every row's
    whitened prediction (the Jacobian does not depend on the measured values), ``log_vis[i]`` the
    in-view probability of object ``objs[i]``.
    """

    r_bar: Float[Array, "Dmax O M R"]
    log_norm: Float[Array, "Dmax O M"]
    gram: Float[Array, "OMR OMR"]
    log_vis: Float[Array, " O"]


def _gram(jac_x: Float[Array, "Q 3"], jac_o: Float[Array, "O S 3"], sub: Float[Array, "E E"]) -> Float[Array, "Q Q"]:
    """``J Σ Jᵀ`` of rows ``Q = O · S`` (object ``o``'s ``S`` rows contiguous) whose Jacobian is
    ``[J_x | 0 .. J_o .. 0]`` over ``[x, objs]`` (``E = 3 + 3O``): a row depends on the pose and
    its own object only. By blocks, ``(JΣ)_q = J_x,q Σ_x: + J_o,q Σ_o(q):`` and
    ``(JΣJᵀ)_qq' = (JΣ)_q,x J_x,q'ᵀ + (JΣ)_q,o(q') J_o,q'ᵀ``: ``O(Q E)`` products instead of the
    dense ``Q E²`` (a gated MRCLAM step: 63 candidate rows of 2, 192 coordinates, 7.7 Mflop per
    parent), the same sums without the zero terms."""
    q, n_obj = jac_x.shape[0], jac_o.shape[0]
    e = sub.shape[0]
    js = jac_x @ sub[:3] + jnp.einsum("osc,oce->ose", jac_o, sub[3:].reshape(n_obj, 3, e)).reshape(q, e)
    on_objects = jnp.einsum("qoc,osc->qos", js[:, 3:].reshape(q, n_obj, 3), jac_o).reshape(q, q)
    return js[:, :3] @ jac_x.T + on_objects


def linear_tables(
    sensor: SensorModel, mean: Float[Array, " D"], cov: Float[Array, "D D"], detections: Detections,
    objs: Int[Array, " O"],
) -> LinearTables:
    """:class:`LinearTables` of one parent for the objects ``objs`` (all, or each slot's candidates)."""
    m = sensor.classifier.num_classes
    n_obj = objs.shape[0]
    x, objects = _split(mean)
    # Every class's rows at once (detection_residuals), then one row set per class: [r_geo, r_sem[c]].
    per_object = jax.vmap(detection_residuals, (None, None, 0, None, None))
    r_geo, r_sem, log_norm = jax.vmap(per_object, (None, None, None, 0, 0))(
        sensor, x, objects[objs], detections.geo, detections.scores)  # (Dmax, O, 2), (Dmax, O, M, M), (Dmax, O, M)
    r_bar = jnp.concatenate([jnp.broadcast_to(r_geo[:, :, None, :], r_geo.shape[:2] + (m, 2)), r_sem], axis=-1)
    # A row depends on the pose and its own object only: its Jacobian is two 3-column blocks, and
    # J Σ Jᵀ needs Σ only over [x, objs] (gathered, (3 + 3 O)²), not the whole (3 + 3 N)² state.
    # The whitened Jacobian does not depend on the measured values: take it from slot 0.
    residuals = lambda x, o: detection_residuals(sensor, x, o, detections.geo[0], detections.scores[0])[:2]  # noqa: E731
    (geo_x, geo_o), (sem_x, sem_o) = jax.vmap(jax.jacfwd(residuals, argnums=(0, 1)), (None, 0))(x, objects[objs])
    per_class = lambda geo, sem: jnp.concatenate(  # noqa: E731  # (O, 2, 3), (O, M, M, 3) -> (O, M, R, 3)
        [jnp.broadcast_to(geo[:, None], (n_obj, m) + geo.shape[1:]), sem], axis=2)
    jac_x, jac_o = per_class(geo_x, sem_x), per_class(geo_o, sem_o)
    rdim = jac_x.shape[2]
    obj_idx = 3 + 3 * objs[:, None] + jnp.arange(3)[None, :]  # (O, 3): each object's state coordinates
    idx = jnp.concatenate([jnp.arange(3), obj_idx.reshape(-1)])
    sub = cov[idx[:, None], idx[None, :]]  # Σ over [x, objs]
    gram = _gram(jac_x.reshape(-1, 3), jac_o.reshape(n_obj, m * rdim, 3), sub)  # (O M R, O M R)
    local = jax.vmap(lambda o: jnp.concatenate([x, o]))(objects[objs])  # (O, 6)
    blocks = jnp.concatenate([jnp.broadcast_to(jnp.arange(3), (n_obj, 3)), obj_idx], axis=1)
    local_cov = cov[blocks[:, :, None], blocks[:, None, :]]  # (O, 6, 6): Σ over [x, object]
    log_vis = jax.vmap(_log_visibility_probability, (None, 0, 0))(sensor, local, local_cov)
    return LinearTables(r_bar, log_norm, gram, log_vis)


def linear_child(
    t: LinearTables, rows: Int[Array, " Dmax"], slot_class: Int[Array, " Dmax"], occupied: Bool[Array, " Dmax"]
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """``log N(r̄; 0, J Σ Jᵀ + I) + log normalizers (+ log P(in view))`` of one child whose slot ``j``
    names row ``rows[j]`` of ``t`` with class ``slot_class[j]`` (where ``occupied``): with and without
    the observation model."""
    m, rdim = t.r_bar.shape[2], t.r_bar.shape[3]
    obj = jnp.maximum(rows, 0)
    base = (obj * m + slot_class) * rdim
    idx = (base[:, None] + jnp.arange(rdim)[None, :]).reshape(-1)
    occ_rows = jnp.repeat(occupied, rdim)
    s = jnp.where(occ_rows[:, None] & occ_rows[None, :], t.gram[idx][:, idx], 0.0)
    s = s + jnp.eye(s.shape[0])
    slots = jnp.arange(rows.shape[0])
    r = jnp.where(occupied[:, None], t.r_bar[slots, obj, slot_class], 0.0).reshape(-1)
    mahalanobis, log_det = gaussian_terms(s, r)
    log_lik = -0.5 * mahalanobis - 0.5 * log_det
    log_lik += jnp.sum(jnp.where(occupied, t.log_norm[slots, obj, slot_class], 0.0))
    return log_lik + jnp.sum(jnp.where(occupied, t.log_vis[obj], 0.0)), log_lik


class PartialChild(NamedTuple):
    """:func:`linear_child`'s density of a child built one slot at a time (inside a beam search): the
    chain rule ``N(r; 0, S) = Π_j N(r_j | r_<j)`` over the slots named so far, in innovation space.
    ``chol`` is the lower Cholesky factor of ``S`` over those slots' rows (identity in the rows of
    the other slots: their rows of ``S`` are too, and stay so until a slot is named) and ``white``
    is ``chol⁻¹ r`` (0 in the other rows). Extending by slot ``j`` costs one ``R×R`` density and a
    triangular solve of ``R`` columns instead of a ``Dmax R`` joint Cholesky per extension. The
    same joint innovation density (thesis Eq. 4.14-4.15) to rounding; tested against the
    exhaustive enumeration's joint form (``tests/test_step.py``)."""

    chol: Float[Array, "DR DR"]
    white: Float[Array, " DR"]
    log_lik: Float[Array, ""]  # the density so far with the slots' log normalizers (linear_child's second)
    log_vis: Float[Array, ""]  # Σ log P(in view) of the named objects (its first minus its second)


def empty_child(slots: int, rdim: int, dtype=float) -> PartialChild:
    """A child that names nothing yet (``slots`` detection slots of ``rdim`` residual rows)."""
    zero = jnp.zeros((), dtype)
    return PartialChild(jnp.eye(slots * rdim, dtype=dtype), jnp.zeros(slots * rdim, dtype), zero, zero)


def _slot_given_earlier(tables: LinearTables, p: Int[Array, ""], child: PartialChild, rows: Int[Array, " Dmax"],
                        slot_class: Int[Array, " Dmax"], named: Bool[Array, " Dmax"], j: Int[Array, ""]):
    """Slot ``j``'s rows given the earlier named slots of ``child`` (parent ``p``'s tables): ``c =
    L⁻¹ S_<j,j``, the conditional covariance ``S_jj − cᵀc`` and residual ``r_j − cᵀ(L⁻¹ r_<j)``."""
    m, rdim = tables.r_bar.shape[3], tables.r_bar.shape[4]
    obj = jnp.maximum(rows, 0)
    idx = ((obj * m + slot_class) * rdim)[:, None] + jnp.arange(rdim)[None, :]  # (Dmax, R): rows of the gram
    own = idx[j]
    earlier = jnp.repeat(named & (jnp.arange(rows.shape[0]) < j), rdim)
    cross = jnp.where(earlier[:, None], tables.gram[p, idx.reshape(-1)[:, None], own[None, :]], 0.0)  # (Dmax R, R)
    c = jax.scipy.linalg.solve_triangular(child.chol, cross, lower=True)
    s = tables.gram[p, own[:, None], own[None, :]] + jnp.eye(rdim, dtype=c.dtype) - c.T @ c
    r = tables.r_bar[p, j, obj[j], slot_class[j]] - c.T @ child.white
    return c, s, r, obj[j]


def extend_child(tables: LinearTables, p: Int[Array, ""], child: PartialChild, rows: Int[Array, " Dmax"],
                 slot_class: Int[Array, " Dmax"], named: Bool[Array, " Dmax"], j: Int[Array, ""]) -> PartialChild:
    """``child`` extended by slot ``j``: naming row ``rows[j]`` of parent ``p``'s ``tables`` (leading
    parent axis) with class ``slot_class[j]`` if ``named[j]`` (else unchanged), slots before ``j``
    as in ``child``. Its factor gains the block row ``[cᵀ, chol(S_jj − cᵀc)]`` in slot ``j``'s rows,
    its density the slot's conditional term ``log N(r_j | r_<j)`` and log normalizer."""
    c, s, r, o = _slot_given_earlier(tables, p, child, rows, slot_class, named, j)
    rdim = s.shape[0]
    low, w, log_det = cholesky_whiten(s, r)
    block = jax.lax.dynamic_update_slice(c.T, low, (0, j * rdim))  # c's rows of slot j and later are 0
    chol = jax.lax.dynamic_update_slice(child.chol, block, (j * rdim, 0))
    white = jax.lax.dynamic_update_slice(child.white, w, (j * rdim,))
    term = -0.5 * jnp.sum(w**2) - 0.5 * log_det + tables.log_norm[p, j, o, slot_class[j]]
    on = named[j]
    return PartialChild(jnp.where(on, chol, child.chol), jnp.where(on, white, child.white),
                        child.log_lik + jnp.where(on, term, 0.0),
                        child.log_vis + jnp.where(on, tables.log_vis[p, o], 0.0))


def linearized_log_likelihood(
    sensor: SensorModel,
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    detections: Detections,
    table: HypothesisTable,
    kids: Children,
    axis_name: str | None = None,
) -> tuple[Float[Array, "A Mc"], Float[Array, "A Mc"], Float[Array, "A Mc"]]:
    """Deterministic ``log ψ``: ``log N(r̄; 0, J Σ Jᵀ + I) + log normalizers + log P(in view)``.

    ``r̄`` and ``J`` are the whitened residuals of the child's detections at the propagated mean
    and their Jacobian (thesis Eq. 4.14-4.15 in whitened form, all detections of the child jointly
    so the shared robot pose correlates them).

    The residuals, Jacobians and their Gram matrix are formed once per (object, class); gated
    (``kids.candidates``), only for each slot's candidates, so the cost does not grow with the map.
    Children are evaluated only in the table rows that match the detection mask (``axis_name``: as
    in :func:`~hybridslam.batching.map_live`, the name of an enclosing vmap over tracks).
    """
    objs = jnp.arange(mean.shape[0] // 3 - 1)
    assign = kids.measured  # the row of `objs` that each slot names
    if kids.candidates is not None:
        dmax, g = kids.candidates.shape
        objs = kids.candidates.reshape(-1)
        assign = jnp.where(assign >= 0, jnp.arange(dmax)[None, :] * g + jnp.asarray(table.assign), -1)
    tables = linear_tables(sensor, mean, cov, detections, objs)
    occupied = assign >= 0

    def one_child(a, slot_class):
        return linear_child(tables, assign[a], slot_class, occupied[a])

    # Only the table rows whose occupied slots are this step's detections can be valid children
    # (:func:`~hybridslam.hypotheses.children`); they are contiguous in the table, and this test is
    # the same for every parent, so chunks of other rows are skipped (rows hold zeros, never read).
    live = jnp.all((jnp.asarray(table.assign) != EMPTY) == detections.mask[None, :], axis=-1)
    log_psi, log_psi_free = map_live(jax.vmap(one_child, (None, 0)), live, jnp.arange(assign.shape[0]),
                                     kids.slot_class, chunk=ROW_CHUNK, axis_name=axis_name)
    return log_psi, log_psi_free, jnp.ones_like(log_psi)  # deterministic: no sampling error


def _child_marginal(mean, cov, assign):
    """The Gaussian of Eq. 17 over ``(x_k, x^o of each slot)``; an empty slot is an independent
    N(0, I) dummy block, which cancels exactly between the target and the proposal."""
    occupied = assign >= 0
    idx = jnp.concatenate([jnp.arange(3), (3 + 3 * jnp.maximum(assign, 0)[:, None] + jnp.arange(3)[None, :]).reshape(-1)])
    keep = jnp.concatenate([jnp.ones(3, bool), jnp.repeat(occupied, 3)])
    both = keep[:, None] & keep[None, :]
    marginal_cov = jnp.where(both, cov[idx][:, idx], jnp.eye(idx.shape[0], dtype=cov.dtype))
    return jnp.where(keep, mean[idx], 0.0), marginal_cov, keep


def _child_evidence(sensor, detections, eps, max_steps, mean, cov, assign, slot_class):
    m_mean, m_cov, keep = _child_marginal(mean, cov, assign)
    angle = keep & (jnp.arange(keep.shape[0]) % 3 == 2)

    def difference(a, b):
        return jnp.where(angle, se2.wrap(a - b), a - b)

    def measurement(y):
        x, objs = y[:3], y[3:].reshape(-1, 3)  # objs[j]: the object of slot j (Eq. 17 layout)
        r, log_norm = slot_residuals(sensor, x, objs, detections.geo, detections.scores, assign, slot_class)
        log_view = jax.vmap(log_visibility, (None, None, 0))(sensor, x, objs)
        return r, log_norm, jnp.sum(jnp.where(assign >= 0, log_view, 0.0))

    ev = laplace_is(measurement, m_mean, m_cov, eps, max_steps, difference)
    return ev.log_evidence, ev.log_evidence_free, ev.ess, ev.solver_result == optx.RESULTS.successful


def laplace_is_log_likelihood(
    sensor: SensorModel,
    mean: Float[Array, "K D"],
    cov: Float[Array, "K D D"],
    detections: Detections,
    eps: Float[Array, "S d"],
    table: HypothesisTable,
    kids: Children,
    screen: Float[Array, "K A Mc"],
    num_candidates: int,
    max_steps: int,
    axis_name: str | None = None,
) -> tuple[Float[Array, "K A Mc"], Float[Array, "K A Mc"], Float[Array, "K A Mc"], Bool[Array, "K A Mc"]]:
    """``log ψ`` of Eq. 16 by importance sampling from each child's Laplace approximation.

    See :mod:`hybridslam.laplace`. Solving a Gauss-Newton problem for every child of every parent
    would cost ``K·A·Mc`` solves, so the children are first ranked by a cheap screening weight
    (``screen``: the parent weight times the linearized evidence, ``-inf`` for invalid children)
    and only the ``num_candidates`` best get the Laplace-IS estimate; the rest get ``-inf``. Each
    candidate solves its problem over ``(x_k, X^o_β)`` (``3 + 3·Dmax`` dimensions, Eq. 17), in
    chunks that skip empty candidates (:func:`~hybridslam.batching.map_live`). Also returns
    whether each child's mode search converged (a failed one leaves the estimate unbiased but less
    efficient; True for children that were not candidates). ``axis_name``: see
    :func:`~hybridslam.batching.map_live`.
    """
    shape = screen.shape
    parent, a, m = jnp.unravel_index(jnp.arange(screen.size), shape)
    out = laplace_is_children(sensor, mean, cov, detections, eps, parent, kids.measured[parent, a],
                              kids.slot_class[parent, a, m], screen.reshape(-1), num_candidates, max_steps, axis_name)
    return tuple(v.reshape(shape) for v in out)  # type: ignore[return-value]  # four arrays


def laplace_is_children(
    sensor: SensorModel,
    mean: Float[Array, "K D"],
    cov: Float[Array, "K D D"],
    detections: Detections,
    eps: Float[Array, "S d"],
    parent: Int[Array, " C"],
    measured: Int[Array, "C Dmax"],
    slot_class: Int[Array, "C Dmax"],
    screen: Float[Array, " C"],
    num_candidates: int,
    max_steps: int,
    axis_name: str | None = None,
) -> tuple[Float[Array, " C"], Float[Array, " C"], Float[Array, " C"], Bool[Array, " C"]]:
    """:func:`laplace_is_log_likelihood` for a flat list of ``C`` children: child ``i`` of parent
    ``parent[i]`` measures the objects ``measured[i]`` (``-1``: no factor) with classes ``slot_class[i]``."""
    top, flat = jax.lax.top_k(screen, min(num_candidates, screen.size))
    one = partial(_child_evidence, sensor, detections, eps, max_steps)
    live = top > -jnp.inf
    p = parent[flat]
    # Four candidates per chunk. One per chunk (unbatched) traces and compiles 0.3-0.5 s faster, but a
    # step with many live candidates then runs their mode searches one after another: every slot of
    # a capacity-16 belief alive, 10 ms -> 30-34 ms per step (scripts/bench_step.py, 2026-11-26).
    *packed, converged = map_live(one, live, mean[p], cov[p], measured[flat], slot_class[flat], chunk=4,
                                  axis_name=axis_name)
    fill = (-jnp.inf, -jnp.inf, 0.0, True)
    return tuple(  # type: ignore[return-value]  # four arrays
        jnp.full(screen.size, f, v.dtype).at[flat].set(jnp.where(live, v, f))
        for v, f in zip((*packed, converged), fill)
    )


# Quadrature nodes of the viewpoint integral of a new object's semantic likelihood.
_VIEWPOINT_NODES = 64


def new_object_log_likelihood(
    sensor: SensorModel, robot_mean: Float[Array, "3"], robot_cov: Float[Array, "3 3"], detections: Detections,
    new: NewObjects,
) -> Float[Array, "Dmax M"]:
    """``log P(z_j | new object of class c)`` for every detection and class (unknown maps).

    The null / new-landmark hypothesis (thesis Sec. 3.2.1): the geometric part is the scenario's
    ``new_object_log_density``; the semantic part is Eq. 2 integrated over the unknown viewpoint,
    ``∫ P(z^sem | c, v) p(v) dv``. The viewpoint of a new object (SCENARIO_FORMAT.md) is
    ``v = θ_x + b + π − θ_o``: with the new object's orientation ``θ_o ~ N(0, orientation_var)``
    independent of the robot heading ``θ_x`` and of the bearing noise, ``v`` is Gaussian (wrapped)
    around ``θ̄_x + b + π`` with variance ``orientation_var + P_θθ + Σ_v[1, 1]``. The integral is
    a midpoint rule on ±6 standard deviations (the whole circle when that is wider, where the
    periodic midpoint rule converges fastest) with wrapped-normal weights, normalized.

    The class of the new object is a fresh realization, like a first association (Sec. IV-D): the
    step splits the child per class with prior ``P(c)``, so summed over classes the semantic term
    is the marginal over the class prior.
    """
    std = jnp.sqrt(new.orientation_var + robot_cov[2, 2] + sensor.geometric_cov[1, 1])
    half = jnp.minimum(jnp.pi, 6.0 * std)
    t = half * ((2.0 * jnp.arange(_VIEWPOINT_NODES) + 1.0) / _VIEWPOINT_NODES - 1.0)
    wraps = 2.0 * jnp.pi * jnp.arange(-4, 5)
    log_w = logsumexp(-0.5 * ((t[:, None] + wraps[None, :]) / std) ** 2, axis=1)
    log_w = log_w - logsumexp(log_w)
    v = robot_mean[2] + detections.geo[:, 1, None] + jnp.pi + t[None, :]  # (Dmax, Q)
    views = jnp.stack([jnp.cos(v), jnp.sin(v)], axis=-1)

    def semantic(scores, view):
        r, log_norm = sensor.classifier.residuals(scores, view)
        return log_norm - 0.5 * jnp.sum(r**2, axis=-1)

    ll = jax.vmap(jax.vmap(semantic, (None, 0)), (0, 0))(detections.scores, views)  # (Dmax, Q, M)
    return new.log_density + logsumexp(ll + log_w[None, :, None], axis=1)


def class_marginal(per_class: Float[Array, "*K Dmax M"]) -> Float[Array, "*K Dmax"]:
    """``log Σ_c P(c) P(z_j | c)`` under a uniform class prior, ``logsumexp_c per_class − log M``,
    from :func:`new_object_log_likelihood`'s per-class terms. Two uses:

    * an *unmapped* object (the new-landmark hypothesis, thesis Sec. 3.2.1, when the component has
      no free object slot to store it in): a new object's class prior is uniform
      (:func:`hybridslam.models.model.model_from_scenario`), so this is the sum over classes of the
      children that would realize the class in a free slot (Sec. IV-D). The hypothesis keeps its
      weight; only the object is not stored, so its later detections are not associated with it
      (each is again a new or unmapped object);
    * clutter: a detection of no known class, scored with the clutter density.
    """
    return logsumexp(per_class, axis=-1) - math.log(per_class.shape[-1])
