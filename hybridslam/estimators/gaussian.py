"""What the single-Gaussian association strategies (``ml``, ``gpda``, ``max-mixture``) share.

All three are filters over one joint Gaussian ``[x_k, o_0, ..., o_{Nmax-1}]`` (``D = 3 + 3 Nmax``):
propagate it through the motion model, compute the step's association probabilities from it, then
update it by Gauss-Newton with the propagated Gaussian as a prior factor. They differ only in how
the probabilities shape the measurement factors (:mod:`.ml`, :mod:`.gpda`, :mod:`.maxmix`).

Association (:func:`associate`), thesis Sec. 3.2-3.3 and 4.2:

* **Gating** (Sec. 3.2.1): per detection, the Mahalanobis distance of its range-bearing innovation
  against every created object, ``d² = rᵀ S⁻¹ r`` with ``S = H Σ Hᵀ + Γ`` (Eq. 4.15); the ``G``
  nearest objects inside the chi-square gate (2 degrees of freedom) are its candidates.
* **Null hypothesis**: with a ``discovery`` section a detection may also be a new object (Sec. 3.2.1,
  the summary's Eq. 13), of log density ``new_object_log_density`` times the semantic evidence under
  the class prior. The ``i``-th new detection of an assignment (slot order) creates slot
  ``num_created + i``; beyond the capacity ``Nmax`` it is an *unmapped* object: weighed the same,
  not stored, its detection unassociated (``StepInfo.unmapped``). Without discovery a null entry
  is always a skip.
* **Clutter** (a known map with a clutter density: the ``clutter`` setting, by default the
  scenario's ``sensor.clutter_log_density``): the null entry is a spurious detection of log density
  ``clutter_log_density`` over ``[range, bearing]`` (prior probability of clutter included) times
  the semantic evidence under a uniform class prior, as the hybrid belief's clutter hypothesis;
  every assignment then competes (no skip), and a detection whose null entry is chosen is an
  outlier (``StepInfo.rejected``). On an unknown map the null entry is a new object and the file's
  clutter density is not used (a first detection of a new object and a spurious one have the same
  constant density in one step).
* **Joint assignments**: every injective assignment of the occupied detection slots to their
  candidates or the null option, enumerated once in numpy (``(G+1)^Dmax`` rows, invalid ones masked).
  An assignment's log weight is the joint linearized marginal likelihood of its associated
  detections (Eq. 4.14-4.15, all of them at once: the shared robot pose correlates them, which is
  joint compatibility), times each one's semantic term ``Σ_c P(z^s | c) P(c | Z⁻)`` (Eq. 4.13 with
  Eq. 2.14), times the null terms. Only the assignments that skip the fewest detections compete
  (a skip, on a known map, is a last resort: an empty gate, two detections of one object).
  Normalized by logsumexp they are ``P(d_k | Z⁻)``; per-detection marginals are their sums.

The semantic likelihood enters the association weights and the class posteriors only; the
Gauss-Newton factors are geometric (Doherty's factorization, Eq. 4.13: with classes marginalized,
the semantic term is a scalar per association). Viewpoint-dependent models are evaluated at the
propagated mean (a new object's viewpoint at its back-projected position, orientation 0).
Classifier models enter only through ``ClassifierModel.residuals``, so ``mirror``, ``none`` and
``confusion`` all work.

Class posteriors (Eq. 4.17 with Eq. 2.14): per object, normalized ``log P(c | Z)``; a detection
associated to object ``n`` with probability ``p`` multiplies it by ``p P(z^s|c) / P(z^s) + (1 − p)``.
Prior objects start from the scenario's class prior, new ones from a uniform prior.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import optimistix as optx
from jax.scipy.special import logsumexp
from jaxtyping import Array, Bool, Float, Int

from ..inference import discovery, gating, sequential
from ..inference.beam import beam_search
from ..inference.gating import chi2_gate
from ..inference.update import prior_gauss_newton, support_of, wrap_angles
from ..models.scenario import Scenario
from ..models import geometry
from ..models.measurement import Detections
from ..models.model import Model, model_from_scenario
from ..models.motion import propagate
from ..models.classifier import ClassifierModel
from . import novelty
from .base import (CLUTTER_FROM_FILE, AbstractEstimator, Mixture, StepInfo, check_clutter, detection_slots,
                   history_length, lacks_object_slots, object_slots, resolve_clutter)
from .options import GATE, GATE_PROBABILITY, MAX_CHILDREN, setting
from .smoothers.kinds import Full, Smoother, SmootherState, check_smoother
from .smoothers.factors import Factors, active_history, new_overflow

_LOG_2PI = math.log(2.0 * math.pi)


@dataclasses.dataclass(frozen=True)
class Structure:
    """What the scenario and the settings fix about a state's code path (static)."""

    discovery: bool  # the null hypothesis creates objects (scenario has a "discovery" section)
    num_candidates: int  # G, at most the object capacity
    clutter: bool = False  # a known map's null hypothesis is clutter (Params.clutter_log_density)


