"""Max-mixtures semantic SLAM (Doherty's thesis Ch. 4, Eq. 4.11-4.17; the summary's Eq. 13).

Association probabilities ``w_jg = P(d_j = g | Z⁻)`` from the linearized marginal likelihood
(Eq. 4.14-4.15) times the semantic term (Eq. 4.13), by :func:`.gaussian.associate`. Each detection
then contributes one max-mixture factor (Eq. 4.16)

    f_j(x_k, ℓ) = max_g  w_jg · p(z_j | x_k, ℓ_g),   g over its gated candidates and the null hypothesis,

inside Gauss-Newton: at every iterate the residual function picks the active component
``g* = argmin_g ½‖r_g(y)‖² − log w_jg − log η_g`` (``η`` the normalizer of ``p``; no gradient
through the choice, as in Olson & Agarwal's max-mixtures) and returns that component's whitened
residual. It also returns the constant ``√(2 (κ_g* − κ_min))`` with ``κ_g = −log w_jg − log η_g``:
it has no Jacobian, so it does not change the Gauss-Newton step, but it makes the solver's
objective ``½‖r‖²`` the factor's negative log (up to a constant), so the convergence test compares
like with like across a switch of component. The null component (a new object's constant density
``new_object_log_density``) contributes no residual: a detection whose null component is active at
the solution is an outlier and moves nothing (counted in ``StepInfo.rejected``). On a known map
with a clutter density (:mod:`.gaussian`, Clutter) the null component is clutter's, of that
density, in the factors of the detections whose likeliest option (association marginal) is
clutter; the others' factors are over their candidates only (see ``_step``: offered to every
detection, the null component made max-mixture drift on real data, dataset 6, robot 2: APE
0.86 m against 0.12 m on the identity-filtered file).

New objects: a detection whose most probable option is the null hypothesis creates one (initialized
from it) and gets no factor. Class estimates: Eq. 4.17, from the association probabilities (the
"component weights of the max-mixture factors"). The history records the component active at the
solution (``-1`` where the null component is: an outlier, left unassociated): with the filter, at the
step's update; with ``smoother=Full()``, every detection's at the latest smoothed trajectory (each
step rewrites the whole history, :func:`.smoothers.factors.active_history`), so the graph rebuilt from a
result file's associations has the file's trajectory as a stationary point. (With ``Lag(L)`` the
history stays as chosen online: the window's solve does not see the older factors.) Settings:
:class:`.gaussian.SingleGaussian`.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..models.measurement import Detections
from . import gaussian
from .base import StepInfo
from .gaussian import GaussianState, SingleGaussian


def component_costs(sensor, y, obj: Int[Array, " G"], geo: Float[Array, "2"], log_w: Float[Array, " G1"],
                    valid: Bool[Array, " G1"], null_log_density: Float[Array, ""]):
    """Per component of one max-mixture factor: whitened residuals ``(G, 2)``, constants ``κ`` and
    costs ``−log(w_g p(z | y, ℓ_g)) = ½‖r_g‖² + κ_g`` (``+inf`` for invalid components; the last is the null)."""
    r = jax.vmap(gaussian.geometric_residual, (None, None, 0, None))(sensor, y, obj, geo)
    _, geo_norm = sensor.geometric_sqrt_information()
    log_eta = jnp.concatenate([jnp.broadcast_to(geo_norm, obj.shape), null_log_density[None]])
    kappa = jnp.where(valid, -log_w - log_eta, 0.0)
    quad = jnp.concatenate([0.5 * jnp.sum(r**2, axis=-1), jnp.zeros(1, r.dtype)])
    return r, kappa, jnp.where(valid, quad + kappa, jnp.inf)


def max_mixture_residual(sensor, y, obj, geo, log_w, valid, null_log_density):
    """The max-mixture factor of one detection (Eq. 4.16): the active component's whitened residual
    and the constant residual of its weight; ``(3,)`` and the active component's index."""
    _, kappa, cost = component_costs(sensor, jax.lax.stop_gradient(y), obj, geo, log_w, valid, null_log_density)
    active = jnp.argmin(cost)
    live = jnp.any(valid)
    g = obj.shape[0]
    r = gaussian.geometric_residual(sensor, y, obj[jnp.minimum(active, g - 1)], geo)
    r = jnp.where(live & (active < g), r, 0.0)
    kappa_min = jnp.min(jnp.where(valid, kappa, jnp.inf))
    excess = 2.0 * (kappa[active] - jnp.where(live, kappa_min, 0.0))
    positive = excess > 0  # √ at 0 has an infinite derivative: a NaN gradient without the double where
    extra = jnp.where(positive, jnp.sqrt(jnp.where(positive, excess, 1.0)), 0.0)
    return jnp.concatenate([r, jnp.where(live, extra, 0.0)[None]]), active


