"""The object bookkeeping of the loop-closure pass (:mod:`.closure`): merges applied to a
slot history and the objects renumbered (:func:`compact`), and the run's own loop closures re-opened
(:func:`reopen`): where an object's detections stop for more than ``gap`` steps and then resume,
the later stretch becomes an object of its own, so that the pass decides it again jointly with the
rest. Pure numpy on ``(T, Dmax)`` histories (object per detection, ``-1`` none)."""

from __future__ import annotations

import numpy as np


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


def reopen(history: np.ndarray, classes: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Split every object at each pause of more than ``gap`` steps between its detections (module
    docstring): the new history, classes, each object's original index, and how many objects were
    added. Unchanged (0 added) if the objects would not fit in ``len(classes)`` slots
    (:func:`pauses` counts the objects it would add)."""
    h, cls, origin, added = _split(history, classes, gap)
    if used_slots(history) + added > len(classes):
        return history, classes, np.arange(len(classes)), 0
    return h, cls, origin, added


def pauses(history: np.ndarray, gap: int) -> int:
    """How many stretches of an object's detections follow a pause of more than ``gap`` steps: the
    objects :func:`reopen` adds, given the slots."""
    return _split(history, np.full(used_slots(history), -1), gap)[3]


def used_slots(history: np.ndarray) -> int:
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