class Params(eqx.Module):
    """Traced association parameters (changing them never recompiles)."""

    gate: Float[Array, ""]  # chi-square threshold on d² (2 degrees of freedom)
    new_object_log_density: Float[Array, ""]
    new_object_orientation_var: Float[Array, ""]
    new_class_log_prior: Float[Array, " M"]  # uniform: a new object's class prior
    clutter_log_density: Float[Array, ""]  # -inf without a clutter hypothesis
    new_landmark_tau: Float[Array, ""]  # τ of new_landmark="mahalanobis:TAU" (inf: the "density" rule)


class GaussianState(eqx.Module):
    """The belief of a single-Gaussian estimator after ``k`` steps."""

    mean: Float[Array, " D"]  # [x_k, o_0, ..., o_{Nmax-1}]; uncreated slots: mean 0, cov I
    cov: Float[Array, "D D"]
    num_created: Int[Array, ""]  # prior objects plus discovered ones
    class_log_post: Float[Array, "Nmax M"]  # normalized log P(c_n | Z) (Eq. 4.17)
    observed: Bool[Array, " Nmax"]  # some detection has been assigned to the object
    history: Int[Array, "T Dmax"]  # assigned object of each detection, -1 = empty slot
    k: Int[Array, ""]
    model: Model
    params: Params
    structure: Structure = eqx.field(static=True)
    # What the smoother keeps (smoother=Full() or Lag(L)): the trajectory x_0..x_T, the data so far,
    # the measurement factors, with Lag(L) the window's prior; empty under Filter().
    smoothing: SmootherState = SmootherState()

    @property
    def max_objects(self) -> int:
        return self.class_log_post.shape[0]


class GaussianDetails(eqx.Module):
    """The single-Gaussian estimators' own diagnostics of one step (``StepInfo.details``)."""

    num_created: Int[Array, ""]
    solver_result: optx.RESULTS


class Association(eqx.Module):
    """The step's association hypotheses (see the module docstring)."""

    candidates: Int[Array, "Dmax G"]  # object of each candidate (nearest first)
    candidate_ok: Bool[Array, "Dmax G"]  # created, inside the gate, detection present
    options: Int[Array, "R Dmax"]  # candidate index per slot, G = null (static table)
    log_prob: Float[Array, " R"]  # log P(d_k | Z⁻); -inf for invalid rows
    new: Bool[Array, "R Dmax"]  # the slot's null entry creates an object
    unmapped: Bool[Array, "R Dmax"]  # ... is a new object with no free slot (weighed, not stored)
    skip: Bool[Array, "R Dmax"]  # the slot's null entry leaves the detection unassociated (known map)
    clutter: Bool[Array, "R Dmax"]  # ... explains the detection as clutter (known map with a clutter density)
    marginals: Float[Array, "Dmax G1"]  # P(d_k^j = candidate g), last column the null option
    class_loglik: Float[Array, "Dmax Nmax M"]  # log P(z^s_j | c) seen from each object
    new_class_loglik: Float[Array, "Dmax M"]  # ... from the object the detection would create
    dropped: Int[Array, ""]  # assignments the beam dropped within its margin of the best (0 if exhaustive)
    candidate_cov: Float[Array, "Dmax G 2 2"]  # innovation covariance S_g of each candidate (Eq. 4.15)

    @property
    def num_candidates(self) -> int:
        return self.candidates.shape[1]


# --------------------------------------------------------------------------- #
# Init and view
# --------------------------------------------------------------------------- #


