"""The beam search over a step's joint assignments (inference/beam.py): exact when it has room
for every assignment, and the same with an incremental score (``carry`` with ``advance``, or rows
returned by the score) as with a joint one."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hybridslam.inference.beam import beam_search

SLOTS, OPTIONS = 3, 3


def _pair_bonus(options, table, pair):
    """A non-separable joint score: per-slot terms plus a coupling of consecutive slots."""
    s = jnp.arange(SLOTS)
    per = table[s, options]
    couple = pair[options[:-1], options[1:]]
    return per, couple


@jax.jit
def _search(table, pair):
    def joint(opts, j):
        per, couple = _pair_bonus(opts, table, pair)
        upto = jnp.arange(SLOTS) <= j
        return jnp.sum(jnp.where(upto, per, 0.0)) + jnp.sum(jnp.where(upto[1:], couple, 0.0)), jnp.zeros((), jnp.int32)

    def incremental(opts, j, previous, parent):
        """The parent's score plus slot j's terms, the coupling read from the carried previous option."""
        return parent + table[j, opts[j]] + jnp.where(j > 0, pair[previous, opts[j]], 0.0), jnp.zeros((), jnp.int32)

    def with_row(opts, j, previous, parent):
        """As ``incremental``, returning the extension's row (its option at j) as well."""
        s, r = incremental(opts, j, previous, parent)
        return s, r, opts[j]

    width = OPTIONS**SLOTS
    a = beam_search(joint, SLOTS, OPTIONS, width, fill=0)
    b = beam_search(incremental, SLOTS, OPTIONS, width, fill=0, carry=jnp.zeros(width, jnp.int32),
                    advance=lambda previous, opts, j: opts[j])
    c = beam_search(joint, SLOTS, OPTIONS, 4, fill=0)
    d = beam_search(with_row, SLOTS, OPTIONS, width, fill=0, carry=jnp.zeros(width, jnp.int32))
    return a, b, c, d


finite = st.floats(-5.0, 5.0, allow_nan=False)


@settings(max_examples=20, deadline=None, derandomize=True)
@given(arrays(np.float64, (SLOTS, OPTIONS), elements=finite), arrays(np.float64, (OPTIONS, OPTIONS), elements=finite))
def test_beam_with_room_for_all_is_the_exhaustive_enumeration(table, pair):
    full, carried, narrow, scored_rows = _search(jnp.asarray(table), jnp.asarray(pair))
    want = {opts: sum(table[j, o] for j, o in enumerate(opts)) + sum(pair[a, b] for a, b in zip(opts, opts[1:]))
            for opts in itertools.product(range(OPTIONS), repeat=SLOTS)}
    for found in (full, carried, scored_rows):
        got = {tuple(int(o) for o in row): float(s) for row, s in zip(np.asarray(found.options), np.asarray(found.score))}
        assert got.keys() == want.keys()
        assert all(abs(got[k] - want[k]) < 1e-9 for k in want)
        assert int(found.dropped) == 0
    # A narrow beam (4 of 27) returns its rows best first, none better than the best assignment.
    for found in (carried, scored_rows):  # each final row is its assignment's last option
        np.testing.assert_array_equal(found.rows, found.options[:, -1])
    narrow_scores = np.asarray(narrow.score)
    assert np.all(np.diff(narrow_scores) <= 1e-12)
    assert narrow_scores[0] <= max(want.values()) + 1e-9


def test_advance_needs_a_carry():
    with pytest.raises(ValueError, match="advance needs a carry"):
        beam_search(lambda o, j, r, p: (0.0, 0), 2, 2, 4, fill=0, advance=lambda r, o, j: r)


PADDED = 5  # slots: the first `used` hold detections, the rest are padding (only `fill` allowed)


@jax.jit
def _padded_search(table, used):
    """A narrow beam over PADDED slots whose slots from ``used`` on are padding, with and without
    ``stop``; slot 0 starts from unsorted parents (as a belief's components enter the hybrid beam)."""
    slots = jnp.arange(PADDED)

    def score(opts, j, row, parent):
        padding = j >= used
        return jnp.where(padding, jnp.where(opts[j] == 0, parent, -jnp.inf), parent + table[j, opts[j]]), \
            jnp.zeros((), jnp.int32), row + jnp.where(padding, 0, opts[j])

    width = 4
    start = (jnp.zeros((width, PADDED), jnp.int32), jnp.array([-1.0, 0.5, -jnp.inf, 0.2]))
    carry = jnp.zeros(width, jnp.int32)
    plain = beam_search(score, PADDED, OPTIONS, width, fill=0, start=start, carry=carry)
    stopped = beam_search(score, PADDED, OPTIONS, width, fill=0, start=start, carry=carry,
                          stop=jnp.max(jnp.where(slots < used, slots + 1, 0)))
    return plain, stopped


@settings(max_examples=20, deadline=None, derandomize=True)
@given(arrays(np.float64, (PADDED, OPTIONS), elements=finite), st.integers(0, PADDED))
def test_stop_skips_the_padding_and_changes_nothing(table, used):
    """``stop`` skips the slots after the last detection; the beam (order, scores, rows, drops) is
    the one that extends them, also with no detection at all (the parents still get sorted)."""
    plain, stopped = _padded_search(jnp.asarray(table), used)
    valid = np.asarray(plain.valid)
    np.testing.assert_array_equal(np.asarray(stopped.valid), valid)  # the invalid rows hold no assignment
    np.testing.assert_array_equal(np.asarray(stopped.score), np.asarray(plain.score))
    for a, b in ((stopped.options, plain.options), (stopped.rank, plain.rank), (stopped.rows, plain.rows)):
        np.testing.assert_array_equal(np.asarray(a)[valid], np.asarray(b)[valid])
    assert int(stopped.dropped) == int(plain.dropped) and valid.sum() == (3 if used == 0 else 4)
    assert np.all(np.diff(np.asarray(stopped.score)[valid]) <= 0)


def test_a_step_s_span_ends_at_its_last_detection():
    """``Detections.span``: the slots the association search extends (a hole before the last
    detection counts; nothing after it does)."""
    from hybridslam.models.measurement import Detections

    mask = jnp.array([[True, False, True, False], [False] * 4, [True] * 4])
    d = Detections(jnp.zeros((3, 4, 2)), jnp.zeros((3, 4, 1)), mask)
    assert d.span().tolist() == [3, 0, 4]
    assert int(Detections(d.geo[0], d.scores[0], mask[0]).span()) == 3
