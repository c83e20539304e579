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
Settings: :class:`.gaussian.SingleGaussian`.
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


def _step(est: GPDA, state: GaussianState, odometry, detections: Detections) -> tuple[GaussianState, StepInfo]:
    mean, cov = gaussian.predict(state, odometry)
    assoc = gaussian.associate(state, mean, cov, detections, est.max_hypotheses)
    g = assoc.num_candidates
    mean, cov, new, created, unmapped = gaussian.create_likeliest_new(state, mean, cov, assoc, detections)
    # A detection whose likeliest option is a new object is that object's alone: created, or unmapped
    # when no slot is free (as a creation, no soft update of the old candidates).
    p = jnp.where(assoc.candidate_ok & ~(new | unmapped)[:, None], assoc.marginals[:, :g], 0.0)  # (Dmax, G)
    geo = jnp.broadcast_to(detections.geo[:, None, :], (*p.shape, 2))
    mean, cov, result = gaussian.weighted_update(state, mean, cov, assoc.candidates.reshape(-1),
                                                 geo.reshape(-1, 2), p.reshape(-1), est.gn_max_steps)
    onehot = assoc.candidates[..., None] == jnp.arange(state.max_objects)[None, None, :]  # (Dmax, G, Nmax)
    prob = jnp.einsum("dg,dgn->dn", p, onehot.astype(p.dtype))
    classes = gaussian.update_classes(state, assoc, prob, created)
    used = jnp.any(p > 0, axis=-1)
    likeliest = assoc.candidates[jnp.arange(p.shape[0]), jnp.argmax(p, axis=-1)]
    assigned = jnp.where(new, created, likeliest)
    skipped = jnp.sum(detections.mask & ~used & ~new & ~unmapped)
    # With a clutter density (known map): the detections whose likeliest option is clutter are outliers
    # (their candidates keep only their small weights).
    rejected = jnp.sum(detections.mask & (jnp.argmax(assoc.marginals, axis=-1) == g)) if state.structure.clutter \
        else jnp.zeros((), jnp.int32)
    # The smoother's factors: every candidate weighted by its association probability (Eq. 3.7);
    # a detection that created its object is that object's factor.
    factor_obj = jnp.where(new[:, None], jnp.maximum(created, 0)[:, None], assoc.candidates)
    log_p = jnp.where(p > 0, jnp.log(jnp.where(p > 0, p, 1.0)), -jnp.inf)
    first = jnp.arange(g) == 0
    factor_w = jnp.where(new[:, None], jnp.where(first[None, :], 0.0, -jnp.inf), log_p)
    return gaussian.commit(est, state, mean, cov, classes, assigned, used | new, detections, jnp.sum(new),
                           {"skipped": skipped, "rejected": rejected, "unmapped": jnp.sum(unmapped), "solver_result": result,
                            "dropped": assoc.dropped}, odometry,
                           (factor_obj, factor_w, jnp.full(new.shape, -jnp.inf)))