class SingleGaussian(AbstractEstimator):
    """What ``ml``, ``gpda`` and ``max-mixture`` share: one joint Gaussian, gated joint association.

    Settings: ``candidates`` (``G``, objects per detection after gating), ``gate_probability`` (of
    the chi-square gate on the innovation's Mahalanobis distance), ``max_hypotheses`` (joint
    assignments kept while they are built one detection at a time, :func:`associate`; ``None``
    enumerates all ``(G+1)^D``, exponential in the detections ``D``), ``gn_max_steps`` (Gauss-Newton
    budget of the update), ``classifier`` (a model name or object replacing the scenario's),
    ``max_detections`` (detection slots per step; ``None``: the scenario's largest step), ``max_steps``
    (the history length; ``None``: the scenario's steps), ``smoother`` (:class:`~.smoothers.kinds.Full`,
    the default: the whole trajectory relinearized at every step, associations decided online;
    :class:`~.smoothers.kinds.Lag`: the last ``L`` steps, older poses marginalized;
    :class:`~.smoothers.kinds.Filter`: the joint Gaussian over ``[x_k, objects]`` only), ``clutter``
    (a known map's clutter log density over ``[range, bearing]``; ``"file"``, the default: the
    scenario's ``sensor.clutter_log_density``, none without it; ``None`` or ``"none"``: none), ``new_landmark``
    (an unknown map's rule for a new object: ``"density"``, the default, or ``"mahalanobis:TAU"``,
    thesis Sec. 3.2.1; :mod:`.novelty`).
    """

    candidates: int = eqx.field(default=3, static=True, metadata=setting(GATE))
    gate_probability: float = eqx.field(default=0.999, static=True, metadata=setting(GATE_PROBABILITY))
    max_hypotheses: int | None = eqx.field(default=64, static=True,
                                           metadata=setting(MAX_CHILDREN, note="joint assignments, default {default}"))
    gn_max_steps: int = eqx.field(default=20, static=True)
    smoother: Smoother = Full()
    classifier: str | ClassifierModel | None = None
    max_detections: int | None = eqx.field(default=None, static=True)
    max_steps: int | None = eqx.field(default=None, static=True)
    clutter: float | str | None = eqx.field(default=CLUTTER_FROM_FILE, static=True,
                                            metadata=setting(note="a known map only"))
    new_landmark: str = eqx.field(default=novelty.DENSITY, static=True)

    init_settings = ("gate_probability", "clutter", "new_landmark", "classifier")
    described = ("candidates", "gate_probability", "gn_max_steps", "max_hypotheses", "smoother", "clutter",
                 "new_landmark")
    factor_mode: ClassVar[Literal["sum", "max"]] = "sum"  # how the smoother reads a detection's candidates (max-mixtures: "max")

    def __check_init__(self):
        check_smoother(type(self).__name__, self.smoother)
        if self.max_hypotheses is not None and not (isinstance(self.max_hypotheses, int) and self.max_hypotheses >= 1):
            raise ValueError(f"{type(self).__name__}.max_hypotheses: expected a positive int or None, "
                             f"got {self.max_hypotheses!r}")
        for name in ("candidates", "gn_max_steps"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"{type(self).__name__}.{name}: expected a positive int, got {value!r}")
        chi2_gate(self.gate_probability)
        check_clutter(type(self).__name__, self.clutter)
        novelty.parse_new_landmark(type(self).__name__, self.new_landmark)
        if self.max_detections is not None and not (isinstance(self.max_detections, int) and self.max_detections >= 1):
            raise ValueError(f"{type(self).__name__}.max_detections: expected a positive int or None, "
                             f"got {self.max_detections!r}")

    def init(self, scenario: Scenario) -> GaussianState:
        """The belief before step 1: the priors of the scenario's objects, then uncreated slots."""
        disc = scenario.discovery
        n, m = scenario.num_objects, scenario.num_classes
        n_max = object_slots(scenario)
        slots = detection_slots(self.max_detections, scenario)
        clutter = self._clutter(scenario)
        model = model_from_scenario(scenario.replace(discovery=None), self.classifier)
        uniform = np.full(m, -math.log(m))
        class_log_post = np.tile(uniform, (n_max, 1))
        class_log_post[:n] = np.log(scenario.class_prior)
        # One class prior row per slot, so the state's shapes depend on the capacity alone.
        model = eqx.tree_at(lambda mod: mod.class_prior, model, jax.device_put(np.exp(class_log_post)))
        dim = 3 + 3 * n_max
        mean = np.zeros(dim)
        cov = np.eye(dim)
        mean[:3], cov[:3, :3] = scenario.robot_prior_mean, scenario.robot_prior_cov
        for i in range(n):  # host-side, once
            mean[3 + 3 * i : 6 + 3 * i] = scenario.object_prior_means[i]
            cov[3 + 3 * i : 6 + 3 * i, 3 + 3 * i : 6 + 3 * i] = scenario.object_prior_covs[i]
        put = jax.device_put  # numpy to the device without a compile (eager jnp ops compile one each)
        f = lambda a: put(np.asarray(a, dtype=float))  # noqa: E731
        params = Params(
            gate=f(chi2_gate(self.gate_probability)),
            new_object_log_density=f(0.0 if disc is None else disc.new_object_log_density),
            new_object_orientation_var=f(1.0 if disc is None else disc.new_object_orientation_var),
            new_class_log_prior=f(uniform),
            clutter_log_density=f(-np.inf if clutter is None else clutter),
            new_landmark_tau=f(novelty.threshold(type(self).__name__, self.new_landmark)),
        )
        steps = history_length(self.max_steps, scenario)
        g = min(self.candidates, n_max)
        state = GaussianState(
            mean=f(mean), cov=f(cov), num_created=put(np.asarray(n, dtype=np.int32)),
            class_log_post=f(class_log_post), observed=put(np.zeros(n_max, dtype=bool)),
            history=put(np.full((steps, slots), -1, dtype=np.int32)),
            k=put(np.zeros((), dtype=np.int32)), model=model, params=params,
            structure=Structure(disc is not None, g, clutter is not None),
        )
        if not self.smoother.smooths:
            return state
        none = Factors(put(np.zeros((steps, slots, g), np.int32)), put(np.full((steps, slots, g), -np.inf)),
                       put(np.full((steps, slots), -np.inf)), put(np.zeros((steps, slots, g), np.int32)))
        smoothing = self.smoother.init(scenario, steps, slots, n_max, self.max_steps)
        return dataclasses.replace(state, smoothing=dataclasses.replace(smoothing, factors=none))

    def _clutter(self, scenario: Scenario) -> float | None:
        """The clutter log density used on ``scenario`` (a known map's only; ``None``: none)."""
        if self.clutter == CLUTTER_FROM_FILE and scenario.discovery is not None:
            return None  # an unknown map's null hypothesis is a new object
        clutter = resolve_clutter(self.clutter, scenario)
        if clutter is not None and scenario.discovery is not None:
            raise ValueError(f"{self.name}: clutter is for a known map; on an unknown map (a discovery section) a "
                             "detection of no known object creates one (the null hypothesis, thesis Sec. 3.2.1)")
        return clutter

    def trajectory(self, state: GaussianState):
        """The smoothed ``x_0..x_T`` (``None`` without smoothing)."""
        return state.smoothing.trajectory()

    def objects(self, state: GaussianState):
        """The smoothed objects and how many exist (``None`` without smoothing)."""
        return None if not state.smoothing.smooths else (state.mean[3:].reshape(-1, 3), state.num_created)

    def view(self, state: GaussianState) -> Mixture:
        """A one-component :class:`~.base.Mixture` (classes: MAP of Eq. 4.17, -1 if unobserved)."""
        classes = jnp.where(state.observed, jnp.argmax(state.class_log_post, axis=-1), -1).astype(jnp.int32)
        return Mixture(
            log_weights=jnp.zeros(1, state.mean.dtype), mean=state.mean[None, :3], cov=state.cov[None, :3, :3],
            classes=classes[None], history=state.history[None], k=state.k,
        )


