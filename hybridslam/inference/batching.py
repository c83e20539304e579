"""Batching over a leading axis that skips the work of dead slots.

A belief has a fixed capacity of component slots and a step has a fixed grid of child
hypotheses, but only some of either are alive. :func:`map_live` runs a per-slot function over
chunks of slots and skips chunks with no live slot, so work scales with what is alive while all
shapes stay static. :func:`map_distinct` also computes once for slots known to give the same
output (components whose factor graphs are equal).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Int


LARGE_GRAPH = 64  # poses + object slots of a graph whose long pose chain is smoothed in chunks
CHAIN_CHUNK = 4  # components smoothed together where the pose chain is long


def smoothing_chunk(num_poses: int, num_objects: int) -> int:
    """Components per :func:`map_live` chunk when each is smoothed (its trajectory and map re-solved):
    one, so that a chunk's Levenberg-Marquardt loop never waits for a slower member and a size-1
    chunk runs unbatched, except where the pose chain is long (MRCLAM's 201 poses beside 15 objects:
    the scan over the chain is latency-bound and batches better by :data:`CHAIN_CHUNK`). Measured on
    the hallway's dense algebra (61 poses, 70 object slots): one by one 10-15% faster than four."""
    return CHAIN_CHUNK if num_poses > num_objects and num_poses + num_objects > LARGE_GRAPH else 1


def map_live(fn: Callable, live: Bool[Array, " K"], *args, chunk: int = 4, axis_name: str | None = None):
    """``jax.vmap(fn)(*args)`` over the leading ``K`` axis, skipping chunks with no live slot.

    After every step the slots are sorted by weight, so the live components form a prefix: work
    done this way scales with the live components rather than the capacity. Chunks run in a
    ``lax.map``; a chunk without a live slot returns zeros (its values are masked by the caller).

    Under an outer ``jax.vmap`` (many tracks) a ``lax.cond`` on a per-track predicate becomes a
    select and nothing would be skipped. Pass that vmap's ``axis_name``: the predicate is then
    "live in any track" (a ``psum`` over the axis, unbatched), so a chunk dead in every track is
    still skipped. Outside a vmap with that axis name, ``axis_name`` must be ``None``.
    """
    k = live.shape[0]
    size, pad, live_chunks, arg_chunks = _chunks(live, args, chunk)
    # Jitted so that the trace eval_shape makes is cached and reused by the call in the cond below:
    # tracing fn once instead of twice halves the tracing time of a step (seconds for the hybrid belief).
    # Chunks of one slot call fn unbatched: a size-1 vmap batches every while loop inside fn (the
    # smoother's Levenberg-Marquardt iterates), which cost the paper setup's `run` ~2 s of its
    # 14-16 s compile (tracing and XLA) and bought nothing.
    if size == 1:
        batched = jax.jit(lambda *a: jax.tree.map(lambda y: y[None], fn(*jax.tree.map(lambda x: x[0], a))))
    else:
        batched = jax.jit(jax.vmap(fn))
    out_shape = jax.eval_shape(batched, *jax.tree.map(lambda x: x[0], arg_chunks))
    zeros = lambda: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), out_shape)  # noqa: E731

    def one_chunk(xs):
        live_c, args_c = xs
        return jax.lax.cond(_any_live(live_c, axis_name), lambda: batched(*args_c), zeros)

    out = jax.lax.map(one_chunk, (live_chunks, arg_chunks))
    return jax.tree.map(lambda x: x.reshape((k + pad,) + x.shape[2:])[:k], out)


def fold_live(fn: Callable, init: Any, live: Bool[Array, " K"], *args, chunk: int = 4,
              axis_name: str | None = None) -> Any:
    """``acc = fn(acc, first, *chunk_args)`` over chunks of ``chunk`` slots of the leading ``K`` axis
    (``first``: the chunk's first slot index), skipping chunks with no live slot, as :func:`map_live`
    does; ``fn`` sees its chunk batched (``chunk`` leading; the last chunk padded with copies of slot
    0, at indices ``K`` and above) and returns an accumulator of ``init``'s structure. For work
    whose per-slot outputs are large but consumed at once (e.g. per-sample tables reduced to a few
    numbers): nothing per slot is stacked, and dead chunks write nothing.
    ``axis_name``: as in :func:`map_live`."""
    size, pad, live_chunks, arg_chunks = _chunks(live, args, chunk)

    def one_chunk(acc, xs):
        first, live_c, args_c = xs
        return jax.lax.cond(_any_live(live_c, axis_name), lambda: fn(acc, first, *args_c), lambda: acc), None

    firsts = jnp.arange(0, live.shape[0] + pad, size)
    acc, _ = jax.lax.scan(one_chunk, init, (firsts, live_chunks, arg_chunks))
    return acc


def _chunks(live: Bool[Array, " K"], args: tuple, chunk: int):
    """``(size, pad, live, args)``: the chunk size, the padding of the last chunk (copies of slot 0,
    dead), and ``live`` and every leaf of ``args`` reshaped to ``(chunks, size, ...)``."""
    k = live.shape[0]
    size = min(chunk, k)
    pad = -k % size
    live = jnp.concatenate([live, jnp.zeros(pad, bool)])
    args = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)]), args)
    split = lambda x: x.reshape((x.shape[0] // size, size) + x.shape[1:])  # noqa: E731
    return size, pad, split(live), jax.tree.map(split, args)


def _any_live(live: Bool[Array, " size"], axis_name: str | None) -> Bool[Array, ""]:
    """Whether a chunk has a live slot; under an outer vmap named ``axis_name``, in any track (a
    ``psum``, so the predicate is unbatched and a ``lax.cond`` on it still skips work)."""
    any_live = jnp.any(live)
    if axis_name is not None:
        any_live = jax.lax.psum(any_live.astype(jnp.int32), axis_name) > 0
    return any_live


def map_distinct(
    fn: Callable, live: Bool[Array, " K"], same: Bool[Array, "K K"], *args, chunk: int = 4,
    axis_name: str | None = None,
) -> tuple[Any, Int[Array, ""]]:
    """:func:`map_live`, computing ``fn`` once per class of live slots that ``same`` calls equal.

    ``same[i, j]`` says slots ``i`` and ``j`` give the same output (an equivalence on the live
    slots, e.g. equal factor graphs; ``same[i, i]`` must hold). Each live slot gets the output of
    the first live slot of its class; those representatives are moved to the front first, so the
    chunks of copies are skipped. Dead slots get an arbitrary slot's output (mask them). Returns
    the outputs and the number of distinct live slots (calls of ``fn`` that count).
    """
    k = live.shape[0]
    index = jnp.arange(k)
    representative = jnp.argmax(same & live[None, :], axis=1)  # the first live slot equal to slot i
    distinct = live & (representative == index)
    order = jnp.argsort(~distinct, stable=True)  # representatives first, in slot order
    position = jnp.zeros(k, index.dtype).at[order].set(index)
    out = map_live(fn, distinct[order], *jax.tree.map(lambda a: a[order], args), chunk=chunk, axis_name=axis_name)
    return jax.tree.map(lambda a: a[position[representative]], out), jnp.sum(distinct, dtype=jnp.int32)
