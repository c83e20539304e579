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

Unknown maps (SCENARIO_FORMAT.md, "Unknown maps"): a slot may also hold :data:`NEW`, the null /
new-landmark hypothesis (thesis Sec. 3.2.1): the detection is an object not yet in the map. The
new objects of a child take the parent's next uncreated slots, in slot order; those beyond the
parent's last slot are *unmapped* (weighed as new objects, not stored: ``Children.unmapped``).

Gating (``Config.gate_candidates = G``): the table then names *candidate ranks* ``0..G-1``
instead of objects, ``(G + 2)^Dmax`` rows (each slot empty, a rank, or :data:`NEW`), and each
parent maps ranks to its own candidates per detection (:mod:`hybridslam.gating`). Injectivity then
depends on the parent, so it is checked per parent rather than built into the table.
"""

from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

EMPTY, NEW = -1, -2  # table entries: no detection in the slot; the detection is a new object


class HypothesisTable(NamedTuple):
    assign: np.ndarray  # (A, Dmax) int: object (or candidate rank when gated), EMPTY, NEW
    combos: np.ndarray  # (Mc, Dmax) int


@functools.lru_cache(maxsize=None)
def hypothesis_table(
    num_objects: int, max_detections: int, num_classes: int, new_objects: bool = False, gated: bool = False
) -> HypothesisTable:
    """The static table. ``num_objects`` is the number of candidate ranks ``G`` when ``gated``."""
    choices = list(range(num_objects)) + ([NEW] if new_objects else [])
    rows = []
    for used in range(max_detections + 1):
        for slots in itertools.combinations(range(max_detections), used):
            for objs in itertools.product(choices, repeat=used):  # lexicographic, as permutations()
                named = [o for o in objs if o != NEW]
                if not gated and len(set(named)) < len(named):
                    continue
                row = [EMPTY] * max_detections
                for slot, obj in zip(slots, objs):
                    row[slot] = obj
                rows.append(row)
    combos = list(itertools.product(range(num_classes), repeat=max_detections))
    return HypothesisTable(
        np.asarray(rows, dtype=np.int32).reshape(-1, max_detections),
        np.asarray(combos, dtype=np.int32).reshape(-1, max_detections),
    )


class Children(eqx.Module):
    """The children of one parent, on a grid ``(A, Mc)`` of (assignment, class combo) (``*K``: stacked
    over parents by ``vmap``)."""

    valid: Bool[Array, "*K A Mc"]  # a real, distinct hypothesis for this step's detection mask
    slot_class: Int[Array, "*K A Mc Dmax"]  # class of the object named in each slot (0 if empty)
    new: Bool[Array, "*K A Mc Dmax"]  # slot associates an object for the first time here
    log_prior: Float[Array, "*K A Mc"]  # Σ log P(c_n) over newly realized classes (Eq. 3)
    assign: Int[Array, "*K A Dmax"]  # β_k: the object of each slot (created ones included), -1 = empty
    creates: Bool[Array, "*K A Dmax"]  # the slot's detection creates object assign[a, j] (unknown maps)
    unmapped: Bool[Array, "*K A Dmax"]  # the slot's detection is a new object with no free slot (assign -1)
    candidates: Int[Array, "*K Dmax G"] | None = None  # gated: the objects that rank r names, per slot

    @property
    def measured(self) -> Int[Array, "*K A Dmax"]:
        """``assign`` with the creating slots emptied: those detections are no factor on the
        object Gaussian (:func:`hybridslam.discovery.create_object` already used them)."""
        return jnp.where(self.creates, EMPTY, self.assign)


def resolve(
    table: HypothesisTable, num_created: Int[Array, ""] | None, candidates: Int[Array, "Dmax G"] | None,
    num_objects: int,
) -> tuple[Int[Array, "A Dmax"], Bool[Array, "A Dmax"], Bool[Array, "A Dmax"], Bool[Array, " A"]]:
    """The objects a parent's table rows name, which slots create one, which are unmapped, and which
    rows are possible.

    Known slots name ``candidates[j, rank]`` (or the entry itself without gating); new ones take
    the slots ``num_created, num_created + 1, ...`` in slot order, and those beyond the
    ``num_objects`` slots are unmapped (``assign`` -1). A row is possible when its known objects
    exist and are distinct.
    """
    rank = jnp.asarray(table.assign)
    occupied, new_object = rank != EMPTY, rank == NEW
    named = occupied & ~new_object
    safe = jnp.maximum(rank, 0)
    known = safe if candidates is None else candidates[jnp.arange(rank.shape[1])[None, :], safe]
    created = jnp.asarray(num_objects, rank.dtype) if num_created is None else num_created
    obj = jnp.where(new_object, created + jnp.cumsum(new_object, axis=-1, dtype=rank.dtype) - 1, known)
    creates, unmapped = new_object & (obj < num_objects), new_object & (obj >= num_objects)
    assign = jnp.where(occupied & ~unmapped, obj, EMPTY)
    same = (assign[:, :, None] == assign[:, None, :]) & named[:, :, None] & named[:, None, :]
    distinct = ~jnp.any(same & ~jnp.eye(rank.shape[1], dtype=bool)[None], axis=(1, 2))
    exists = jnp.all(~named | (known < created), axis=-1)
    return assign, creates, unmapped, distinct & exists


def children(
    table: HypothesisTable,
    parent_classes: Int[Array, " N"],
    mask: Bool[Array, " Dmax"],
    class_prior: Float[Array, "N M"],
    realize_classes: bool = True,
    num_created: Int[Array, ""] | None = None,
    candidates: Int[Array, "Dmax G"] | None = None,
) -> Children:
    """Split one parent (Algorithm 1, line 2) given its class realizations and the detection mask.

    With ``realize_classes=False`` (a classifier that ignores scores) objects stay open: every
    class realization would have the same weight and Gaussian, so by the argument of Sec. IV-D
    they need not be split, and ``P(C | H_k)`` stays the prior — exactly.

    Unknown maps: ``num_created`` objects exist in the parent; a created object's class is open
    (``-1``), so its first detection realizes it like any first association (Sec. IV-D), with
    prior ``class_prior`` of its slot. ``candidates``: the parent's gate (:mod:`hybridslam.gating`).
    """
    possible: Array | bool
    if num_created is None and candidates is None:  # known map, exact enumeration
        flat = jnp.asarray(table.assign)
        creates, possible = jnp.zeros(flat.shape, bool), True
        unmapped = creates
    else:
        flat, creates, unmapped, feasible = resolve(table, num_created, candidates, parent_classes.shape[0])
        possible = feasible[:, None]
    assign = flat[:, None, :]  # (A, 1, Dmax)
    combos = jnp.asarray(table.combos)[None, :, :]  # (1, Mc, Dmax)
    occupied = assign >= 0
    obj = jnp.where(occupied, assign, 0)
    known = parent_classes[obj]  # (A, 1, Dmax)
    new = occupied & (known < 0) & realize_classes
    slot_class = jnp.where(new, combos, jnp.where(occupied, jnp.maximum(known, 0), 0))
    canonical = jnp.all(new | (combos == 0), axis=-1)  # unused combo entries must be 0
    matches_mask = jnp.all((occupied | unmapped[:, None, :]) == mask[None, None, :], axis=-1)  # (A, 1)
    valid = canonical & matches_mask & possible
    log_prior = jnp.sum(jnp.where(new, jnp.log(class_prior[obj, slot_class]), 0.0), axis=-1)
    return Children(valid, jnp.broadcast_to(slot_class, valid.shape + (assign.shape[-1],)),
                    jnp.broadcast_to(new, valid.shape + (assign.shape[-1],)), log_prior,
                    flat, creates, unmapped, candidates)