# --------------------------------------------------------------------------- #
# Association probabilities
# --------------------------------------------------------------------------- #


def _objects(mean: Float[Array, " D"]) -> Float[Array, "Nmax 3"]:
    return mean[3:].reshape(-1, 3)


def _class_loglik(classifier, scores, x, obj):
    """``log P(z^s | c, viewpoint)`` for every class (Eq. 2 / Eq. 2.14)."""
    r, log_norm = classifier.residuals(scores, geometry.viewpoint(x, obj))
    return log_norm - 0.5 * jnp.sum(r**2, axis=-1)


def _joint_log_likelihood(obj, used, inn: gating.Innovations, cov, geometric_cov):
    """Joint linearized ``log p(z_used | d, Z⁻)`` (Eq. 4.14-4.15 stacked over the used slots).

    ``S = H Σ Hᵀ + I⊗Γ`` over ``[x_k, o_{obj_1}, ..., o_{obj_Dmax}]``; unused slots are masked to
    unit rows and contribute nothing.
    """
    dmax = obj.shape[0]
    slots = jnp.arange(dmax)
    r = jnp.where(used[:, None], inn.residual[slots, obj], 0.0).reshape(-1)
    h_x, h_o = inn.jac_pose[obj], inn.jac_object[obj]  # (Dmax, 2, 3)
    h_o = (h_o[:, :, None, :] * jnp.eye(dmax, dtype=cov.dtype)[:, None, :, None]).reshape(dmax, 2, 3 * dmax)
    h = jnp.concatenate([h_x, h_o], axis=-1).reshape(2 * dmax, 3 + 3 * dmax)
    idx = jnp.concatenate([jnp.arange(3), (3 + 3 * obj[:, None] + jnp.arange(3)[None, :]).reshape(-1)])
    s = h @ cov[idx][:, idx] @ h.T + jnp.kron(jnp.eye(dmax, dtype=cov.dtype), geometric_cov)
    rows = jnp.repeat(used, 2)
    s = jnp.where(rows[:, None] & rows[None, :], s, jnp.eye(2 * dmax, dtype=cov.dtype))
    chol = jnp.linalg.cholesky(s)
    white = jsl.solve_triangular(chol, r, lower=True)
    log_det = jnp.sum(jnp.log(jnp.diagonal(chol)))  # ½ log|S|; the unit rows add 0
    return -0.5 * jnp.sum(white**2) - log_det - jnp.sum(used) * _LOG_2PI


