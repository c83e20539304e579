"""Gaussian probabilistic data association (Doherty's thesis Sec. 3.4, Eq. 3.7).

One EM iteration (the thesis's footnote to Sec. 5.4 and Table 4.1: association probabilities
computed once, proactively): with the per-detection marginals ``p_jg = P(d_j = g | Z⁻)`` of
:func:`.gaussian.associate`, the update maximizes ``E_d[log p(X, L | Z, d)] =
Σ_j Σ_g p_jg log p(z_j | x_k, ℓ_g) + prior`` — one Gauss-Newton solve in which every (detection,
candidate) factor's whitened residual is scaled by ``√p_jg`` (its information by ``p_jg``). The
result is one Gaussian between the modes of the association hypotheses, nearer the likelier ones.

Null hypothesis: a detection whose most probable option is "new object" creates one (initialized
from it, :func:`hybridslam.discovery.create_object`) and adds no other factor; otherwise its null
mass simply drops out (a constant in the expected log-likelihood). The history records each
detection's most probable object (``-1`` for a detection no candidate is compatible with).

Clutter (a known map with a clutter density, :mod:`.gaussian`): a detection whose most probable
option is clutter is an outlier (Sec. 3.2.1's gating rule, as the null hypothesis decides a new
object; ``StepInfo.rejected``) and adds no factor; the others' clutter mass ``β₀`` shrinks their
candidates' pull as in the probabilistic data association filter (:func:`clutter_weights`; without
clutter the weights are Eq. 3.7's ``p_jg``). Settings: :class:`.gaussian.SingleGaussian`.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..models.measurement import Detections
from . import gaussian
from .base import StepInfo
from .gaussian import GaussianState, SingleGaussian


class GPDA(SingleGaussian):
    """Gaussian PDA, one EM iteration (see the module docstring)."""

    name: ClassVar[str] = "gpda"
    title: ClassVar[str] = "Gaussian PDA, one EM iteration"
    reference: ClassVar[str] = "Doherty thesis Sec. 3.4, Eq. 3.7"

    def step(self, state: GaussianState, odometry: Float[Array, "3"], detections: Detections,
             key: jax.Array) -> tuple[GaussianState, StepInfo]:
        """One filter step; ``key`` is unused (the estimator is deterministic)."""
        return _step(self, state, odometry, detections)


def clutter_weights(p: Float[Array, "Dmax G"], clutter: Float[Array, " Dmax"],
                    spread: Float[Array, "Dmax G"]) -> Float[Array, "Dmax G"]:
    """The factor weights of a detection with clutter mass ``β₀ = clutter`` (PDA, Bar-Shalom & Tse).

    Eq. 3.7 gives candidate ``g`` the information ``p_g Γ⁻¹``; with clutter in the association,
    ``Σ_g p_g = 1 − β₀`` and that factor, whitened by the sensor noise alone while ``p_g`` was
    weighed under the innovation covariance ``S_g = H P⁻ Hᵀ + Γ`` (Eq. 4.15), moves the mean
    nearly all the way to the candidate whenever ``P⁻`` is broad: a 16% association pulled the
    pose as a certain one would (dataset 7, robot 1). The probabilistic data association filter the
    thesis's PDA stems from (its ref. [3]) moves it by ``(1 − β₀) K ν`` and keeps ``β₀`` of the
    prior covariance. For one candidate and a linear model a factor of noise ``Γ + β₀/(1 − β₀) S``
    does exactly that (gain ``P Hᵀ (S/(1−β₀))⁻¹``: the PDA's mean and covariance, less its spread
    term). Split between candidates as Eq. 3.7 splits ``1 − β₀`` (``q_g = p_g / (1 − β₀)``), with
    ``S_g ≼ λ_g Γ`` (``λ_g = spread``, the largest eigenvalue of ``Γ^{-½} S_g Γ^{-½}``, ``≥ 1``)
    the scalar weight

        w_g = q_g / (1 + β₀ λ_g / (1 − β₀)) = p_g / (1 − β₀ + β₀ λ_g)

    gives no more information than that factor. ``β₀ = 0`` (no clutter) is Eq. 3.7's ``p_g``;
    ``w_g ≤ p_g`` always. Shapes: ``p`` and ``spread`` ``(Dmax, G)``, ``clutter`` ``(Dmax,)``.
    """
    b0 = clutter[:, None]
    return p / (1.0 - b0 + b0 * jnp.maximum(spread, 1.0))


def innovation_spread(sensor, candidate_cov: Float[Array, "Dmax G 2 2"]) -> Float[Array, "Dmax G"]:
    """``λ_max(Γ^{-½} S_g Γ^{-½})`` of every (detection, candidate) pair (:func:`clutter_weights`),
    from the candidates' innovation covariances ``S_g`` (``Association.candidate_cov``)."""
    w, _ = sensor.geometric_sqrt_information()
    m = jnp.einsum("ij,...jk,lk->...il", w, candidate_cov, w)
    half_sum, half_diff = 0.5 * (m[..., 0, 0] + m[..., 1, 1]), 0.5 * (m[..., 0, 0] - m[..., 1, 1])
    return half_sum + jnp.sqrt(half_diff**2 + m[..., 0, 1] * m[..., 1, 0])


