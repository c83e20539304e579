"""Static-size buckets: work on the live prefix of a padded axis, at a few compiled sizes.

A run's smoother is compiled for the whole trajectory (``P = T + 1`` pose slots), but after ``k``
steps only ``x_0..x_k`` are live; the padded poses carry no factor (identity rows of ``H``, zero
gradient) and add nothing but work to every elimination: ``O(P²N)`` per solve on the hallway. A
shape cannot depend on ``k`` inside ``jax.jit``, so :func:`by_bucket` compiles the work for a few
sizes (:func:`bucket_sizes`: a quarter, half, three quarters and all of the axis) and picks, with
``lax.switch``, the smallest that holds the live prefix. The result is exact whatever the bucket:
the slots left out are uncoupled and stay where they are.

Under ``jax.vmap`` a batched ``lax.switch`` index turns into a select that runs every branch, so the
index goes through :func:`batch_max`: the largest live size of the batch, unbatched (each member
then works at the size the largest one needs, still exact).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap
from jaxtyping import Array, Int

def buckets_from_environment() -> int:
    """``$HYBRIDSLAM_BUCKETS`` (default 4); a ``ValueError`` naming it for anything but a positive integer."""
    text = os.environ.get("HYBRIDSLAM_BUCKETS", "4")
    if not text.strip().isdigit() or int(text) < 1:
        raise ValueError(f"HYBRIDSLAM_BUCKETS: expected a positive integer (1: no buckets), got {text!r}")
    return int(text)


# Sizes compiled per bucketed axis; each one more compiles the solves again (about 1-1.5 s on the
# MRCLAM and hallway programs). HYBRIDSLAM_BUCKETS=1 compiles them once, for short runs from a cold cache.
# None: read $HYBRIDSLAM_BUCKETS when a graph is bucketed (at trace time), so that a bad value is an
# error of the run (one line from the CLI), not of importing the package.
BUCKETS: int | None = None
MIN_BUCKETED = 32  # an axis shorter than this is not bucketed (the paper setup's 11 poses: one compile)


@custom_vmap
def batch_max(x: Int[Array, ""]) -> Int[Array, ""]:
    """``x``; under ``jax.vmap``, the maximum over the batch, unbatched (nested vmaps: over all)."""
    return x


@batch_max.def_vmap
def _batch_max_rule(axis_size: int, in_batched: list[bool], x: Int[Array, " B"]) -> tuple[Int[Array, ""], bool]:
    del axis_size
    # Through batch_max again: an enclosing vmap (nested vmaps) sees the maximum still batched over its axis.
    return batch_max(jnp.max(x, axis=0) if in_batched[0] else x), False


def bucket_sizes(*lengths: int, count: int | None = None, minimum: int | None = None) -> tuple[tuple[int, ...], ...]:
    """The sizes a work over padded axes of these ``lengths`` is compiled for: ``count`` buckets,
    bucket ``i`` holding ``ceil(n i / count)`` of each axis of length ``n ≥ minimum`` (a shorter axis
    is whole in every bucket), ascending; a single bucket if every axis is short. One switch index
    for all axes (not one per axis) keeps the compiles at ``count``: the axes grow together (a run's
    poses and the objects it creates), or only one is long."""
    if count is None:
        count = buckets_from_environment() if BUCKETS is None else BUCKETS
    minimum = MIN_BUCKETED if minimum is None else minimum
    if count <= 1 or all(n < minimum for n in lengths):
        return (tuple(lengths),)
    return tuple(dict.fromkeys(tuple(n if n < minimum else math.ceil(n * i / count) for n in lengths)
                               for i in range(1, count + 1)))


def by_bucket(sizes: tuple[tuple[int, ...], ...], live: tuple[Int[Array, ""] | int, ...], fn: Callable[..., Any],
              *operands: Any) -> Any:
    """``fn(size, *operands)`` for the first bucket ``size`` of ``sizes`` (:func:`bucket_sizes`)
    that holds ``live`` on every axis (the last if none does): ``fn`` is traced once per bucket, and
    every bucket must give outputs of the same shapes. ``live`` (one count per axis) may be traced
    and batched (:func:`batch_max`)."""
    if len(sizes) == 1:
        return fn(sizes[0], *operands)
    index = jnp.zeros((), jnp.int32)
    for axis, count in enumerate(live):
        bounds = jnp.asarray([size[axis] for size in sizes])
        index = jnp.maximum(index, jnp.searchsorted(bounds, batch_max(jnp.asarray(count, jnp.int32))))
    branches = [functools.partial(fn, size) for size in sizes]
    return jax.lax.switch(jnp.minimum(index, len(sizes) - 1), branches, *operands)