def associate(state: GaussianState, mean: Float[Array, " D"], cov: Float[Array, "D D"],
              detections: Detections, width: int | None = None) -> Association:
    """Gating, joint assignment probabilities and per-detection marginals at the propagated belief.

    ``width``: the joint assignments are built one detection at a time keeping the ``width`` best
    (:func:`hybridslam.inference.beam.beam_search`: linear in the detections, exact while at most
    ``width`` partial assignments are valid); ``None`` enumerates all ``(G+1)^Dmax`` (the reference).
    """
    cfg, params, sensor = state.structure, state.params, state.model.sensor
    n_max, g = state.max_objects, cfg.num_candidates
    dmax = detections.mask.shape[0]
    x, objs = mean[:3], _objects(mean)
    gamma = sensor.geometric_cov

    # Per (detection, object): innovation, Jacobians, Mahalanobis distance (gating, Sec. 3.2.1).
    inn = gating.innovations(sensor, mean, cov, detections)
    candidates, d2 = gating.nearest(inn.d2, state.num_created, g)
    candidate_ok = (d2 <= params.gate) & detections.mask[:, None]
    # The thesis's new-landmark rule (Sec. 3.2.1, .novelty): candidates within τ only, and "new" only
    # where none is (the nearest G hold the nearest object, so none inside the G means none at all).
    # (τ traced, inf under the density rule: novelty.threshold.)
    near = jnp.zeros(dmax, bool)
    if cfg.discovery:
        candidate_ok &= novelty.allowed(d2, params.new_landmark_tau)
        near = novelty.known_within(jnp.where(candidate_ok, d2, jnp.inf), None, params.new_landmark_tau)

    # Semantic terms (Eq. 4.13 / 2.14): per object, and under the null hypothesis.
    classifier = sensor.classifier
    per_class = jax.vmap(jax.vmap(_class_loglik, (None, None, None, 0)), (None, 0, None, None))
    class_loglik = per_class(classifier, detections.scores, x, objs)  # (Dmax, Nmax, M)
    new_pos = jax.vmap(discovery.back_project, (None, 0))(x, detections.geo)
    new_objs = jnp.concatenate([new_pos, jnp.zeros((dmax, 1), mean.dtype)], axis=-1)
    new_class_loglik = jax.vmap(_class_loglik, (None, 0, None, 0))(classifier, detections.scores, x, new_objs)
    sem = logsumexp(state.class_log_post[None] + class_loglik, axis=-1)  # (Dmax, Nmax)
    slots = jnp.arange(dmax)
    sem_cand = sem[slots[:, None], candidates]  # (Dmax, G)
    uniform_sem = logsumexp(params.new_class_log_prior[None] + new_class_loglik, axis=-1)  # (Dmax,)
    # The null entry's log weight: a new object's (unknown map) or a clutter detection's (known map).
    null_w = (params.new_object_log_density if cfg.discovery else params.clutter_log_density) + uniform_sem

    def flags(opts, upto):
        """Validity, objects and new / unmapped / skipped slots of the assignment ``opts`` of slots ``0..upto``."""
        occupied = detections.mask & (slots <= upto)
        used = occupied & (opts < g)
        pick = jnp.minimum(opts, g - 1)
        obj = candidates[slots, pick]
        ok = jnp.all(jnp.where(used, candidate_ok[slots, pick], occupied | (opts == g)))
        twice = (obj[:, None] == obj[None, :]) & used[:, None] & used[None, :] & ~jnp.eye(dmax, dtype=bool)
        ok &= ~jnp.any(twice)
        null = occupied & (opts == g)
        none = jnp.zeros_like(null)
        if not cfg.discovery:  # known map: the null entry is clutter, or (without a clutter density) a skip
            return (ok, used, pick, obj, none, none, none, null) if cfg.clutter else (ok, used, pick, obj, none, none, null, none)
        new = null & (state.num_created + jnp.cumsum(null) - 1 < n_max)
        return ok, used, pick, obj, new, null & ~new, none, none

    if width is None:  # every joint assignment: the exhaustive reference, (G+1)^Dmax rows
        def row(opts):
            ok, used, pick, obj, new, unmapped, skip, clutter = flags(opts, dmax - 1)
            log_w = (_joint_log_likelihood(obj, used, inn, cov, gamma) + jnp.sum(jnp.where(used, sem_cand[slots, pick], 0.0))
                     + jnp.sum(jnp.where(new | unmapped | clutter, null_w, 0.0)))
            return ok, new, unmapped, skip, clutter, log_w

        options = jnp.asarray(gating.joint_options(g, dmax))
        dropped = jnp.zeros((), jnp.int32)
        ok, new, unmapped, skip, clutter, log_w = jax.vmap(row)(options)
    else:  # built one detection at a time, `width` kept (inference.beam); skips rank last
        def score(opts, upto, partial_row, parent):
            """The joint log weight, one detection's term at a time (inference.sequential)."""
            ok, used, pick, obj, new, unmapped, skip, clutter = flags(opts, upto)
            term = jnp.where(used[upto],
                             sequential.innovation_log_density(inn, partial_row, upto, obj[upto]) + sem_cand[upto, pick[upto]],
                             jnp.where(new[upto] | unmapped[upto] | clutter[upto], null_w[upto], 0.0))
            # A new object where a known one lies within τ breaks the Mahalanobis rule: ranked with
            # the skips, so only the assignments that break it fewest compete (never none at all).
            return jnp.where(ok, parent + term, -jnp.inf), jnp.sum(skip) + jnp.sum((new | unmapped) & near)

        def advance(partial_row, opts, upto):
            _, used, _, obj, *_ = flags(opts, upto)
            return sequential.condition(inn, cov, partial_row, upto, obj[upto], used[upto])

        found = beam_search(score, dmax, g + 1, width, fill=g, carry=sequential.start(width, mean.shape[0], dmax, mean.dtype),
                            advance=advance, stop=detections.span())
        options, dropped = found.options, found.dropped
        ok, _, _, _, new, unmapped, skip, clutter = jax.vmap(flags, (0, None))(options, dmax - 1)
        ok &= found.valid  # a row the beam did not fill is no hypothesis (it may repeat another)
        log_w = found.score
    num_skip = jnp.sum(skip, axis=-1) + jnp.sum((new | unmapped) & near[None], axis=-1)  # rule breaks rank as skips
    ok &= num_skip == jnp.min(jnp.where(ok, num_skip, dmax + 1))  # the all-null row is always ok
    log_w = jnp.where(ok, log_w, -jnp.inf)
    log_prob = log_w - logsumexp(log_w)
    onehot = options[:, :, None] == jnp.arange(g + 1)[None, None, :]  # (R, Dmax, G+1)
    marginals = jnp.einsum("r,rdo->do", jnp.exp(log_prob), onehot.astype(mean.dtype))
    return Association(candidates, candidate_ok, options, log_prob, new, unmapped, skip, clutter, marginals,
                       class_loglik, new_class_loglik, dropped, inn.cov[candidates])


