"""What every estimator is: one interface, one view of its belief, one report of each step.

An estimator is an :class:`AbstractEstimator`: an ``equinox.Module`` whose fields are its
settings (static: they fix shapes and code paths), validated when it is built. It has

* ``init(scenario) -> state`` — host-side: the belief before step 1, a pytree of fixed shapes
  that carries every traced parameter of the model (so changing alpha or a covariance never
  recompiles, and a batch of states may carry a batch of models);
* ``step(state, odometry, detections, key) -> (state, StepInfo)`` — pure and jittable:
  odometry ``u_k`` ``(3,)``, the step's :class:`~hybridslam.models.measurement.Detections`
  padded to a fixed number of slots, a PRNG key;
* ``view(state) -> Mixture`` — the belief as weighted Gaussian components over the current robot
  pose, which is all the result file (``docs/file_format.md``) and the paper's metrics need;
* ``trajectory(state)`` — the smoothed trajectory ``x_0..x_T`` of the best component, for
  estimators that keep it (``None`` for filters);
* ``describe()`` — the result file's ``estimator`` text.

:mod:`hybridslam.driver` runs any of them; :func:`make_estimator` builds one from its name and
command-line style options. A :class:`StepInfo` knows its own warnings, written once here (the way
optimistix's ``RESULTS`` carry their messages).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from ..version import __version__
from ..config import require_x64
from ..models.scenario import Scenario
from ..models.measurement import Detections
from .options import shown, value_text

LOW_ESS = 0.01  # below this a weight estimate rests on ~1% of its draws


class Mixture(eqx.Module):
    """A belief as ``K`` weighted Gaussian components over the current robot pose ``x_k``.

    A single-Gaussian estimator (``ml``, ``gpda``, ``max-mixture``) is a mixture with one live slot.
    The hybrid belief's own :class:`~hybridslam.estimators.hybrid.belief.Belief` has the same
    fields (its ``mean``/``cov`` hold the whole joint state, whose first three entries are ``x_k``),
    so the metrics and marginals of :mod:`hybridslam.analysis` take either.
    """

    log_weights: Float[Array, " K"]  # -inf marks an empty slot; need not be normalized
    mean: Float[Array, "K 3"]  # robot pose x_k = [x, y, theta]
    cov: Float[Array, "K 3 3"]
    classes: Int[Array, "K N"]  # class estimate or realization per object, -1 = none yet
    history: Int[Array, "K T Dmax"]  # object of each detection of steps 1..T; -1 = empty slot or clutter
    k: Int[Array, ""]  # steps taken

    @property
    def alive(self) -> Bool[Array, " K"]:
        return self.log_weights > -jnp.inf

    @property
    def weights(self) -> Float[Array, " K"]:
        return jnp.exp(self.log_weights)


# --------------------------------------------------------------------------- #
# The report of one step
# --------------------------------------------------------------------------- #


RELEVANT_NATS = 30.0  # e^-30 ≈ 1e-13: hypotheses further below the best do not raise warnings


def _zero_int() -> Int[Array, ""]:
    return jnp.zeros((), jnp.int32)


class StepInfo(eqx.Module):
    """What an estimator reports about one step: counts and flags (scalars), the same for every
    estimator (zero where a notion does not apply), plus estimator-specific ``details``.

    Every count of a hypothesis or detection that a budget, a gate or a capacity dropped is here,
    so nothing is lost silently; :meth:`warnings` turns them into one line each.
    """

    k: Int[Array, ""]  # the step just taken (1-based)
    num_components: Int[Array, ""]  # live components after the step
    log_evidence: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.full((), jnp.nan))
    dropped_capacity: Int[Array, ""] = eqx.field(default_factory=_zero_int)  # above the pruning threshold, no slot
    dropped_budget: Int[Array, ""] = eqx.field(default_factory=_zero_int)  # cut by a gate / child budget, would have survived pruning
    dropped_mass: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros(()))  # posterior mass beyond a budget
    visibility_ignored: Bool[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), bool))
    solver_failures: Int[Array, ""] = eqx.field(default_factory=_zero_int)  # updates that did not converge
    is_failures: Int[Array, ""] = eqx.field(default_factory=_zero_int)  # laplace-is mode searches that did not converge
    min_ess: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.full((), jnp.nan))  # smallest normalized ESS
    skipped: Int[Array, ""] = eqx.field(default_factory=_zero_int)  # detections left unassociated
    rejected: Int[Array, ""] = eqx.field(default_factory=_zero_int)  # detections explained as clutter / null
    # Detections of new objects weighed but not stored: no free object slot (unmapped objects).
    unmapped: Int[Array, ""] = eqx.field(default_factory=_zero_int)
    # A likely component had no free object slot at a step with detections (lacks_object_slots).
    object_overflow: Bool[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), bool))
    log_overflow: Int[Array, ""] = eqx.field(default_factory=_zero_int)  # detections beyond the smoother's factor budget
    # Most detections of the step unexplained by the best component (gating.contradicted).
    inconsistent: Bool[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), bool))
    # Components merged into a likelier one with the same Gaussian (the hybrid belief's merge_threshold).
    merged: Int[Array, ""] = eqx.field(default_factory=_zero_int)
    details: Any = None  # estimator-specific diagnostics (e.g. the hybrid belief's per-component solver results)

    def warnings(self) -> list[str]:
        """One line per thing a user must hear about after this step (host-side)."""
        return [f"step {int(self.k)}: {line}" for line in messages(_totals(self), per_step=True)]


def relevant_children(log_w: Float[Array, " C"]) -> Bool[Array, " C"]:
    """The children (or components) within ``RELEVANT_NATS`` of the best: those whose trouble a
    warning names (``multimodal``: with a smoother, the children smoothed)."""
    return log_w > jnp.max(log_w) - RELEVANT_NATS  # all -inf: none


def lacks_object_slots(mask: Bool[Array, " Dmax"], num_created: Int[Array, "*K"], max_objects: int,
                       relevant: Bool[ArrayLike, "*K"] = True) -> Bool[Array, ""]:
    """``StepInfo.object_overflow`` of an unknown map's step: a relevant component (``relevant``, e.g.
    within ``RELEVANT_NATS`` of the best) has no free object slot at a step with detections, so the
    capacity leaves no room for a new object (thesis Sec. 3.2.1: a detection of a new landmark is
    then an unmapped object, weighed but not stored). ``num_created``:
    objects that exist, per component. A component with a few free slots and more new landmarks in
    view is flagged one step later, when its slots are full."""
    return jnp.any(mask) & jnp.any(jnp.asarray(relevant) & (num_created >= max_objects))


_COUNTS = ("dropped_capacity", "dropped_budget", "dropped_mass", "visibility_ignored", "solver_failures",
           "is_failures", "skipped", "rejected", "unmapped", "object_overflow", "log_overflow",
           "num_components", "inconsistent", "merged")


def _totals(info: StepInfo) -> dict[str, float]:
    """Host-side totals of the counts of one info, or of a stack of them (any leading axes)."""
    return _totals_of({name: getattr(info, name) for name in (*_COUNTS, "min_ess")})


def _totals_of(counts: Mapping[str, Any]) -> dict[str, float]:
    """:func:`_totals` of :class:`StepInfo`'s fields given by name (a missing count is zero, a missing
    ``min_ess`` unknown), each of any shape (e.g. tracks × steps)."""
    a = {name: np.asarray(counts.get(name, 0)) for name in _COUNTS}
    ess = np.asarray(counts.get("min_ess", math.nan), dtype=float)
    out: dict[str, float] = {name: float(np.sum(v)) for name, v in a.items()}
    out["steps_dropped_capacity"] = float(np.sum(a["dropped_capacity"] > 0))
    out["min_ess"] = float(np.min(ess[np.isfinite(ess)])) if np.any(np.isfinite(ess)) else math.nan
    out["num_components_max"] = float(np.max(a["num_components"])) if a["num_components"].size else 0.0
    return out


def summarize(infos: StepInfo) -> list[str]:
    """The warnings of many steps at once (``infos`` stacked on leading axes, e.g. tracks × steps)."""
    return messages(_totals(infos), per_step=False)


def summarize_counts(counts: Mapping[str, Any]) -> list[str]:
    """:func:`summarize` of :class:`StepInfo`'s counts given by field name, as stored (e.g. a study's
    per-cell diagnostics, tracks × steps): a missing count is zero."""
    return messages(_totals_of(counts), per_step=False)


def messages(t: dict[str, float], per_step: bool) -> list[str]:
    """The warning lines for counts ``t`` (:func:`_totals`): the texts of every estimator, written once."""
    out = []
    where = "" if per_step else f" in {int(t['steps_dropped_capacity'])} step(s)"
    if (n := int(t["dropped_capacity"])) > 0:
        out.append(f"{n} {'hypothesis' if n == 1 else 'hypotheses'} above the pruning threshold dropped for lack "
                   f"of capacity{where} (the belief is truncated); rerun with a larger --capacity")
    if (n := int(t["dropped_budget"])) > 0:
        out.append(f"{n} {'hypothesis' if n == 1 else 'hypotheses'} cut by the association gate or the child "
                   "budget would have survived pruning; raise --gate or --max-children")
    if (m := t["dropped_mass"]) > 1e-6:
        out.append(f"{m:.2e} of the posterior mass lay in hypotheses beyond the child budget and was dropped "
                   "(raise --max-children or --capacity)")
    if (n := int(t["visibility_ignored"])) > 0:
        out.append("no hypothesis has every detected object in view; the visibility model was ignored "
                   + ("for this step" if per_step else f"for {n} step(s)")
                   + " (weights from the measurement likelihood alone; spurious detections? --clutter)")
    if (n := int(t["solver_failures"])) > 0:
        of = f" of {int(t['num_components'])}" if per_step else ""
        out.append(f"the update (Gauss-Newton; with a smoother, its Levenberg-Marquardt solve) did not converge for "
                   f"{n}{of} component(s)")
    if (n := int(t["is_failures"])) > 0:
        out.append(f"the laplace-is mode search did not converge for {n} component(s) (their weights stay "
                   "unbiased but are noisier)")
    if (e := t["min_ess"]) < LOW_ESS:
        out.append(f"a kept weight rests on few draws (effective sample size {e:.3g} of 1); its value is luck: "
                   "prefer --weights laplace-is or more --samples")
    if (n := int(t["skipped"])) > 0:
        out.append(f"{n} detection(s) left unassociated (no object inside the gate of a known map, more detections "
                   "than objects that could explain them: spurious ones? --clutter)")
    if (n := int(t["rejected"])) > 0:
        out.append(f"{n} detection(s) explained as clutter by the null hypothesis (treated as outliers)")
    if (n := int(t["unmapped"])) > 0:
        out.append(f"{n} detection(s) of new objects with no free object slot were weighed as new objects but not "
                   "stored (unmapped: later detections of them cannot be associated)")
    if int(t["object_overflow"]) > 0:
        out.append("object capacity full (a likely component has no free object slot"
                   + ("" if per_step else f", at {int(t['object_overflow'])} step(s)") + "): a new landmark is not "
                   "stored (its detections are weighed as unmapped new objects) (raise the file's discovery.max_objects: "
                   "hybridslam import mrclam or kitti-tracking --max-objects N)")
    if (n := int(t["inconsistent"])) > 0:
        out.append("most detections the best hypothesis could not explain (left unassociated, or associated beyond "
                   "the 1e-6 tail of its prediction) " + ("at this step" if per_step else f"at {n} step(s)")
                   + ": the pose belief contradicts the detections (a kidnapped robot, wrong odometry, a wrong map) "
                     "or they are spurious (--clutter)")
    if (n := int(t["merged"])) > 0:
        out.append(f"{n} component(s) merged into a likelier one with the same Gaussian (--merge-threshold): their weight "
                   "kept, their association histories dropped")
    if (n := int(t["log_overflow"])) > 0:
        out.append(f"{n} detection(s) beyond the smoother's factor budget are not in its graph (the state was sized "
                   "for a scenario with fewer detections, in all or in a fixed-lag window; build it with max_steps "
                   "set for room for every slot)")
    return out


# --------------------------------------------------------------------------- #
# The interface
# --------------------------------------------------------------------------- #


def _jsonable(value: Any) -> Any:
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (tuple, list)):
        return [_jsonable(v) for v in value]
    if isinstance(value, eqx.Module) and hasattr(value, "name") and dataclasses.is_dataclass(value):
        fields = {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
        name = getattr(value, "name")
        return {"name": name, **fields} if fields else name
    return type(value).__name__  # e.g. a classifier model object


def classifier_name(classifier: Any, scenario: Scenario | None) -> str:
    """How a result file names the classifier model an estimator runs with."""
    if classifier is None:
        return scenario.classifier.model if scenario is not None else "scenario"
    return classifier if isinstance(classifier, str) else type(classifier).__name__


CLUTTER_FROM_FILE = "file"  # an estimator's default clutter setting: the scenario's sensor.clutter_log_density
CLUTTER_OFF = "none"  # no clutter hypothesis, whatever the file says (also ``None``)


def check_clutter(owner: str, setting: Any) -> None:
    """``setting`` must be ``"file"``, ``"none"``/``None`` or a finite log density (a ValueError naming ``owner``)."""
    if setting is None or setting in (CLUTTER_FROM_FILE, CLUTTER_OFF):
        return
    if not (isinstance(setting, (int, float)) and not isinstance(setting, bool) and math.isfinite(setting)):
        raise ValueError(f"{owner}.clutter: expected a finite log density, 'file' or 'none', got {setting!r}")


def resolve_clutter(setting: Any, scenario: Scenario) -> float | None:
    """The clutter log density an estimator uses on ``scenario`` (``None``: no clutter hypothesis).

    ``"file"`` (every estimator's default): the scenario's optional ``sensor.clutter_log_density``,
    none when the file has no such field (the paper's model: every detection is of an object;
    ``hybridslam simulate`` writes no such field); ``"none"`` or ``None``: none; a number: that log
    density over ``[range, bearing]`` (prior probability of clutter included).
    """
    if setting == CLUTTER_FROM_FILE:
        return scenario.clutter_log_density
    if setting is None or setting == CLUTTER_OFF:
        return None
    return float(setting)


def clutter_text(setting: Any, scenario: Scenario | None) -> str:
    """``", clutter=D"`` for an estimator's settings line, ``""`` without a clutter hypothesis (or
    with ``"file"`` and no scenario to read it from)."""
    if scenario is None:
        value = None if setting is None or setting in (CLUTTER_FROM_FILE, CLUTTER_OFF) else float(setting)
    else:
        value = resolve_clutter(setting, scenario)
    return "" if value is None else f", clutter={value:g}"


def object_slots(scenario: Scenario) -> int:
    """The objects an association may name: the known ones, or an unknown map's ``max_objects``.
    A scenario with none is refused here, at init, naming the field (nothing to associate; a gather
    over an empty object axis would otherwise fail inside the compiled step)."""
    n = scenario.num_objects if scenario.discovery is None else scenario.discovery.max_objects
    if n < 1:
        raise ValueError("objects: the scenario has no objects and no discovery section to create any (a known map "
                         "must hold an object; a log without one is an unknown map: e.g. hybridslam import ... "
                         "--unknown-map)")
    return n


def detection_slots(max_detections: int | None, scenario: Scenario) -> int:
    """The detection slots of a state for ``scenario``: its largest step's, or ``max_detections`` (a
    shared number that lets files share one compiled step; fewer than a step has are refused)."""
    slots = max_detections or max(scenario.max_detections, 1)
    if scenario.max_detections > slots:
        raise ValueError(f"max_detections: {slots} slots, but a step of the scenario has "
                         f"{scenario.max_detections} detections")
    return slots


def history_length(max_steps: int | None, scenario: Scenario) -> int:
    """The association-history length of a state for ``scenario``: its steps, or ``max_steps`` (a
    shared length that lets files of different lengths run on one compiled step)."""
    if max_steps is None:
        return max(scenario.num_steps, 1)
    if max_steps < scenario.num_steps:
        raise ValueError(f"max_steps: {max_steps}, but the scenario has {scenario.num_steps} steps")
    return max_steps


class AbstractEstimator(eqx.Module):
    """The interface every estimator implements (see the module docstring)."""

    name: ClassVar[str]  # what ``--estimator`` selects
    title: ClassVar[str]  # what it is, in the result file's estimator text
    reference: ClassVar[str]  # the paper and section it implements
    # The fields the estimator text shows, in order (None: every field in field order, but those
    # that only size the compiled step); classifier comes first either way.
    described: ClassVar[tuple[str, ...] | None] = None
    # The settings only ``init`` reads: it writes their effect into the state (a traced value, such
    # as a clutter density or the new-landmark threshold, or the state's static structure), and the
    # step reads it there. Estimators that differ only in these share one compiled step
    # (:meth:`stepping`), so a sweep over them never recompiles.
    init_settings: ClassVar[tuple[str, ...]] = ()

    def __check_init__(self):
        # Every estimator computes in float64 (hybridslam.config): refused when built, not a float32 run.
        require_x64(f"{type(self).__name__}()")

    def stepping(self) -> AbstractEstimator:
        """This estimator as its compiled step sees it: :attr:`init_settings` at their defaults. The
        driver and the studies compile and call the step with it, so that estimators that differ
        only in what ``init`` wrote into the state share one program."""
        defaults = {f.name: f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc,operator]
                    for f in dataclasses.fields(self) if f.name in self.init_settings}
        return dataclasses.replace(self, **defaults) if defaults else self

    def closing(self) -> AbstractEstimator:
        """This estimator as the last step of a run sees it: its smoother's
        :meth:`~.smoothers.kinds.AbstractSmoother.closing` in place of the smoother (``incremental:L``:
        the whole graph re-solved once); itself where that is the same."""
        smoother = getattr(self, "smoother", None)
        if smoother is None or smoother.closing() is smoother:
            return self
        return dataclasses.replace(self, smoother=smoother.closing())  # type: ignore[call-arg]  # every smoothing estimator's field

    @abc.abstractmethod
    def init(self, scenario: Scenario) -> Any:
        """The state before step 1 (host-side; raises ``ValueError`` for a scenario it cannot run)."""

    @abc.abstractmethod
    def step(
        self, state: Any, odometry: Float[Array, "3"], detections: Detections, key: PRNGKeyArray
    ) -> tuple[Any, StepInfo]:
        """Advance the state by one step (pure, jittable)."""

    @abc.abstractmethod
    def view(self, state: Any) -> Mixture:
        """The belief as weighted Gaussian components over ``x_k``."""

    def trajectory(self, state: Any) -> Float[Array, "T1 3"] | None:
        """The smoothed ``x_0..x_T`` of the best component (smoothers), else ``None``."""
        return None

    def objects(self, state: Any) -> tuple[Float[Array, "N 3"], Int[Array, ""]] | None:
        """The smoothed object poses of the component :meth:`trajectory` belongs to (every slot,
        indexed like its classes) and how many of the slots hold an object (the first ones);
        ``None`` for filters. The result file's optional ``objects`` (SCENARIO_FORMAT.md)."""
        return None

    def loop_closure_access(self) -> LoopClosureAccess | None:
        """What loop closure during the run (:class:`~.loops.online.OnlineLoopClosure`) reads and
        writes of this estimator's state; ``None``: the estimator has none."""
        return None

    def describe(self, scenario: Scenario | None = None) -> str:
        """The result file's ``estimator`` text: name, paper, every setting (the classifier the
        ``scenario`` names where the estimator does not override it), each as its field's
        metadata says (:func:`.options.setting`), the clutter density as the ``scenario`` resolves it."""
        parts = [f"classifier={classifier_name(getattr(self, 'classifier', None), scenario)}"]
        for name, write in shown(self, self.described):
            if name == "clutter":
                setting = getattr(self, "clutter") if scenario is None else self._clutter(scenario)
                text = clutter_text(setting, scenario)
                text = text.removeprefix(", ")
            else:
                text = write(self) if write is not None else f"{name}={value_text(getattr(self, name))}"
            if text:
                parts.append(text)
        return f"hybridslam {__version__} {self.title} ({self.reference}); " + ", ".join(parts)

    def _clutter(self, scenario: Scenario) -> float | None:
        """The clutter log density used on ``scenario`` (``None``: no clutter hypothesis)."""
        return resolve_clutter(getattr(self, "clutter", None), scenario)

    def settings(self) -> dict[str, Any]:
        """Every setting as JSON-able values (what a study's records depend on)."""
        return {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name != "batch_axis"}

    def with_batch_axis(self, axis_name: str | None) -> AbstractEstimator:
        """This estimator under an enclosing ``jax.vmap`` named ``axis_name`` (studies batch tracks
        that way); estimators that skip dead slots use the name to skip them in every track at once."""
        return self


class MergedComponent(NamedTuple):
    """A component that loop closure during the run (:class:`~.loops.online.OnlineLoopClosure`) adds,
    in its own object numbering: its association history ``(T, Dmax)``, class realizations
    ``(Nmax,)`` (-1 open), objects in use, trajectory ``(T+1, 3)``, marginal mean ``(D,)`` and
    covariance ``(D, D)`` of ``[x_k, objects]``, and per object in use the parent component's
    objects it joins (one: kept or split off; more: merged)."""

    history: np.ndarray
    classes: np.ndarray
    num: int
    poses: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    sources: tuple[tuple[int, ...], ...]


class LoopClosureAccess(abc.ABC):
    """What loop closure during the run (:class:`~.loops.online.OnlineLoopClosure`) needs of one
    estimator's state beyond the fields every mixture state here has; an estimator gives it through
    :meth:`AbstractEstimator.loop_closure_access`."""

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