def _step(est: GPDA, state: GaussianState, odometry, detections: Detections) -> tuple[GaussianState, StepInfo]:
    mean, cov = gaussian.predict(state, odometry)
    assoc = gaussian.associate(state, mean, cov, detections, est.max_hypotheses)
    g = assoc.num_candidates
    if state.structure.clutter:  # the clutter mass shrinks each candidate's pull (clutter_weights)
        spread = innovation_spread(state.model.sensor, assoc.candidate_cov)
    mean, cov, new, created, unmapped = gaussian.create_likeliest_new(state, mean, cov, assoc, detections)
    # A detection whose likeliest option is a new object is that object's alone: created, or unmapped
    # when no slot is free (as a creation, no soft update of the old candidates).
    # With clutter, a detection whose likeliest option is clutter is clutter (the thesis's gating rule,
    # Sec. 3.2.1, as a likeliest "new object" creates one): no factor. Soft pulls of a detection more
    # likely spurious than not add up over the steps when the spurious source stands still (another
    # robot seen again and again, dataset 7, robot 1: 1.455 m APE with them against 0.127 m without).
    outlier = (jnp.argmax(assoc.marginals, axis=-1) == g) & state.structure.clutter
    p = jnp.where(assoc.candidate_ok & ~(new | unmapped | outlier)[:, None], assoc.marginals[:, :g], 0.0)  # (Dmax, G)
    weight = clutter_weights(p, assoc.marginals[:, g], spread) if state.structure.clutter else p
    geo = jnp.broadcast_to(detections.geo[:, None, :], (*p.shape, 2))
    mean, cov, result = gaussian.weighted_update(state, mean, cov, assoc.candidates.reshape(-1),
                                                 geo.reshape(-1, 2), weight.reshape(-1), est.gn_max_steps)
    onehot = assoc.candidates[..., None] == jnp.arange(state.max_objects)[None, None, :]  # (Dmax, G, Nmax)
    prob = jnp.einsum("dg,dgn->dn", p, onehot.astype(p.dtype))
    classes = gaussian.update_classes(state, assoc, prob, created)
    used = jnp.any(p > 0, axis=-1)
    likeliest = assoc.candidates[jnp.arange(p.shape[0]), jnp.argmax(p, axis=-1)]
    assigned = jnp.where(new, created, likeliest)
    skipped = jnp.sum(detections.mask & ~used & ~new & ~unmapped & ~outlier)
    # With a clutter density (known map): the detections whose likeliest option is clutter are outliers.
    rejected = jnp.sum(detections.mask & outlier)
    # The smoother's factors: every candidate weighted by its association probability (Eq. 3.7);
    # a detection that created its object is that object's factor.
    factor_obj = jnp.where(new[:, None], jnp.maximum(created, 0)[:, None], assoc.candidates)
    log_p = jnp.where(weight > 0, jnp.log(jnp.where(weight > 0, weight, 1.0)), -jnp.inf)
    first = jnp.arange(g) == 0
    factor_w = jnp.where(new[:, None], jnp.where(first[None, :], 0.0, -jnp.inf), log_p)
    return gaussian.commit(est, state, mean, cov, classes, assigned, used | new, detections, jnp.sum(new),
                           {"skipped": skipped, "rejected": rejected, "unmapped": jnp.sum(unmapped), "solver_result": result,
                            "dropped": assoc.dropped}, odometry,
                           (factor_obj, factor_w, jnp.full(new.shape, -jnp.inf)))