# --------------------------------------------------------------------------- #
# Pieces of a step
# --------------------------------------------------------------------------- #


def predict(state: GaussianState, odometry: Float[Array, "3"]) -> tuple[Float[Array, " D"], Float[Array, "D D"]]:
    """Propagate the joint Gaussian through the motion model (thesis Eq. 2.3; the paper's Eq. 11)."""
    return propagate(state.mean, state.cov, odometry, state.model.motion_cov)


def new_slots(state: GaussianState, new: Bool[Array, " Dmax"]) -> Int[Array, " Dmax"]:
    """The slot each new detection creates (slot order), -1 elsewhere."""
    return jnp.where(new, state.num_created + jnp.cumsum(new) - 1, -1)


def fits(state: GaussianState, new: Bool[Array, " Dmax"]) -> Bool[Array, " Dmax"]:
    """``new`` without the detections that would exceed the capacity of object slots."""
    return new & (state.num_created + jnp.cumsum(new) - 1 < state.max_objects)


def create_objects(state: GaussianState, mean, cov, slots: Int[Array, " Dmax"], detections: Detections):
    """Initialize every slot ``slots[j] >= 0`` from detection ``j`` (:func:`hybridslam.discovery.create_objects`)."""
    return discovery.create_objects(mean, cov, slots, slots >= 0, detections.geo, state.model.sensor.geometric_cov,
                                    state.params.new_object_orientation_var)


