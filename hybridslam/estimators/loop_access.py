"""What the loop closure during the run (:mod:`.loop_online`) needs of an estimator: the access an
estimator gives through :meth:`~.base.AbstractEstimator.loop_closure_access`, and the component
the search adds. Its own module so that the estimators' base names the access without importing
the search."""

from __future__ import annotations

import abc
from typing import Any, NamedTuple

import numpy as np


class MergedComponent(NamedTuple):
    """A component :class:`OnlineLoopClosure` adds, in its own object numbering: its association
    history ``(T, Dmax)``, class realizations ``(Nmax,)`` (-1 open), objects in use, trajectory
    ``(T+1, 3)``, marginal mean ``(D,)`` and covariance ``(D, D)`` of ``[x_k, objects]``, and per
    object in use the parent component's objects it joins (one: kept or split off; more: merged)."""

    history: np.ndarray
    classes: np.ndarray
    num: int
    poses: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    sources: tuple[tuple[int, ...], ...]


class LoopClosureAccess(abc.ABC):
    """What :class:`OnlineLoopClosure` needs of one estimator's state beyond the fields every
    mixture state here has (module docstring)."""

    max_steps: int  # Gauss-Newton / Levenberg-Marquardt iterations of each re-solve

    @abc.abstractmethod
    def classes(self, state: Any, i: int) -> np.ndarray:
        """Component ``i``'s class realization per object slot ``(Nmax,)``, ``-1`` where open: the
        search pairs only objects whose realizations are equal or open."""

    @abc.abstractmethod
    def factors(self, state: Any) -> tuple[bool, bool]:
        """``(semantic, realize)``: whether the re-solved graph has the estimator's semantic factors,
        and whether they take each object's class realization (the graph the estimator smooths)."""

    @abc.abstractmethod
    def write(self, state: Any, slot: int, log_weights: np.ndarray, component: MergedComponent,
              parent: int) -> Any:
        """``state`` with ``component`` in ``slot`` (its other fields derived from component
        ``parent``'s) and the normalized ``log_weights (K,)``."""
