"""What the loop-closure pass (:mod:`.closure`) may do and what it reports: its settings
(:class:`LoopClosureSettings`), the score of one merge set (:class:`MergeScore`), one accepted round
(:class:`Closure`) and the pass's report (:class:`LoopClosureReport`)."""

from __future__ import annotations

import dataclasses
import math

from ...models.scenario import Scenario
from ...inference.gating import chi2_gate


@dataclasses.dataclass(frozen=True)
class LoopClosureSettings:
    """``gap``: steps between an old object's last detection and a late object's first (default
    20); ``gate``: squared Mahalanobis distance of a candidate pair's position difference (default
    25, wide: the pass is about drift of several sd); ``candidates``: old objects kept per late object
    (default 8); ``beam``: partial joint assignments kept (default 256); ``threshold``: the least log
    posterior odds to accept (default 0: more likely closed than not; during the run, against the
    component searched, and a negative value adds less likely closures as hypotheses of their own:
    :class:`~.online.OnlineLoopClosure`); ``revisit_log_odds``: the
    prior log odds, per merge, that a late object is an old one rather than new (default 0: the
    estimators' own model, in which a detection is a new object or a known one with no prior
    preference; a positive value says the robot expects to revisit, e.g. once the map is complete);
    ``verify_probability`` (default 0.999) and ``tries`` (default 8): the sets re-solved and
    verified per round; ``reopen`` (default True): first undo the run's own loop closures, so that
    the search decides them jointly with the rest (:mod:`.merge`); ``detection_probability``
    (``None``, the default: the scenario's ``sensor.detection_probability``, 0.9 where the file has
    none; 0 leaves negative information out), ``min_miss_probability`` (default 0.1: the least
    probability a miss is given, so a miss costs at most ``log 0.1``. The footprint test is on the
    solved estimate, not on the truth, so an object the estimate puts just inside may be truly
    outside; a sensor that never misses, detection probability 1 (the hallway simulator's), would
    otherwise rule out every merge that adds one miss), ``misses`` (default ``"marginal"``: how sure
    it is that an object was in view, under the solved graph's covariance; ``"point"``: in view when
    the solved object lies inside the solved pose's footprint by ``fov_margin``, default 0.5 m,
    0.2 rad; :mod:`.misses`) of the negative-information term; ``max_rounds`` (default 5; 0: only re-solve the graph); ``max_steps``: Levenberg-Marquardt
    iterations per solve (default 100)."""

    gap: int = 20
    gate: float = 25.0
    candidates: int = 8
    beam: int = 256
    threshold: float = 0.0
    revisit_log_odds: float = 0.0
    verify_probability: float = 0.999
    max_rounds: int = 5
    tries: int = 8
    reopen: bool = True
    detection_probability: float | None = None
    min_miss_probability: float = 0.1
    misses: str = "marginal"
    fov_margin: tuple[float, float] = (0.5, 0.2)
    max_steps: int = 100

    def __post_init__(self):
        for name in ("gap", "candidates", "beam", "max_rounds", "tries", "max_steps"):
            v, least = getattr(self, name), 0 if name in ("gap", "max_rounds") else 1
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= least):
                raise ValueError(f"LoopClosureSettings.{name}: expected a {'non-negative' if least == 0 else 'positive'}"
                                 f" int, got {v!r}")
        if not math.isfinite(self.revisit_log_odds):
            raise ValueError(f"LoopClosureSettings.revisit_log_odds: expected a finite number, got {self.revisit_log_odds!r}")
        if not (math.isfinite(self.gate) and self.gate > 0):
            raise ValueError(f"LoopClosureSettings.gate: expected a positive number, got {self.gate!r}")
        if not math.isfinite(self.threshold):
            raise ValueError(f"LoopClosureSettings.threshold: expected a finite number, got {self.threshold!r}")
        chi2_gate(self.verify_probability)  # raises on a probability outside (0, 1)
        if self.detection_probability is not None and not 0.0 <= self.detection_probability <= 1.0:
            raise ValueError("LoopClosureSettings.detection_probability: expected a number in [0, 1] or None, got "
                             f"{self.detection_probability!r}")
        if not 0.0 < self.min_miss_probability <= 1.0:
            raise ValueError("LoopClosureSettings.min_miss_probability: expected a number in (0, 1], got "
                             f"{self.min_miss_probability!r}")
        if self.misses not in MISS_MODELS:
            raise ValueError(f"LoopClosureSettings.misses: expected one of {', '.join(MISS_MODELS)}, got {self.misses!r}")
        if len(self.fov_margin) != 2 or not all(math.isfinite(m) and m >= 0 for m in self.fov_margin):
            raise ValueError(f"LoopClosureSettings.fov_margin: expected two non-negative numbers, got {self.fov_margin!r}")


    def for_scenario(self, scenario: Scenario) -> LoopClosureSettings:
        """These settings with ``detection_probability`` decided: its own value, else the scenario's
        ``sensor.detection_probability``, else :data:`DEFAULT_DETECTION_PROBABILITY`."""
        if self.detection_probability is not None:
            return self
        p = scenario.detection_probability
        return dataclasses.replace(self, detection_probability=DEFAULT_DETECTION_PROBABILITY if p is None else p)


