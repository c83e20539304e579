"""The :class:`Multimodal` estimator: settings, ``init``, ``step`` and the view of its state."""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ...inference.ties import best_slot
from ...models.scenario import Scenario
from ...models.classifier import ClassifierModel
from ...models.measurement import Detections
from ...models.model import model_from_scenario
from .. import novelty
from ..base import (CLUTTER_FROM_FILE, AbstractEstimator, Mixture, StepInfo, check_clutter, detection_slots,
                    history_length, object_slots, resolve_clutter)
from ..options import GATE, MAX_CHILDREN, MERGE_THRESHOLD, Option, setting
from ..smoothers.kinds import Full, Smoother, check_smoother
from .state import (ASSOCIATION_PRIORS, DEFAULT_CANDIDATES, DEFAULT_MERGE_THRESHOLD, DEFAULT_SAMPLES,
                    PROPOSALS, Params, State, Structure)
from .step import _step


# --------------------------------------------------------------------------- #
# The estimator
# --------------------------------------------------------------------------- #


class Multimodal(AbstractEstimator):
    """Sum-mixture semantic SLAM (Doherty's thesis Ch. 5): see the module docstring.

    Settings: ``capacity`` (``K`` components), ``samples`` (Monte Carlo draws per child, Eq. 5.10),
    ``max_assignments`` (joint assignments kept per component while they are built one detection
    at a time, :func:`hybridslam.inference.beam.beam_search`; ``None``: all ``(G+1)^D``),
    ``candidates`` (``G`` gated objects per detection, plus the null hypothesis), ``children``
    (children that get a Gauss-Newton update; ``None``: ``2·capacity``), ``merge_threshold``
    (squared Mahalanobis distance over the whole state), ``association_prior`` (``"mc"``: thesis
    Eq. 5.11; ``"uniform"``), ``proposal`` (``"posterior"`` or ``"prior"``), ``clutter`` (a known
    map's clutter log density; module docstring), ``new_landmark`` (``"density"`` or
    ``"mahalanobis:TAU"``, thesis Sec. 3.2.1: :mod:`.novelty`), ``gn_max_steps``,
    ``classifier``, ``max_detections``, ``max_steps`` and ``smoother`` (:class:`~..smoothers.kinds.Full` by
    default: each component's trajectory relinearized at every step, the thesis's mm-iSAM in spirit;
    :class:`~..smoothers.kinds.Filter`) as in every estimator.
    """

    capacity: int = eqx.field(default=64, static=True)
    samples: int = eqx.field(default=DEFAULT_SAMPLES, static=True,
                             metadata=setting(note="per child, default {default}", show="num_samples"))
    candidates: int = eqx.field(default=DEFAULT_CANDIDATES, static=True, metadata=setting(GATE))
    children: int | None = eqx.field(default=None, static=True, metadata=setting(
        MAX_CHILDREN, note="children that get a Gauss-Newton update, default 2 x capacity",
        show=lambda e: f"children={2 * e.capacity if e.children is None else e.children}"))
    merge_threshold: float = eqx.field(default=DEFAULT_MERGE_THRESHOLD, static=True, metadata=setting(
        MERGE_THRESHOLD, show=lambda e: f"merge_threshold={e.merge_threshold}"))
    max_assignments: int | None = eqx.field(default=64, static=True, metadata=setting(show=False))
    association_prior: str = eqx.field(default="mc", static=True, metadata=setting(
        Option("association_prior", "mc (thesis Eq. 5.11) or uniform", parse=str, command_line=False)))
    proposal: str = eqx.field(default="posterior", static=True, metadata=setting(
        Option("proposal", "posterior or prior", parse=str, command_line=False)))
    gn_max_steps: int = eqx.field(default=20, static=True)
    smoother: Smoother = Full()
    classifier: str | ClassifierModel | None = None
    max_detections: int | None = eqx.field(default=None, static=True)
    max_steps: int | None = eqx.field(default=None, static=True)
    clutter: float | str | None = eqx.field(default=CLUTTER_FROM_FILE, static=True,
                                            metadata=setting(note="a known map only"))
    new_landmark: str = eqx.field(default=novelty.DENSITY, static=True)

    init_settings: ClassVar[tuple[str, ...]] = ("merge_threshold", "clutter", "new_landmark", "classifier")
    name: ClassVar[str] = "multimodal"
    title: ClassVar[str] = "multimodal sum-mixture semantic SLAM"
    reference: ClassVar[str] = "Doherty thesis Ch. 5, Eq. 5.9-5.11"

    def __check_init__(self):
        check_smoother("Multimodal", self.smoother)
        for field in ("capacity", "samples", "candidates", "gn_max_steps"):
            value = getattr(self, field)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"Multimodal.{field}: must be at least 1, got {value!r}")
        if self.max_assignments is not None and not (isinstance(self.max_assignments, int) and self.max_assignments >= 1):
            raise ValueError(f"Multimodal.max_assignments: must be at least 1 or None, got {self.max_assignments!r}")
        if self.children is not None and not (isinstance(self.children, int) and self.children >= 1):
            raise ValueError(f"Multimodal.children: must be at least 1, got {self.children!r}")
        if self.association_prior not in ASSOCIATION_PRIORS:
            raise ValueError(f"Multimodal.association_prior: must be one of {ASSOCIATION_PRIORS}, "
                             f"got {self.association_prior!r}")
        if self.proposal not in PROPOSALS:
            raise ValueError(f"Multimodal.proposal: must be one of {PROPOSALS}, got {self.proposal!r}")
        if not (isinstance(self.merge_threshold, (int, float)) and self.merge_threshold > 0):
            raise ValueError(f"Multimodal.merge_threshold: must be positive, got {self.merge_threshold!r}")
        check_clutter("Multimodal", self.clutter)
        novelty.parse_new_landmark("Multimodal", self.new_landmark)

    def _clutter(self, scenario: Scenario) -> float | None:
        """The clutter log density used on ``scenario`` (a known map's only; ``None``: none)."""
        if self.clutter == CLUTTER_FROM_FILE and scenario.discovery is not None:
            return None  # an unknown map's null hypothesis is a new object
        return resolve_clutter(self.clutter, scenario)

    def _structure(self, scenario: Scenario) -> Structure:
        n_max = object_slots(scenario)
        clutter = self._clutter(scenario)
        if clutter is not None and scenario.discovery is not None:
            raise ValueError("multimodal: --clutter is for a known map; on an unknown map (a discovery section) a "
                             "detection of no known object creates one (the null hypothesis, thesis Sec. 3.2.1)")
        slots = detection_slots(self.max_detections, scenario)
        candidates = min(self.candidates, n_max)
        assignments = (candidates + 1) ** slots if self.max_assignments is None else self.max_assignments
        children = min(2 * self.capacity if self.children is None else self.children, self.capacity * assignments)
        return Structure(self.capacity, n_max, slots, history_length(self.max_steps, scenario), self.samples, candidates, children,
                         self.gn_max_steps, scenario.discovery is not None, self.association_prior, self.proposal,
                         self.max_assignments, clutter is not None)

    def init(self, scenario: Scenario) -> State:
        """One component of weight 1: the robot and object priors, uncreated slots ``N(0, I)`` (Eq. 3)."""
        cfg = self._structure(scenario)
        model = model_from_scenario(scenario.replace(discovery=None), self.classifier)
        n, n_max, m = scenario.num_objects, cfg.max_objects, scenario.num_classes
        dim = 3 + 3 * n_max
        mean = np.zeros(dim)
        mean[:3] = scenario.robot_prior_mean
        mean[3:3 + 3 * n] = np.asarray(scenario.object_prior_means).reshape(-1)
        cov = np.eye(dim)
        cov[:3, :3] = scenario.robot_prior_cov
        for i in range(n):  # once, at init
            cov[3 + 3 * i:6 + 3 * i, 3 + 3 * i:6 + 3 * i] = scenario.object_prior_covs[i]
        class_lp = np.full((n_max, m), -math.log(m))
        with np.errstate(divide="ignore"):
            class_lp[:n] = np.log(scenario.class_prior)
        disc = scenario.discovery
        put = jax.device_put  # numpy to the device without a compile (eager jnp ops compile one each)
        f = lambda a: put(np.asarray(a, dtype=float))  # noqa: E731
        params = Params(
            f(disc.new_object_log_density if disc else -np.inf),
            f(disc.new_object_orientation_var if disc else 1.0),
            f(float(self.merge_threshold)),
            f(-np.inf if (clutter := self._clutter(scenario)) is None else clutter),
            f(novelty.threshold("Multimodal", self.new_landmark)),
        )
        # The class prior padded to Nmax rows: runs with the same capacities share one compiled step.
        model = eqx.tree_at(lambda mo: mo.class_prior, model, put(np.exp(class_lp)))
        k = cfg.capacity
        return State(
            log_weights=put(np.concatenate([[0.0], np.full(k - 1, -np.inf)])),
            mean=put(np.broadcast_to(mean, (k, dim))),
            cov=put(np.broadcast_to(cov, (k, dim, dim))),
            class_log_probs=put(np.broadcast_to(class_lp, (k, n_max, m))),
            observed=put(np.zeros((k, n_max), dtype=bool)),
            num_created=put(np.full((k,), n, dtype=np.int32)),
            history=put(np.full((k, cfg.max_steps, cfg.max_detections), -1, dtype=np.int32)),
            k=put(np.zeros((), dtype=np.int32)),
            model=model,
            params=params,
            config=cfg,
            smoothing=self.smoother.init(scenario, cfg.max_steps, cfg.max_detections, n_max, self.max_steps, k),
        )

    def trajectory(self, state: State):
        """The smoothed ``x_0..x_T`` of the best component (``None`` without smoothing)."""
        return state.smoothing.trajectory(best_slot(state.log_weights)) if state.smoothing.smooths else None

    def objects(self, state: State):
        """The best component's smoothed objects and their count (``None`` without smoothing)."""
        if not state.smoothing.smooths:
            return None
        best = best_slot(state.log_weights)
        return state.mean[best, 3:].reshape(-1, 3), state.num_created[best]

    def loop_closure_access(self):
        """The state's fields for loop closure during the run (:mod:`.loops`)."""
        from .loops import MultimodalLoopAccess

        return MultimodalLoopAccess(self.gn_max_steps)

    def step(self, state: State, odometry: Float[Array, "3"], detections: Detections,
             key: jax.Array) -> tuple[State, StepInfo]:
        """Propagate (Eq. 5.7's odometry factor), weigh the (component, joint assignment) children by
        Eq. 5.9-5.11, update them and merge them back to ``K`` components."""
        return _step(state, odometry, detections, key, self.smoother)

    def view(self, state: State) -> Mixture:
        """The robot-pose mixture, per-component argmax classes of associated objects (else -1), histories."""
        classes = jnp.where(state.observed, jnp.argmax(state.class_log_probs, axis=-1), -1).astype(jnp.int32)
        # Kept in the state, but a weight that underflows to 0 is no component of the reported belief.
        log_w = jnp.where(jnp.exp(state.log_weights) > 0, state.log_weights, -jnp.inf)
        return Mixture(log_w, state.mean[:, :3], state.cov[:, :3, :3], classes, state.history, state.k)