def create_likeliest_new(state: GaussianState, mean, cov, assoc: Association, detections: Detections):
    """Create an object for every detection whose most probable option is "new" (and that fits).

    The soft strategies (``gpda``, ``max-mixture``) decide a detection's existence by its marginal
    (a new object cannot be created by a fraction). Returns the updated mean and covariance, the
    new-detection mask, the slot each creates (-1 elsewhere) and the unmapped mask (new, no free slot).
    """
    best = jnp.argmax(assoc.marginals, axis=-1)
    wants_new = detections.mask & (best == assoc.num_candidates) if state.structure.discovery \
        else jnp.zeros_like(detections.mask)
    new = fits(state, wants_new)
    created = new_slots(state, new)
    mean, cov = create_objects(state, mean, cov, created, detections)
    return mean, cov, new, created, wants_new & ~new


def geometric_residual(sensor, y, obj, geo):
    """Whitened ``W (z − h(x_k, o_obj))`` of one detection (the paper's Eq. 10, geometric part)."""
    w, _ = sensor.geometric_sqrt_information()
    return w @ geometry.geometric_residual(geo, geometry.range_bearing(y[:3], _objects(y)[obj]))


def _weighted_residuals(y, args):
    sensor, obj, geo, weight = args
    r = jax.vmap(geometric_residual, (None, None, 0, 0))(sensor, y, obj, geo)
    return (jnp.sqrt(weight)[:, None] * r).reshape(-1)


def weighted_update(state: GaussianState, mean, cov, obj: Int[Array, " F"], geo: Float[Array, "F 2"],
                    weight: Float[Array, " F"], max_steps: int):
    """Gauss-Newton with factors ``√w_f W (z_f − h(x_k, o_{obj_f}))`` (``w_f = 0``: no factor).

    ``w = 1`` is an ordinary factor (ML); fractional weights scale its information (GPDA, Eq. 3.7).
    """
    args = (state.model.sensor, jnp.maximum(obj, 0), geo, weight)
    # Kalman-form Gauss-Newton: O(D² m) per iterate, not a dense solve over the whole map.
    value, new_cov, result = prior_gauss_newton(_weighted_residuals, mean, cov, args, max_steps,
                                                support_of(obj))
    return wrap_angles(value), new_cov, result


def update_classes(state: GaussianState, assoc: Association, prob: Float[Array, "Dmax Nmax"],
                   created: Int[Array, " Dmax"]) -> Float[Array, "Nmax M"]:
    """Class posteriors after the step (Eq. 4.17 with Eq. 2.14).

    ``prob[j, n]``: the probability that detection ``j`` is of existing object ``n``; each
    multiplies ``P(c_n | Z)`` by ``p P(z^s|c)/P(z^s) + (1 − p)``. A created object ``created[j]``
    starts from the uniform prior times its detection's likelihood.
    """
    post = state.class_log_post  # (Nmax, M)
    lik = assoc.class_loglik - logsumexp(post[None] + assoc.class_loglik, axis=-1, keepdims=True)  # P(z|c)/P(z)
    p = prob[..., None]
    log_p = jnp.log(jnp.where(p > 0, p, 1.0))
    # log(1 − p), −inf at p = 1 (a certain association) through a double where: log1p's derivative
    # there is infinite, and times a zero cotangent it would make every gradient NaN.
    certain = p >= 1.0
    log_q = jnp.where(certain, -jnp.inf, jnp.log1p(-jnp.where(certain, 0.0, p)))
    factor = jnp.where(p > 0, jnp.logaddexp(log_p + lik, log_q), 0.0)
    post = post + jnp.sum(factor, axis=0)
    fresh = state.params.new_class_log_prior[None] + assoc.new_class_loglik  # (Dmax, M)
    hit = created[:, None] == jnp.arange(state.max_objects)[None, :]  # (Dmax, Nmax)
    post = jnp.where(jnp.any(hit, axis=0)[:, None], jnp.einsum("dn,dm->nm", hit.astype(post.dtype), fresh), post)
    return post - logsumexp(post, axis=-1, keepdims=True)


