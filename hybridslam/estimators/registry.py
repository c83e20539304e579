"""Estimators by name, and from command-line style options (``hybridslam run --estimator NAME``)."""

from __future__ import annotations

from typing import Any

from ..io.scenario import Scenario
from .base import AbstractEstimator
from .gpda import GPDA
from .hybrid.branching import Beam, Exhaustive
from .hybrid.estimator import Hybrid
from .hybrid.weighers import WEIGHERS, LaplaceIS, make_weigher
from .maxmix import MaxMixture
from .ml import ML
from .smoothing import parse_smoother
from .multimodal import Multimodal
from .profiles import recommended

ESTIMATORS: dict[str, type[AbstractEstimator]] = {
    "hybrid": Hybrid,
    "ml": ML,
    "gpda": GPDA,
    "max-mixture": MaxMixture,
    "multimodal": Multimodal,
}

# Which estimator setting each option sets (an option an estimator lacks is an error, never ignored).
_COMMON = {"classifier": "classifier", "gn_max_steps": "gn_max_steps", "max_detections": "max_detections",
           "new_landmark": "new_landmark",
           "max_steps": "max_steps", "smoother": "smoother"}
_OPTIONS: dict[str, dict[str, str]] = {
    "hybrid": {**_COMMON, "capacity": "capacity", "prune_ratio": "prune_ratio", "gate": "gate",
               "weights": "weights", "samples": "weights", "visibility_temperature": "visibility_temperature",
               "max_children": "branching", "exhaustive": "branching", "clutter": "clutter"},
    "ml": {**_COMMON, "gate": "candidates", "gate_probability": "gate_probability", "max_children": "max_hypotheses",
             "clutter": "clutter"},
    "gpda": {**_COMMON, "gate": "candidates", "gate_probability": "gate_probability", "max_children": "max_hypotheses",
             "clutter": "clutter"},
    "max-mixture": {**_COMMON, "gate": "candidates", "gate_probability": "gate_probability",
                    "max_children": "max_hypotheses", "clutter": "clutter"},
    "multimodal": {**_COMMON, "capacity": "capacity", "samples": "samples", "gate": "candidates",
                   "max_children": "children", "merge_threshold": "merge_threshold",
                   "association_prior": "association_prior", "proposal": "proposal", "clutter": "clutter"},
}


def estimator_names() -> tuple[str, ...]:
    return tuple(ESTIMATORS)


def make_estimator(name: str, scenario: Scenario | None = None, profile: str | None = None,
                   **options: Any) -> AbstractEstimator:
    """The estimator ``name`` with ``options`` (``None`` values mean "the default").

    With ``scenario``, the options not given are those :func:`.profiles.recommended` chooses for
    that file (``profile="paper"``: the estimator's own defaults; ``None``: ``"auto"``), as
    ``hybridslam run`` does;
    loop closure during the run, which that profile may also choose, is not part of an estimator:
    ``recommended(scenario).close_loops``. Without ``scenario``, the estimator's own defaults.

    Options: ``classifier``, ``gn_max_steps``, ``max_detections`` (every estimator); ``capacity``
    (hybrid, multimodal); ``samples`` (the draws of the hybrid's weights or of multimodal's Monte
    Carlo); ``weights`` (hybrid: ``laplace-is``, ``sampled``, ``linearized``); ``prune_ratio``
    (hybrid); ``gate`` (the association gate: candidate objects per detection; the hybrid's default
    ``None`` enumerates every object); ``gate_probability`` (ml, gpda, max-mixture);
    ``max_children`` (the hybrid's beam width, ml/gpda/max-mixture's joint hypotheses, multimodal's
    updated children); ``exhaustive`` (hybrid: enumerate every child, the reference); ``clutter`` (every
    estimator: a clutter log density, ``"none"``, or ``"file"``, the default: the scenario's
    ``sensor.clutter_log_density``; ml, gpda, max-mixture and multimodal use it on a known map only). An option the
    estimator has no use for is an error naming it.
    """
    if name not in ESTIMATORS:
        raise ValueError(f"estimator: unknown {name!r} (known: {', '.join(ESTIMATORS)})")
    if scenario is not None:
        options = recommended(scenario, name, profile or "auto").merged(**options)
    given = {k: v for k, v in options.items() if v is not None}
    known = _OPTIONS[name]
    for option in given:
        if option not in known:
            users = [n for n, opts in _OPTIONS.items() if option in opts]
            where = f" (it applies to: {', '.join(users)})" if users else ""
            raise ValueError(f"--{option.replace('_', '-')}: the {name} estimator has no such setting{where}")
    special = ("weights", "samples", "max_children", "exhaustive") if name == "hybrid" else ()
    fields = {known[k]: v for k, v in given.items() if k not in special}
    if isinstance(fields.get("smoother"), str):
        fields["smoother"] = parse_smoother(fields["smoother"])
    if name == "hybrid" and ("weights" in given or "samples" in given):
        fields["weights"] = make_weigher(given.get("weights", LaplaceIS.name), given.get("samples"))
    if name == "hybrid" and given.get("exhaustive"):
        if "max_children" in given:
            raise ValueError("--max-children: the exhaustive enumeration keeps every child")
        fields["branching"] = Exhaustive()
    elif name == "hybrid" and "max_children" in given:
        fields["branching"] = Beam(width=given["max_children"])
    return ESTIMATORS[name](**fields)


__all__ = ["ESTIMATORS", "WEIGHERS", "estimator_names", "make_estimator"]
