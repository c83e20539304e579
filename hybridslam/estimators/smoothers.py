"""The smoothers ``--smoother`` offers: :data:`SMOOTHERS` is the one place a smoother is registered.

A smoother is an :class:`~.smoothing.AbstractSmoother` subclass (in a module of its own, or beside
the built-in ones in :mod:`.smoothing`) with its ``spelling`` and ``summary``; its line here makes
:func:`parse_smoother` read it, and ``--smoother``'s metavar and help (:data:`METAVAR`,
:func:`help_text`) name it, in this order.
"""

from __future__ import annotations

from .smoothing import AbstractSmoother, Filter, Full, Incremental, Lag

SMOOTHERS: tuple[type[AbstractSmoother], ...] = (Full, Lag, Incremental, Filter)

METAVAR = "{" + ",".join(s.spelling for s in SMOOTHERS) + "}"


def help_text() -> str:
    """``--smoother``'s help: each smoother's spelling and summary."""
    return "; ".join(f"{s.spelling}: {s.summary}" for s in SMOOTHERS)


def parse_smoother(text: str) -> AbstractSmoother:
    """The smoother ``text`` spells (``"full"``, ``"lag:50"``, ...: the ``--smoother`` option), else a
    ``ValueError`` that lists the spellings."""
    for kind in SMOOTHERS:
        smoother = kind.from_text(text)
        if smoother is not None:
            return smoother
    spellings = [s.spelling for s in SMOOTHERS]
    raise ValueError(f"--smoother: expected {', '.join(spellings[:-1])} or {spellings[-1]} (L a positive number of "
                     f"steps), got {text!r}")