def commit(est: SingleGaussian, state: GaussianState, mean, cov, class_log_post, assigned: Int[Array, " Dmax"],
           used: Bool[Array, " Dmax"], detections: Detections, num_new, info: dict, odometry: Float[Array, "3"],
           factors: tuple[Int[Array, "Dmax G"], Float[Array, "Dmax G"], Float[Array, " Dmax"]],
           ) -> tuple[GaussianState, StepInfo]:
    """Write the step's results into the state (and, with ``est.smoother`` ``Full()`` or ``Lag(L)``, smooth it).

    ``assigned`` is the object of each detection; ``used`` marks the detections that really were
    associated (their objects count as observed). The history records ``assigned`` where ``used``
    and ``-1`` elsewhere: a detection left unassociated (skipped, or an outlier) is ``-1`` in a
    result file (SCENARIO_FORMAT: "-1 marks a detection that the component left unassociated"),
    not a guess at its object. ``factors``: the step's measurement
    factors for the smoother, per detection slot its candidate objects, their log weights (``-inf``:
    none) and the null component's (:class:`~.smoothers.factors.Factors`).
    """
    assigned = jnp.where(detections.mask & used, assigned, -1).astype(jnp.int32)
    hit = (assigned[:, None] == jnp.arange(state.max_objects)[None, :]) & (used & detections.mask)[:, None]
    observed = state.observed | jnp.any(hit, axis=0)
    num_created = (state.num_created + num_new).astype(jnp.int32)
    result = info["solver_result"]
    kept = state.smoothing
    if est.smoother.smooths:
        # The whole trajectory and map relinearized with every factor so far (smoothers/kinds.py); the
        # associations stay as decided online, except a max-mixture's under Full (below).
        before = kept.factors
        kept = kept.record(state.k, odometry, detections)
        assert before is not None and kept.poses is not None and kept.log is not None  # the smoother's init keeps them
        objs, log_w, null = factors
        stored = Factors(before.objects.at[state.k].set(objs.astype(jnp.int32)),
                         before.log_weight.at[state.k].set(log_w),
                         before.null_log_weight.at[state.k].set(null), before.classes)
        out = est.smoother.smooth(kept, stored, state.k + 1, num_created, state.model.sensor, state.model.motion_cov,
                                  False, est.factor_mode, mean, cov)
        mean, cov, result = out.mean, out.cov, out.result
        kept = SmootherState(out.poses, kept.log, out.window, stored)
    history = state.history.at[state.k].set(assigned)
    if est.factor_mode == "max" and est.smoother.whole_trajectory:
        # A max-mixture's associations are the components active at the solution the file reports
        # (re-chosen over the whole trajectory at every relinearization), not those chosen online.
        assert kept.log is not None and kept.factors is not None and out.active is not None
        rewritten = active_history(kept.log, kept.factors, state.k + 1, out.active, history)
        history = jnp.where(result == optx.RESULTS.nonfinite, history, rewritten)  # a failed solve: kept
    new_state = dataclasses.replace(
        state, mean=mean, cov=0.5 * (cov + cov.T), num_created=num_created, class_log_post=class_log_post,
        observed=observed, history=history, k=state.k + 1, smoothing=kept,
    )
    zero = jnp.zeros((), jnp.int32)
    skipped = info.get("skipped", zero).astype(jnp.int32)
    step_info = StepInfo(
        k=(state.k + 1).astype(jnp.int32), num_components=jnp.ones((), jnp.int32),
        skipped=skipped, rejected=info.get("rejected", zero).astype(jnp.int32),
        unmapped=info.get("unmapped", zero).astype(jnp.int32),
        # Associations pass the gate, so only skipped detections go unexplained (gating.contradicted).
        inconsistent=2 * skipped > jnp.sum(detections.mask),
        dropped_budget=info.get("dropped", zero).astype(jnp.int32),
        solver_failures=(result != optx.RESULTS.successful).astype(jnp.int32),
        log_overflow=new_overflow(state.smoothing.log, kept.log),
        # Before the step: with no free slot, a new landmark's detection is unmapped (gaussian.fits).
        object_overflow=(lacks_object_slots(detections.mask, state.num_created, state.max_objects)
                         if state.structure.discovery else jnp.zeros((), bool)),
        details=GaussianDetails(num_created, result),
    )
    return new_state, step_info
