"""Settings chosen by the file: what ``hybridslam run`` uses for the options it is not given.

Each estimator's own defaults (``Hybrid()``: every object a candidate of every detection,
``laplace-is`` weights, the low-variance estimate of Eq. 16, 64 components, the full smoother) are
the reference configuration of the paper's setup (Tchuiev et al. 2019, Sec. V: Algorithm 1 with
every association enumerated), and the golden files pin them. On the paper's files (6 objects, at
most 2-4 detections per step, tens of steps) they cost a few ms per step. Beyond them they do not
serve: on a 75-step hallway file (100 object slots, unknown map) they take 2-3 minutes and end
1.5 m off, where the settings of the README's hallway and real-data studies take under a minute
and end 0.7 m off (``docs/settings.md``).

:func:`recommended` is a pure function of properties every scenario file has (object slots,
detections per step, steps, classes, whether the map is known), never of a dataset's name, so a
file from a new source (KITTI, another simulator) gets the settings of the files it resembles:

* **paper** — at most :data:`EXACT_MAX_OBJECTS` object slots and :data:`EXACT_MAX_DETECTIONS`
  detections per step: the estimator's own defaults, unchanged (the exact enumeration is cheap
  there, and it is what the paper and the golden files specify);
* **large** — more objects or detections: the hybrid belief with ``capacity 16``, ``gate 3``
  (thesis Sec. 3.2.1: 3 candidate objects per detection after Mahalanobis gating) and
  ``linearized`` weights, ``multimodal`` with ``capacity 16`` (the README's hallway and MRCLAM
  settings); ``ml``, ``gpda`` and ``max-mixture`` already gate to 3 candidates and keep their
  defaults;
* on an unknown map whose detections carry class scores (two classes or more and a classifier
  that is not ``none``), the hybrid belief with the full smoother also closes loops during the
  run (:class:`~.loops.online.OnlineLoopClosure`, gap 20): the merge search only pairs objects of
  one class, and the class pattern is what tells two places apart (README, The hallway). Where
  every landmark looks the same (MRCLAM's barcodes hidden) the merges it finds join landmarks of
  one cluster, it does not help and it doubles the run's time (README, Real data), so it is off;
* **long** — more than :data:`LONG_RUN_STEPS` steps: ``incremental:L`` instead of the full
  smoother, which re-solves the whole trajectory at every step: ``lag:L``'s bounded steps and, at
  the last step, the whole graph re-solved, so the result's trajectory is the batch solution
  (docs/performance.md, Whole logs). ``L`` is :data:`LONG_RUN_LAG` (50) for the mixtures (the
  hybrid belief: 31 ms per step on a whole MRCLAM log, against up to 550 ms) and
  :data:`LONG_RUN_LAG_SINGLE` (20) for ``ml``, ``gpda`` and ``max-mixture``, whose step is mostly
  the window's solve (``ml``: 4.3-4.9 ms instead of 6.6 ms, the same online errors).

Explicit settings always win: ``make_estimator(name, scenario=...)`` and ``hybridslam run`` fill only the options
they are not given.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from ..models.scenario import Scenario
from .smoothers import parse_smoother

PROFILES = ("auto", "paper")
EXACT_MAX_OBJECTS = 10  # the paper's map has 6 objects; MRCLAM 15 landmarks, the hallway 60-100 slots
EXACT_MAX_DETECTIONS = 4  # the paper's detector reports 2, the benchmark's paper layout 4; MRCLAM up to 8
LONG_RUN_STEPS = 500  # a full smoother's steps past this many poses cost several times a short run's
LONG_RUN_LAG = 50  # 25 s of MRCLAM's motion: the full smoother's online errors (docs/performance.md, Whole logs)
LONG_RUN_LAG_SINGLE = 20  # ml, gpda, max-mixture: their step is the window's solve (docs/performance.md, Whole logs)
CLOSE_LOOPS_GAP = 20  # LoopClosureSettings.gap's default: the README's hallway runs

_LARGE: dict[str, dict[str, Any]] = {
    "hybrid": {"capacity": 16, "gate": 3, "weights": "linearized"},
    "multimodal": {"capacity": 16},
}
_LONG_LAG = {"hybrid": LONG_RUN_LAG, "multimodal": LONG_RUN_LAG}  # the others: LONG_RUN_LAG_SINGLE


@dataclasses.dataclass(frozen=True)
class Profile:
    """The settings :func:`recommended` chose for one file and estimator.

    ``options``: :func:`~.registry.make_estimator` keywords (empty: the estimator's own defaults);
    ``close_loops``: the gap of loop closure during the run (``None``: none); ``kind``: ``"paper"``
    or ``"large"``, with ``"long"`` added for a file of more than :data:`LONG_RUN_STEPS` steps;
    ``reason``: what about the file chose them, in words.
    """

    estimator: str
    kind: str
    options: dict[str, Any]
    close_loops: int | None
    reason: str

    def flags(self) -> str:
        """The chosen settings as ``hybridslam run`` flags (``""``: none)."""
        out = []
        for name, value in self.options.items():
            out.append(f"--{name.replace('_', '-')} {value}")
        if self.close_loops is not None:
            out.append("--close-loops" if self.close_loops == CLOSE_LOOPS_GAP else f"--close-loops {self.close_loops}")
        return " ".join(out)

    def merged(self, **explicit: Any) -> dict[str, Any]:
        """``explicit`` options (``None``: not given) over the chosen ones: an explicit option always
        wins, and one that changes what a chosen option means drops it (``samples`` or ``exhaustive``
        with no ``weights``: the weights the draws are for, not ``linearized``)."""
        given = {k: v for k, v in explicit.items() if v is not None}
        chosen = dict(self.options)
        if "weights" not in given and ("samples" in given or given.get("exhaustive")):
            chosen.pop("weights", None)
        return {**chosen, **given}

    def loops(self, **explicit: Any) -> int | None:
        """The loop-closure gap to use under ``explicit`` options: ``None`` where they leave the
        hybrid belief's full smoother (loop closure during the run needs it)."""
        if self.close_loops is None:
            return None
        smoother = explicit.get("smoother")
        if isinstance(smoother, str):
            smoother = parse_smoother(smoother)
        if smoother is not None and not smoother.whole_trajectory:  # the search re-solves the whole graph
            return None
        return self.close_loops

    def between_steps(self, estimator, scenario: Scenario, gap: int | None = None, **settings: Any):
        """Loop closure during the run for :func:`hybridslam.run`'s ``between_steps`` (an
        :class:`~.loops.online.OnlineLoopClosure`, gap ``gap`` or the chosen one, and ``settings`` the
        other :class:`~.loops.settings.LoopClosureSettings` fields), or ``None`` where none was chosen
        and ``gap`` is ``None`` or the estimator cannot close loops (not the hybrid belief or
        ``multimodal`` with the full smoother)."""
        from .loops.online import OnlineLoopClosure
        from .loops.settings import LoopClosureSettings

        gap = self.close_loops if gap is None else gap
        smoother = getattr(estimator, "smoother", None)
        if (gap is None or estimator.loop_closure_access() is None or smoother is None
                or not smoother.whole_trajectory):
            return None
        return OnlineLoopClosure(estimator, scenario, LoopClosureSettings(gap=gap, **settings))


def file_summary(scenario: Scenario) -> str:
    """``a 75-step file with 100 object slots (unknown map), up to 4 detections per step``."""
    if scenario.discovery is not None:
        objects = f"{scenario.discovery.max_objects} object slots (unknown map)"
    else:
        objects = f"{scenario.num_objects} objects (known map)"
    return f"a {scenario.num_steps}-step file with {objects}, up to {scenario.max_detections} detections per step"


def object_slots(scenario: Scenario) -> int:
    """Objects an association may name: the known ones, or an unknown map's ``max_objects``."""
    return scenario.discovery.max_objects if scenario.discovery is not None else scenario.num_objects


def has_classes(scenario: Scenario) -> bool:
    """Whether the detections' scores can tell objects apart (two classes or more, a classifier)."""
    return scenario.num_classes >= 2 and scenario.classifier.model != "none"


def recommended(scenario: Scenario, estimator: str = "hybrid", profile: str = "auto") -> Profile:
    """The settings for ``estimator`` on ``scenario`` (module docstring); ``profile="paper"``: the
    estimator's own defaults whatever the file."""
    if profile not in PROFILES:
        raise ValueError(f"profile: expected one of {', '.join(PROFILES)}, got {profile!r}")
    if profile == "paper":
        return Profile(estimator, "paper", {}, None, "--profile paper: the estimator's own defaults")
    slots, detections = object_slots(scenario), scenario.max_detections
    options: dict[str, Any] = {}
    close_loops = None
    if slots <= EXACT_MAX_OBJECTS and detections <= EXACT_MAX_DETECTIONS:
        kind = "paper"
        reason = (f"at most {EXACT_MAX_OBJECTS} objects and {EXACT_MAX_DETECTIONS} detections per step: the "
                  f"paper's configuration")
    else:
        kind = "large"
        what = (f"{slots} objects, more than {EXACT_MAX_OBJECTS}" if slots > EXACT_MAX_OBJECTS else
                f"{detections} detections per step, more than {EXACT_MAX_DETECTIONS}")
        reason = f"{what}: the README's hallway and real-data settings"
        options.update(_LARGE.get(estimator, {}))
        if estimator == "hybrid" and scenario.discovery is not None and scenario.num_steps <= LONG_RUN_STEPS:
            if has_classes(scenario):
                close_loops = CLOSE_LOOPS_GAP
                reason += "; unknown map with classes: loop closure during the run"
            else:
                reason += "; unknown map without classes: no loop closure (it does not help there)"
    if scenario.num_steps > LONG_RUN_STEPS:
        kind += "+long"
        options["smoother"] = f"incremental:{_LONG_LAG.get(estimator, LONG_RUN_LAG_SINGLE)}"
        reason += (f"; more than {LONG_RUN_STEPS} steps: the fixed-lag window at every step, the whole graph "
                   "re-solved at the last")
    return Profile(estimator, kind, options, close_loops, reason)


__all__ = ["EXACT_MAX_DETECTIONS", "EXACT_MAX_OBJECTS", "LONG_RUN_STEPS", "PROFILES", "Profile", "file_summary",
           "recommended"]