DEFAULT_DETECTION_PROBABILITY = 0.9  # a file without sensor.detection_probability
MISS_MODELS = ("marginal", "point")  # LoopClosureSettings.misses (misses.py)


@dataclasses.dataclass(frozen=True)
class Closure:
    """One accepted round: ``merges`` ``(late, old)`` object pairs (indices of the run's final
    component before the pass), its score (``log_bayes_factor``: log posterior odds against no
    merge, the negative-information term included) and the smoother cost before and after."""

    merges: tuple[tuple[int, int], ...]
    log_bayes_factor: float
    cost_before: float
    cost_after: float


@dataclasses.dataclass(frozen=True)
class LoopClosureReport:
    """What :func:`~.closure.close_loops` did: the accepted rounds; ``considered``: late objects with at least one
    gated candidate, summed over rounds; ``beam_dropped``: partial assignments the beam dropped
    (0: the search was exhaustive); ``rejected``: merge sets whose re-solved graph failed verification (each undone);
    ``failed``: whether a solve did not converge (the last good solution is kept); ``reopened``: the
    run's own loop closures re-opened (``reopen``), each a later stretch of an object's detections
    made a late object of its own (a merge back onto the same object confirms it)."""

    closures: tuple[Closure, ...]
    considered: int
    beam_dropped: int
    rejected: int
    failed: bool
    reopened: int = 0

    @property
    def merged(self) -> int:
        return sum(len(c.merges) for c in self.closures)

    def summary(self) -> str:
        pairs = ", ".join(f"{a}->{b}" for c in self.closures for a, b in c.merges) or "none"
        lines = [f"loop closure: {self.merged} objects merged ({pairs}) in {len(self.closures)} round(s); "
                 f"{self.considered} late objects had candidates; {self.reopened} of the run's own closures re-opened"]
        if self.beam_dropped:
            lines.append(f"warning: the beam dropped {self.beam_dropped} partial assignments (raise the beam: "
                         "LoopClosureSettings.beam, close-loops --beam)")
        if self.rejected:
            lines.append(f"warning: {self.rejected} merge set(s) failed verification and were undone")
        if self.failed:
            lines.append("warning: a smoother solve did not converge; the last converged solution is kept")
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class MergeScore:
    """How the pass judges one merge set (:func:`~.closure.score_merges`): ``log_bayes_factor`` against no
    merge (Laplace, from the unmerged graph; ``revisit_log_odds`` per merge included), the
    ``negative_information`` term of the re-solved graph (log-likelihood change of the misses),
    ``log_odds``, their sum (what :func:`~.closure.close_loops` compares with ``threshold``), ``cost_rise``
    (smoother cost after the merge minus before, re-solved) and whether it passes verification
    (``verified``: converged, and ``2 · cost_rise`` within the chi-square ``verify_probability``
    quantile)."""

    log_bayes_factor: float
    negative_information: float
    cost_rise: float
    verified: bool

    @property
    def log_odds(self) -> float:
        return self.log_bayes_factor + self.negative_information
