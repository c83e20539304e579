"""How the parents split into children (Algorithm 1, line 2): exhaustively, or by a beam.

* :class:`Exhaustive` — every injective assignment of the step's detections to objects × every
  class realization of the newly associated objects, from the static table of :mod:`.hypotheses`:
  ``A · M^Dmax`` children per parent, exponential in the detections. The reference.
* :class:`Beam` — the children built one detection at a time (:func:`hybridslam.inference.beam.beam_search`):
  every partial child of every parent is extended by each option of the next detection (a
  candidate object with a class for a first association, or a new object), scored by its *joint*
  linearized weight so far (parent weight × class priors × new-object terms × the linearized
  marginal likelihood of the detections it names, thesis Eq. 4.14-4.15, × the in-view
  probability), and the ``width`` best survive. ``Dmax · width · (G+1)·M`` scores per step: linear
  in the detections. The density is carried per partial child in sequential form
  (:class:`~.weights.PartialChild`: ``N(r; 0, S) = Π_j N(r_j | r_<j)``), so a score costs one
  ``R×R`` conditional density and an ``R``-column triangular solve, not a ``Dmax R`` Cholesky.
  The survivors then get the weigher's own weight (Eq. 16), exactly as the exhaustive children
  do, so on steps where no more than ``width`` partial children are valid the two give the same
  children and weights (``tests/test_step.py``). Partial children dropped
  within ``log(prune_ratio)`` of the best (children that could have survived pruning) are counted
  in ``StepInfo.dropped_budget``.

  Unknown maps: a new object takes the parent's next free object slot. With none left the
  hypothesis is not lost (nor is the detection forced onto an old object): it is an *unmapped*
  object, weighed by the new-object term with its class marginalized
  (:func:`~.weights.class_marginal`), its detection unassociated (``assign = -1``,
  ``unmapped``) and counted in ``StepInfo.unmapped``. :mod:`.hypotheses` does the same.

  On a known map without a clutter hypothesis a step may have no child at all: more detections
  than objects, or gates that leave two detections only the same object (every detection must be
  of an object in the paper's model, and an assignment is injective). Rather than lose the whole
  step, the beam then lets a detection be *skipped*: an option ranked below every assignment that
  skips fewer (:func:`~hybridslam.inference.beam.beam_search`'s rank), so it changes nothing where
  a full assignment exists; otherwise the children that skip the fewest detections are kept
  (the joint-compatibility answer, thesis Sec. 3.2.2), the skipped ones unassociated (``-1``) and
  counted in ``StepInfo.skipped``.
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ...inference.batching import map_live
from ...inference.beam import beam_search
from ...models.measurement import Detections, SensorModel
from .belief import Belief
from .weights import LinearTables, PartialChild, class_marginal, empty_child, extend_child, linear_tables

# A child whose objects are (almost surely) out of view still ranks by its likelihood, this many
# nats below any child in view (as the laplace-is screen does).
OUT_OF_VIEW_NATS = 50.0


class Exhaustive(eqx.Module):
    """Every child of every parent (the static hypothesis table): the exact reference."""

    name: ClassVar[str] = "exhaustive"


class Beam(eqx.Module):
    """Children built one detection at a time, the ``width`` best kept (see the module docstring)."""

    width: int = eqx.field(default=64, static=True)
    name: ClassVar[str] = "beam"

    def __check_init__(self):
        if not (isinstance(self.width, int) and not isinstance(self.width, bool) and self.width >= 1):
            raise ValueError(f"Beam.width: expected a positive int, got {self.width!r}")


Branching = Exhaustive | Beam


class FlatChildren(NamedTuple):
    """``C`` children of any parents, with everything the weighers and the update need."""

    parent: Int[Array, " C"]
    assign: Int[Array, "C Dmax"]  # β_k: object of each slot (created ones included), -1 = empty
    creates: Bool[Array, "C Dmax"]  # the slot's detection creates object assign[c, j]
    unmapped: Bool[Array, "C Dmax"]  # the slot's detection is a new object with no free slot (assign -1)
    new: Bool[Array, "C Dmax"]  # the slot realizes its object's class here (Sec. IV-D)
    slot_class: Int[Array, "C Dmax"]  # class of the object each slot names (0 if empty)
    prior: Float[Array, " C"]  # parent log weight + class priors + new-object terms (no Gaussian factor)
    linear: Float[Array, " C"]  # linearized log-likelihood, with the in-view probability
    linear_free: Float[Array, " C"]  # ... without it
    valid: Bool[Array, " C"]
    dropped: Int[Array, ""]  # partial children dropped by the budget within log(prune_ratio) of the best

    @property
    def measured(self) -> Int[Array, "C Dmax"]:
        """``assign`` without the creating slots (no factor: the back-projection used them)."""
        return jnp.where(self.creates, -1, self.assign)


def beam_children(
    belief: Belief,
    mean: Float[Array, "K D"],
    cov: Float[Array, "K D D"],
    detections: Detections,
    candidates: Int[Array, "K Dmax G"] | None,
    new_terms: Float[Array, "K Dmax M"] | None,
    realize: bool,
    width: int,
    batch_axis: str | None,
    clutter_terms: Float[Array, "K Dmax"] | None = None,
    skip: bool = False,
) -> FlatChildren:
    """The ``width`` best children of the propagated parents ``(mean, cov)`` (see the module docstring).

    ``candidates``: each parent's gate (the objects a slot may name); ``None`` names every object.
    ``new_terms``: each parent's :func:`~.weights.new_object_log_likelihood` (``None``: known map).
    ``clutter_terms``: each parent's log likelihood of each detection under the clutter hypothesis
    (``None``: no clutter hypothesis); a clutter slot associates nothing (``assign = -1``).
    ``skip`` (without ``clutter_terms``): a detection may be left unassociated, ranked below every
    child that skips fewer (module docstring); only the children that skip the fewest are valid.
    """
    if skip and clutter_terms is not None:
        raise ValueError("beam_children: skip is the fallback without a clutter hypothesis, not beside one")
    model = belief.model
    sensor: SensorModel = model.sensor
    k, n = belief.capacity, belief.num_objects
    dmax = detections.mask.shape[0]
    m = model.num_classes
    classes_here = m if realize else 1
    discovery = new_terms is not None
    gated = candidates is not None
    g = candidates.shape[-1] if gated else n
    clutter = clutter_terms is not None or skip
    choices = g + (1 if discovery else 0) + (1 if clutter else 0)  # the candidates, a new object, clutter / skip
    num_options = choices * classes_here
    created = belief.num_created if discovery else jnp.full((k,), n, jnp.int32)
    unmapped_terms = class_marginal(new_terms) if discovery else None

    # Per parent: the residuals, Jacobian Gram matrix and in-view probability of every row a slot
    # may name (every object, or each slot's candidates).
    def tables_of(mn, cv, cand):
        objs = jnp.arange(n) if cand is None else cand.reshape(-1)
        return linear_tables(sensor, mn, cv, detections, objs)

    tables: LinearTables = map_live(tables_of, belief.alive, mean, cov, candidates, axis_name=batch_axis)
    slots = jnp.arange(dmax)

    def child(opts: Int[Array, " S"], upto: Int[ArrayLike, ""]):
        """Every field of the child ``opts = [parent, option of slot 0, ...]`` over slots ``0..upto``
        but its density, and the table rows its slots name (``rows``, ``named``)."""
        p = opts[0]
        o = opts[1:]
        considered = slots <= upto
        occupied = detections.mask & considered
        choice, c = o // classes_here, o % classes_here
        named = occupied & (choice < g)
        new_object = occupied & (choice == g) if discovery else jnp.zeros(dmax, bool)
        noise = occupied & (choice == choices - 1) if clutter else jnp.zeros(dmax, bool)
        obj = jnp.where(named, candidates[p, slots, jnp.minimum(choice, g - 1)] if gated else choice, 0)
        made = created[p] + jnp.cumsum(new_object, dtype=jnp.int32) - 1
        # A new object beyond the component's object slots is scored as one but not stored (unmapped).
        makes, unmapped = new_object & (made < n), new_object & (made >= n)
        assign = jnp.where(named, obj, jnp.where(makes, made, -1))
        ok = jnp.all(jnp.where(occupied, named | new_object | noise, jnp.where(considered, o == 0, True)))
        twice = (obj[:, None] == obj[None, :]) & named[:, None] & named[None, :] & ~jnp.eye(dmax, dtype=bool)
        ok &= ~jnp.any(twice) & jnp.all(~named | (obj < created[p]))
        known = belief.classes[p, jnp.where(named, obj, 0)]
        first = named & (known < 0) & realize
        new = first | (makes & realize)
        ok &= jnp.all(new | (c == 0))  # a slot's class option is used only by a first association
        slot_class = jnp.where(new, c, jnp.where(named, jnp.maximum(known, 0), 0))
        prior_obj = jnp.where(named, obj, jnp.minimum(made, n - 1))
        log_prior = belief.log_weights[p] + jnp.sum(jnp.where(new, jnp.log(model.class_prior[prior_obj, slot_class]), 0.0))
        if discovery:
            log_prior += jnp.sum(jnp.where(makes, new_terms[p, slots, slot_class], 0.0))
            log_prior += jnp.sum(jnp.where(unmapped, unmapped_terms[p], 0.0))
        if clutter_terms is not None:
            log_prior += jnp.sum(jnp.where(noise, clutter_terms[p], 0.0))
        rows = jnp.where(named, slots * g + jnp.minimum(choice, g - 1) if gated else obj, -1)
        skipped = jnp.sum(noise, dtype=jnp.int32) if skip else jnp.zeros((), jnp.int32)
        return ok, assign, makes, unmapped, new, slot_class, log_prior, rows, named, skipped

    # The density of the detections a partial child names is carried per beam row in sequential
    # form (weights.PartialChild): an extension adds one slot's conditional term, and its row is
    # the score's by-product. (Recomputing the row for the kept extensions only, with an
    # ``advance`` and L⁻¹ carried instead of L, was slower at 16 detections: 78 against 73 ms.)
    def score(opts, j, partial: PartialChild, parent_score):
        ok, *_, slot_class, log_prior, rows, named, skipped = child(opts, j - 1)
        grown = extend_child(tables, opts[0], partial, rows, slot_class, named, j - 1)
        in_view = jnp.maximum(grown.log_lik + grown.log_vis, grown.log_lik - OUT_OF_VIEW_NATS)
        return jnp.where(ok, log_prior + in_view, -jnp.inf), skipped, grown

    # The beam starts from the parents (slot 0 of an option vector is the parent's index).
    start = min(width, k)
    first = jnp.full((width, 1 + dmax), 0, jnp.int32).at[:start, 0].set(jnp.arange(start, dtype=jnp.int32))
    first_score = jnp.full((width,), -jnp.inf).at[:start].set(belief.log_weights[:start])
    keep = jnp.log(model.prune_ratio)
    rdim = tables.r_bar.shape[-1]
    empty = jax.tree.map(lambda a: jnp.broadcast_to(a, (width,) + a.shape), empty_child(dmax, rdim, mean.dtype))
    found = beam_search(score, 1 + dmax, num_options, width, fill=0, keep_nats=keep, start=(first, first_score),
                        first_slot=1, carry=empty, stop=1 + detections.span())  # slot 0 is the parent
    ok, assign, makes, unmapped, new, slot_class, log_prior, *_ = jax.vmap(child, (0, None))(found.options, dmax - 1)
    valid = ok & found.valid
    if skip:  # only the children that skip the fewest detections (the beam ranks them first)
        valid &= found.rank == jnp.min(jnp.where(valid, found.rank, jnp.iinfo(jnp.int32).max))
    lin_free = found.rows.log_lik
    lin = lin_free + found.rows.log_vis
    return FlatChildren(found.options[:, 0], assign, makes, unmapped, new, slot_class, log_prior, lin, lin_free,
                        valid, found.dropped)
