"""Unknown maps: object slots that a detection can create (SCENARIO_FORMAT.md, "Unknown maps").

An estimator that allows new objects keeps a joint Gaussian over ``[x_k, o_0, ..., o_{N_max-1}]``
with a fixed capacity ``N_max`` of object slots; the first ``N`` are the scenario's prior objects,
the others are *uncreated* placeholders (mean 0, covariance I, uncorrelated: never observed, kept
only so batched Cholesky factors stay finite). A detection associated with the null / new-landmark
hypothesis (Doherty's thesis Sec. 3.2.1; the max-mixtures summary's Eq. 13) creates the next slot,
initialized from the detection by back-projecting its range and bearing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..models import se2


def back_project(x: se2.Pose, geo: Float[Array, "2"]) -> Float[Array, "2"]:
    """The object position that ``geo = [range, bearing]`` seen from robot pose ``x`` implies (m)."""
    local = geo[0] * jnp.stack([jnp.cos(geo[1]), jnp.sin(geo[1])])
    return x[:2] + se2.rotation(x[2]) @ local


def back_project_jacobians(x: se2.Pose, geo: Float[Array, "2"]) -> tuple[Float[Array, "2 3"], Float[Array, "2 2"]]:
    """``(∂p/∂x, ∂p/∂z)`` of :func:`back_project` in closed form: ``p = t + ρ [cos φ, sin φ]`` with
    ``φ = θ + b`` (the inverse of Eq. 10), so ``∂p/∂t = I``, ``∂p/∂θ = ρ [−sin φ, cos φ]`` and
    ``∂p/∂(ρ, b) = [[cos φ, −ρ sin φ], [sin φ, ρ cos φ]]``."""
    c, s = jnp.cos(x[2] + geo[1]), jnp.sin(x[2] + geo[1])
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    j_x = jnp.stack([jnp.stack([one, zero, -geo[0] * s]), jnp.stack([zero, one, geo[0] * c])])
    j_z = jnp.stack([jnp.stack([c, -geo[0] * s]), jnp.stack([s, geo[0] * c])])
    return j_x, j_z


def create_object(
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    slot: Int[Array, ""],
    geo: Float[Array, "2"],
    geometric_cov: Float[Array, "2 2"],
    orientation_var: Float[Array, ""],
    apply: Bool[Array, ""] | bool = True,
) -> tuple[Float[Array, " D"], Float[Array, "D D"]]:
    """Write a new object into slot ``slot`` of the joint Gaussian, initialized from detection ``geo``.

    Position: ``p = back_project(x_k, z)``, linearized at the mean, so with ``J_x = ∂p/∂x_k`` and
    ``J_z = ∂p/∂z`` the new blocks are ``Σ_pp = J_x Σ_xx J_xᵀ + J_z Σ_v J_zᵀ`` and
    ``Σ_p· = J_x Σ_x·`` (the pose uncertainty correlates the new object with everything the pose
    is correlated with). Orientation: unobserved by range and bearing, so mean 0 and variance
    ``orientation_var`` (scenario key ``new_object_orientation_var``), uncorrelated.
    Whatever the slot held before is discarded. ``slot`` may be traced (a dynamic index).
    ``apply`` False returns ``mean`` and ``cov`` unchanged (a detection that creates nothing), so
    that callers need not select between two whole covariances.

    Only the slot's three rows and columns change: they are written in place, ``O(D)``, where the
    affine map ``A Σ Aᵀ + B Σ_v Bᵀ`` that drops the slot and writes ``p`` costs two dense ``D³``
    products (``D`` = 213 on the hallway, per created object and component) and a block-wise
    product still several passes over ``D²``.
    """
    dim = mean.shape[0]
    x = mean[:3]
    j_x, j_z = back_project_jacobians(x, geo)  # (2, 3), (2, 2)
    start = jnp.asarray(3 + 3 * slot, jnp.int32)
    zero = jnp.zeros((), jnp.int32)
    pp = j_x @ cov[:3, :3] @ j_x.T + j_z @ geometric_cov @ j_z.T
    block = jnp.zeros((3, 3), cov.dtype).at[:2, :2].set(0.5 * (pp + pp.T)).at[2, 2].set(orientation_var)
    rows = jnp.concatenate([j_x @ cov[:3, :], jnp.zeros((1, dim), cov.dtype)])  # Σ_p· = J_x Σ_x·; heading: 0
    rows = jax.lax.dynamic_update_slice(rows, block, (zero, start))  # the slot's own block
    rows = jnp.where(apply, rows, jax.lax.dynamic_slice(cov, (start, zero), (3, dim)))
    new_cov = jax.lax.dynamic_update_slice(cov, rows, (start, zero))
    new_cov = jax.lax.dynamic_update_slice(new_cov, rows.T, (zero, start))
    value = jnp.concatenate([back_project(x, geo), jnp.zeros(1, mean.dtype)])
    value = jnp.where(apply, value, jax.lax.dynamic_slice(mean, (start,), (3,)))
    return jax.lax.dynamic_update_slice(mean, value, (start,)), new_cov


def create_objects(
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    slots: Int[Array, " Dmax"],
    creates: Bool[Array, " Dmax"],
    geo: Float[Array, "Dmax 2"],
    geometric_cov: Float[Array, "2 2"],
    orientation_var: Float[Array, ""],
) -> tuple[Float[Array, " D"], Float[Array, "D D"]]:
    """:func:`create_object` for every detection ``j`` with ``creates[j]``, into slot ``slots[j]``.

    In detection order (a scan over the slots): each new object is correlated with the ones created
    before it, through the pose. Entries with ``creates[j]`` False change nothing (their slot may be
    anything, e.g. -1).
    """

    def one(carry, item):
        slot, apply, z = item
        return create_object(*carry, jnp.maximum(slot, 0), z, geometric_cov, orientation_var, apply), None

    (mean, cov), _ = jax.lax.scan(one, (mean, cov), (slots, creates, geo))
    return mean, cov