def _residuals(y, args):
    sensor, obj, geo, log_w, valid, null_log_density = args
    rows, _ = jax.vmap(max_mixture_residual, (None, None, 0, 0, 0, 0, None))(
        sensor, y, obj, geo, log_w, valid, null_log_density)
    return rows.reshape(-1)


class MaxMixture(SingleGaussian):
    """Max-mixtures semantic SLAM (see the module docstring)."""

    name: ClassVar[str] = "max-mixture"
    title: ClassVar[str] = "max-mixtures semantic SLAM"
    reference: ClassVar[str] = "Doherty thesis Ch. 4, Eq. 4.16"
    factor_mode: ClassVar[Literal["sum", "max"]] = "max"

    def step(self, state: GaussianState, odometry: Float[Array, "3"], detections: Detections,
             key: jax.Array) -> tuple[GaussianState, StepInfo]:
        """One filter step; ``key`` is unused (the estimator is deterministic)."""
        return _step(self, state, odometry, detections)


def _step(est: MaxMixture, state: GaussianState, odometry, detections: Detections) -> tuple[GaussianState, StepInfo]:
    mean, cov = gaussian.predict(state, odometry)
    assoc = gaussian.associate(state, mean, cov, detections, est.max_hypotheses)
    g = assoc.num_candidates
    mean, cov, new, created, unmapped = gaussian.create_likeliest_new(state, mean, cov, assoc, detections)

    w = assoc.marginals
    # The null component: a new object's density (unknown map), or clutter's (a known map with a
    # clutter density) for the detections whose likeliest option is clutter. The association
    # marginals weigh clutter against N(z; h, S), the pose uncertainty included; inside Gauss-Newton a
    # component's cost is whitened by the sensor noise alone, so at a predicted pose a few cm off
    # every detection would pick clutter at the first iterate, pull nothing, and the track drift.
    if state.structure.clutter:
        null_ok = (jnp.argmax(w, axis=-1) == g)[:, None]
    else:
        null_ok = jnp.full((w.shape[0], 1), state.structure.discovery)
    valid = jnp.concatenate([assoc.candidate_ok, null_ok], axis=-1) & (w > 0) & ~new[:, None] & detections.mask[:, None]
    log_w = jnp.log(jnp.where(valid, w, 1.0))
    null_ld = state.params.new_object_log_density if state.structure.discovery else state.params.clutter_log_density
    args = (state.model.sensor, assoc.candidates, detections.geo, log_w, valid, null_ld)
    # The prior enters in Kalman form (update.prior_gauss_newton); the active components are
    # re-chosen at every iterate, as in Eq. 4.16.
    value, cov, result = gaussian.prior_gauss_newton(_residuals, mean, cov, args, est.gn_max_steps,
                                                     gaussian.support_of(assoc.candidates))
    mean = gaussian.wrap_angles(value)

    _, active = jax.vmap(max_mixture_residual, (None, None, 0, 0, 0, 0, None))(
        state.model.sensor, mean, assoc.candidates, detections.geo, log_w, valid, null_ld)
    live = jnp.any(valid, axis=-1)
    on_object = live & (active < g)
    slots = jnp.arange(w.shape[0])
    likeliest = jnp.argmax(jnp.where(valid[:, :g], w[:, :g], -1.0), axis=-1)
    chosen = jnp.where(on_object, jnp.minimum(active, g - 1), likeliest)
    assigned = jnp.where(new, created, assoc.candidates[slots, chosen])

    p = jnp.where(valid[:, :g], w[:, :g], 0.0)
    onehot = assoc.candidates[..., None] == jnp.arange(state.max_objects)[None, None, :]
    prob = jnp.einsum("dg,dgn->dn", p, onehot.astype(p.dtype))
    classes = gaussian.update_classes(state, assoc, prob, created)
    # A detection whose likeliest option is a new object with no free slot, and whose mode picks the
    # null component, is unmapped (not stored), not an outlier.
    unmapped = unmapped & ~on_object
    info = {"skipped": jnp.sum(detections.mask & ~live & ~new & ~unmapped), "unmapped": jnp.sum(unmapped),
            "rejected": jnp.sum(live & ~on_object & ~unmapped), "solver_result": result, "dropped": assoc.dropped}
    # The smoother's factors: the same max-mixture (candidates with their weights, and the null
    # component's weight times its density), its active component re-chosen at every iterate over the
    # whole trajectory; a detection that created its object is that object's factor.
    first = jnp.arange(g) == 0
    factor_obj = jnp.where(new[:, None], jnp.maximum(created, 0)[:, None], assoc.candidates)
    factor_w = jnp.where(new[:, None], jnp.where(first[None, :], 0.0, -jnp.inf),
                         jnp.where(valid[:, :g], log_w[:, :g], -jnp.inf))
    null = jnp.where(valid[:, g] & ~new, log_w[:, g] + null_ld, -jnp.inf)
    return gaussian.commit(est, state, mean, cov, classes, assigned, on_object | new, detections, jnp.sum(new), info,
                           odometry, (factor_obj, factor_w, null))
