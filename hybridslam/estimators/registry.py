"""Estimators by name, and from command-line style options (``hybridslam run --estimator NAME``)."""

from __future__ import annotations

from typing import Any

from ..models.scenario import Scenario
from .base import AbstractEstimator
from .gpda import GPDA
from .hybrid.estimator import Hybrid
from .hybrid.weighers import WEIGHERS
from .maxmix import MaxMixture
from .ml import ML
from .multimodal import Multimodal
from .options import Option, all_options, field_values, options_of
from .profiles import recommended

# Every estimator by the name ``--estimator`` selects: adding one here is all it takes for the
# commands to offer it with its options (read off its fields, :mod:`.options`).
ESTIMATORS: dict[str, type[AbstractEstimator]] = {
    "hybrid": Hybrid,
    "ml": ML,
    "gpda": GPDA,
    "max-mixture": MaxMixture,
    "multimodal": Multimodal,
}
DEFAULT = "hybrid"  # what ``--estimator`` selects when not given


def estimator_names() -> tuple[str, ...]:
    return tuple(ESTIMATORS)


def estimator_options() -> dict[str, Option]:
    """Every option of every estimator, by name (:func:`.options.all_options`)."""
    return all_options(ESTIMATORS)


def make_estimator(name: str, scenario: Scenario | None = None, profile: str | None = None,
                   **options: Any) -> AbstractEstimator:
    """The estimator ``name`` with ``options`` (``None`` values mean "the default").

    With ``scenario``, the options not given are those :func:`.profiles.recommended` chooses for
    that file (``profile="paper"``: the estimator's own defaults; ``None``: ``"auto"``), as
    ``hybridslam run`` does;
    loop closure during the run, which that profile may also choose, is not part of an estimator:
    ``recommended(scenario).close_loops``. Without ``scenario``, the estimator's own defaults.

    The options are read off the estimator class's fields (:mod:`.options`; every one, with what it
    means for each estimator: ``docs/cli.md``, "Estimator options", or :func:`estimator_options`);
    ``smoother`` may be its command-line text (``"lag:50"``). An option the estimator has no use
    for is an error naming it.
    """
    if name not in ESTIMATORS:
        raise ValueError(f"estimator: unknown {name!r} (known: {', '.join(ESTIMATORS)})")
    if scenario is not None:
        options = recommended(scenario, name, profile or "auto").merged(**options)
    given = {k: v for k, v in options.items() if v is not None}
    cls = ESTIMATORS[name]
    known = options_of(cls)
    for option in given:
        if option not in known:
            users = [n for n, c in ESTIMATORS.items() if option in options_of(c)]
            where = f" (it applies to: {', '.join(users)})" if users else ""
            raise ValueError(f"--{option.replace('_', '-')}: the {name} estimator has no such setting{where}")
    return cls(**field_values(cls, given))


__all__ = ["DEFAULT", "ESTIMATORS", "WEIGHERS", "estimator_names", "estimator_options", "make_estimator"]
