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
detection's most probable object. Options as in :mod:`.ml`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..belief import Detections
from . import gaussian
from .gaussian import GaussianState, StepInfo
from .base import Settings

NAME = "gpda"


def init(scenario, settings: Settings) -> GaussianState:
    return gaussian.init_state(scenario, settings)


@jax.jit
def step(state: GaussianState, odometry: Float[Array, "3"], detections: Detections,
         key: jax.Array) -> tuple[GaussianState, StepInfo]:
    """One filter step; ``key`` is unused (the estimator is deterministic)."""
    del key
    mean, cov = gaussian.predict(state, odometry)
    assoc = gaussian.associate(state, mean, cov, detections)
    g = assoc.num_candidates
    mean, cov, new, created = gaussian.create_likeliest_new(state, mean, cov, assoc, detections)
    p = jnp.where(assoc.candidate_ok & ~new[:, None], assoc.marginals[:, :g], 0.0)  # (Dmax, G)
    geo = jnp.broadcast_to(detections.geo[:, None, :], (*p.shape, 2))
    mean, cov, result = gaussian.weighted_update(state, mean, cov, assoc.candidates.reshape(-1),
                                                 geo.reshape(-1, 2), p.reshape(-1))
    onehot = assoc.candidates[..., None] == jnp.arange(state.max_objects)[None, None, :]  # (Dmax, G, Nmax)
    prob = jnp.einsum("dg,dgn->dn", p, onehot.astype(p.dtype))
    classes = gaussian.update_classes(state, assoc, prob, created)
    used = jnp.any(p > 0, axis=-1)
    likeliest = assoc.candidates[jnp.arange(p.shape[0]), jnp.argmax(p, axis=-1)]
    assigned = jnp.where(new, created, likeliest)
    skipped = jnp.sum(detections.mask & ~used & ~new)
    return gaussian.commit(state, mean, cov, classes, assigned, used | new, detections, jnp.sum(new),
                           {"skipped": skipped, "solver_result": result})


view = gaussian.view
warnings = gaussian.warnings


def describe(settings: Settings) -> str:
    return gaussian.describe("Gaussian PDA, one EM iteration", "Doherty thesis Sec. 3.4, Eq. 3.7", settings)
