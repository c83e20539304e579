"""Association hypotheses built one detection at a time, with a fixed budget: a beam search.

Enumerating every joint assignment of a step's ``D`` detections is exponential in ``D``
(``(G+1)^D`` rows for ``G`` gated candidates per detection; 65,536 at 8 detections, 16.7 million
at 12). A beam search builds the assignments slot by slot instead: each of the ``W`` partial
assignments kept so far is extended by every option of the next slot, every extension is scored
as a whole (the caller's joint score of the partial assignment: measurements are conditionally
independent given the state, so a partial assignment's likelihood is that of the detections it
names), and the ``W`` best survive. The work is ``D · W · O`` scores (``O`` options per slot),
linear in the detections.

It is exact whenever no more than ``W`` partial assignments are valid at any slot: then the beam
holds every one of them and the final set equals the exhaustive enumeration (tested against it).
Otherwise the lowest-scoring partial assignments are dropped; each drop whose score lies within
``keep_nats`` of the best is counted (:attr:`Beam.dropped`), so a budget that loses a hypothesis
that could matter says so.

Scores are ranked lexicographically by a *rank* (an integer the caller may use to order classes
of hypotheses first, e.g. fewer skipped detections) and then by the log score.

A score that is a sum of per-slot terms conditioned on the earlier slots (a joint Gaussian density
in its sequential form, ``N(r; 0, S) = Π_j N(r_j | r_<j)``) need not be recomputed from scratch for
every extension: pass a ``carry`` (one row per partial assignment, e.g. a conditioned covariance)
and an ``advance`` that updates the row of every kept extension; the score then gets the row and
the score of the assignment it extends, and adds one slot's term. Without ``advance`` the score
returns each extension's row itself (cheap rows: no second pass over the kept extensions, and the
caller's code traced once). The rows of the final assignments come back with them
(:attr:`Beam.rows`).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PyTree

# Large enough that one unit of rank outweighs any log-likelihood difference, small enough that the
# sort key keeps the log score's precision to ~1e-9 nats.
_RANK_NATS = 1e6


class Beam(eqx.Module):
    """The ``W`` best complete assignments (invalid rows have ``score = -inf``)."""

    options: Int[Array, "W S"]  # the option of every slot
    score: Float[Array, " W"]  # the caller's joint log score of the whole assignment
    rank: Int[Array, " W"]  # the caller's rank (lower first)
    dropped: Int[Array, ""]  # valid partial assignments dropped within keep_nats of the best
    rows: PyTree | None = None  # with a ``carry``: each complete assignment's row

    @property
    def valid(self) -> Bool[Array, " W"]:
        return self.score > -jnp.inf


def beam_search(
    score: Callable[..., tuple[Float[Array, ""], Int[Array, ""]]],  # (options, j) or (options, j, row, parent)
    num_slots: int,
    num_options: int,
    width: int,
    fill: int,
    keep_nats: float | Float[Array, ""] = 30.0,
    start: tuple[Int[Array, "W S"], Float[Array, " W"]] | None = None,
    first_slot: int = 0,
    carry: PyTree | None = None,
    advance: Callable[[PyTree, Int[Array, " S"], Int[Array, ""]], PyTree] | None = None,
    stop: Int[Array, ""] | int | None = None,
) -> Beam:
    """Beam search over ``num_slots`` slots of ``num_options`` options each.

    ``score(options, j)`` returns the joint log score (``-inf``: invalid) and the rank of the
    partial assignment ``options`` whose slots ``0..j`` are set (the others hold ``fill``). The
    search starts from the single assignment with every slot at ``fill``, or from ``start`` (``W``
    partial assignments and their scores, ``-inf`` for none), and extends slots ``first_slot..``.

    With ``carry`` (a pytree of arrays with a leading ``W`` axis: the caller's state of each partial
    assignment) the score is called as ``score(options, j, row, parent)`` with the row and the joint
    score ``parent`` of the assignment being extended, and after each slot ``advance(row, options,
    j)`` returns the row of every kept extension (``options``: its assignment). With ``carry`` and
    no ``advance``, the score returns ``(score, rank, row)``: the extension's own row.

    ``stop`` (traced or not): the slots from ``stop`` on are padding, whose only valid option is
    ``fill`` at an unchanged score. They are skipped by a ``lax.cond``: on a CPU a step pays for its
    own detections, not for the padding to the run's busiest step (under ``vmap`` both branches run,
    as without it). At least slot ``first_slot`` is extended, so the result is the one without
    ``stop``: the beam's order included.
    """
    if advance is not None and carry is None:
        raise ValueError("beam_search: advance needs a carry")
    if start is None:
        start_options = jnp.full((width, num_slots), fill, dtype=jnp.int32)
        start_score = jnp.full((width,), -jnp.inf).at[0].set(0.0)
    else:
        start_options, start_score = start
    start_rank = jnp.zeros((width,), jnp.int32)
    choices = jnp.arange(num_options, dtype=jnp.int32)

    def extend(state, j):
        options, live_score, _, dropped, rows = state
        grown = jnp.broadcast_to(options[:, None, :], (width, num_options, num_slots))
        grown = grown.at[:, :, j].set(jnp.broadcast_to(choices[None, :], (width, num_options)))
        flat = grown.reshape(width * num_options, num_slots)
        grown_rows = None
        if rows is None:
            s, r = jax.vmap(score, (0, None))(flat, j)
        else:
            out = jax.vmap(jax.vmap(score, (0, None, None, None)), (0, None, 0, 0))(grown, j, rows, live_score)
            s, r = out[0].reshape(-1), out[1].reshape(-1)
            if advance is None:
                grown_rows = jax.tree.map(lambda a: a.reshape((width * num_options,) + a.shape[2:]), out[2])
        parent_live = jnp.repeat(live_score > -jnp.inf, num_options)
        s = jnp.where(parent_live, s, -jnp.inf)
        key = jnp.where(s > -jnp.inf, s - _RANK_NATS * r.astype(s.dtype), -jnp.inf)
        top, index = jax.lax.top_k(key, width)
        kept = jnp.zeros(key.shape, bool).at[index].set(top > -jnp.inf)
        best = jnp.max(jnp.where(s > -jnp.inf, key, -jnp.inf))
        lost = (s > -jnp.inf) & ~kept & (key >= best - keep_nats)
        new_score = jnp.where(top > -jnp.inf, s[index], -jnp.inf)
        if grown_rows is not None:
            rows = jax.tree.map(lambda a: a[index], grown_rows)
        elif rows is not None:
            parent = jax.tree.map(lambda a: a[index // num_options], rows)
            rows = jax.vmap(advance, (0, 0, None))(parent, flat[index], j)
        return (flat[index], new_score, r[index].astype(jnp.int32), dropped + jnp.sum(lost, dtype=jnp.int32), rows), None

    step = extend
    if stop is not None:
        last = jnp.maximum(stop, first_slot + 1)

        def step(state, j):  # padding slots keep the state: the one option they allow changes nothing
            return jax.lax.cond(j < last, extend, lambda st, _: (st, None), state, j)

    init = (start_options, start_score, start_rank, jnp.zeros((), jnp.int32), carry)
    (options, final, rank, dropped, rows), _ = jax.lax.scan(step, init, jnp.arange(first_slot, num_slots))
    return Beam(options, final, rank, dropped, rows)
