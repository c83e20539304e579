"""What the analysis functions read from a belief: a weighted mixture of Gaussian components.

A structural type (PEP 544), so that :mod:`hybridslam.analysis` depends on no estimator: the hybrid
:class:`~hybridslam.estimators.hybrid.belief.Belief` and every estimator's
:class:`~hybridslam.estimators.Mixture` view have these fields.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from jaxtyping import Array, Bool, Float, Int


@runtime_checkable
class WeightedMixture(Protocol):
    """``K`` weighted Gaussian components (empty slots have ``log_weights = -inf``)."""

    @property
    def log_weights(self) -> Float[Array, " K"]: ...
    @property
    def weights(self) -> Float[Array, " K"]: ...
    @property
    def alive(self) -> Bool[Array, " K"]: ...
    @property
    def mean(self) -> Float[Array, "K D"]: ...  # the first three entries are the robot pose x_k
    @property
    def cov(self) -> Float[Array, "K D D"]: ...
    @property
    def classes(self) -> Int[Array, "K N"]: ...
    @property
    def history(self) -> Int[Array, "K T Dmax"]: ...


@runtime_checkable
class ClassedMixture(WeightedMixture, Protocol):
    """A mixture that also carries its model (for the class prior of objects left open, Sec. IV-D)."""

    @property
    def model(self) -> Any: ...  # has num_classes and class_prior (M,)
