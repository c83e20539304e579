"""Static enumeration of a step's association and class hypotheses (Algorithm 1, line 2; Sec. IV-D).

A parent component splits into one child per injective assignment ``β_k`` of the step's
detections to objects, times one class realization for every object that ``β_k`` associates for
the first time in that component (lazy realizations, Sec. IV-D). The table below enumerates both
once, in numpy, for the static shapes (objects ``N``, detection slots ``Dmax``, classes ``M``):

* ``assign[a]`` — an injective map from the *occupied* slots to objects; empty slots hold ``-1``.
  Every subset of slots is covered, so any detection mask selects exactly its own rows.
* ``combos[m]`` — a class for each slot. A child ``(a, m)`` uses ``combos[m, j]`` only where slot
  ``j`` names an object that is still open; elsewhere it must be 0 so children are not repeated.

Children per parent: ``A · M^Dmax`` with ``A = Σ_n C(Dmax, n) · N!/(N−n)!``.
"""

from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int


class HypothesisTable(NamedTuple):
    assign: np.ndarray  # (A, Dmax) int, -1 = empty slot
    combos: np.ndarray  # (Mc, Dmax) int


@functools.lru_cache(maxsize=None)
def hypothesis_table(num_objects: int, max_detections: int, num_classes: int) -> HypothesisTable:
    rows = []
    for used in range(max_detections + 1):
        for slots in itertools.combinations(range(max_detections), used):
            for objs in itertools.permutations(range(num_objects), used):
                row = [-1] * max_detections
                for slot, obj in zip(slots, objs):
                    row[slot] = obj
                rows.append(row)
    combos = list(itertools.product(range(num_classes), repeat=max_detections))
    return HypothesisTable(
        np.asarray(rows, dtype=np.int32).reshape(-1, max_detections),
        np.asarray(combos, dtype=np.int32).reshape(-1, max_detections),
    )


class Children(eqx.Module):
    """The children of one parent, on a grid ``(A, Mc)`` of (assignment, class combo)."""

    valid: Bool[Array, "A Mc"]  # a real, distinct hypothesis for this step's detection mask
    slot_class: Int[Array, "A Mc Dmax"]  # class of the object named in each slot (0 if empty)
    new: Bool[Array, "A Mc Dmax"]  # slot associates an object for the first time here
    log_prior: Float[Array, "A Mc"]  # Σ log P(c_n) over newly realized classes (Eq. 3)


def children(
    table: HypothesisTable,
    parent_classes: Int[Array, " N"],
    mask: Bool[Array, " Dmax"],
    class_prior: Float[Array, "N M"],
    realize_classes: bool = True,
) -> Children:
    """Split one parent (Algorithm 1, line 2) given its class realizations and the detection mask.

    With ``realize_classes=False`` (a classifier that ignores scores) objects stay open: every
    class realization would have the same weight and Gaussian, so by the argument of Sec. IV-D
    they need not be split, and ``P(C | H_k)`` stays the prior — exactly.
    """
    assign = jnp.asarray(table.assign)[:, None, :]  # (A, 1, Dmax)
    combos = jnp.asarray(table.combos)[None, :, :]  # (1, Mc, Dmax)
    occupied = assign >= 0
    obj = jnp.where(occupied, assign, 0)
    known = parent_classes[obj]  # (A, 1, Dmax)
    new = occupied & (known < 0) & realize_classes
    slot_class = jnp.where(new, combos, jnp.where(occupied, jnp.maximum(known, 0), 0))
    canonical = jnp.all(new | (combos == 0), axis=-1)  # unused combo entries must be 0
    matches_mask = jnp.all(occupied == mask[None, None, :], axis=-1)  # (A, 1)
    valid = canonical & matches_mask
    log_prior = jnp.sum(jnp.where(new, jnp.log(class_prior[obj, slot_class]), 0.0), axis=-1)
    return Children(valid, jnp.broadcast_to(slot_class, valid.shape + (assign.shape[-1],)),
                    jnp.broadcast_to(new, valid.shape + (assign.shape[-1],)), log_prior)
