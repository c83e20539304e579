"""Smoothers: how an estimator's components keep and re-solve their trajectories (a strategy chosen
once, at the boundary: ``--smoother`` or an estimator's ``smoother=`` field).

* :mod:`.kinds`: the smoother objects (:class:`Full`, :class:`Lag`, :class:`Incremental`,
  :class:`Filter`), what they keep between steps (:class:`SmootherState`, one field of every
  estimator state) and their step;
* :mod:`.factors`: the factor graphs they solve, rebuilt from what a state holds (the data log and
  each component's factors); the solver itself is :mod:`hybridslam.inference.smoother`;
* here: :data:`SMOOTHERS`, the one place a smoother is registered.

A smoother is an :class:`AbstractSmoother` subclass (in a module of its own, or beside the built-in
ones in :mod:`.kinds`) with its ``spelling`` and ``summary``; its line in :data:`SMOOTHERS` makes
:func:`parse_smoother` read it, and ``--smoother``'s metavar and help (:data:`METAVAR`,
:func:`help_text`) name it, in this order. Only this package tests a smoother's type.
"""

from __future__ import annotations

from .kinds import AbstractSmoother, Closing, Filter, Full, Incremental, Lag, Smoother, SmootherState

__all__ = ["SMOOTHERS", "METAVAR", "AbstractSmoother", "Closing", "Filter", "Full", "Incremental", "Lag",
           "Smoother", "SmootherState", "help_text", "parse_smoother"]

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
