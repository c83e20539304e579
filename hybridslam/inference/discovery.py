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
from jaxtyping import Array, Float, Int

from ..models import se2


def back_project(x: se2.Pose, geo: Float[Array, "2"]) -> Float[Array, "2"]:
    """The object position that ``geo = [range, bearing]`` seen from robot pose ``x`` implies (m)."""
    local = geo[0] * jnp.stack([jnp.cos(geo[1]), jnp.sin(geo[1])])
    return x[:2] + se2.rotation(x[2]) @ local


def create_object(
    mean: Float[Array, " D"],
    cov: Float[Array, "D D"],
    slot: Int[Array, ""],
    geo: Float[Array, "2"],
    geometric_cov: Float[Array, "2 2"],
    orientation_var: Float[Array, ""],
) -> tuple[Float[Array, " D"], Float[Array, "D D"]]:
    """Write a new object into slot ``slot`` of the joint Gaussian, initialized from detection ``geo``.

    Position: ``p = back_project(x_k, z)``, linearized at the mean, so with ``J_x = ∂p/∂x_k`` and
    ``J_z = ∂p/∂z`` the new blocks are ``Σ_pp = J_x Σ_xx J_xᵀ + J_z Σ_v J_zᵀ`` and
    ``Σ_p· = J_x Σ_x·`` (the pose uncertainty correlates the new object with everything the pose
    is correlated with). Orientation: unobserved by range and bearing, so mean 0 and variance
    ``orientation_var`` (scenario key ``new_object_orientation_var``), uncorrelated.
    Whatever the slot held before is discarded. ``slot`` may be traced (a dynamic index).
    """
    dim = mean.shape[0]
    x = mean[:3]
    j_x = jax.jacfwd(back_project, argnums=0)(x, geo)  # (2, 3)
    j_z = jax.jacfwd(back_project, argnums=1)(x, geo)  # (2, 2)
    rows = 3 + 3 * slot + jnp.arange(3)  # the slot's [x, y, theta] entries
    select = jax.nn.one_hot(rows, dim, dtype=mean.dtype)  # (3, D)
    # A Σ Aᵀ + B Σ_v Bᵀ of the affine map y' = A y + B z that drops the slot and writes p into its
    # position rows, block by block: O(D²), where the dense products cost two D³ (the hallway's
    # D = 213, per created object and component).
    keep = 1.0 - jnp.sum(select, axis=0)  # (D,): 0 on the slot's entries
    cross = (j_x @ cov[:3, :]) * keep[None, :]  # Σ_p· = J_x Σ_x·, (2, D), outside the slot
    put = select[:2].T  # (D, 2): writes a 2-vector into the position rows
    pp = j_x @ cov[:3, :3] @ j_x.T + j_z @ geometric_cov @ j_z.T
    new_cov = (cov * keep[:, None] * keep[None, :] + put @ cross + cross.T @ put.T + put @ pp @ put.T
               + orientation_var * jnp.outer(select[2], select[2]))
    new_mean = mean.at[rows].set(jnp.concatenate([back_project(x, geo), jnp.zeros(1, mean.dtype)]))
    return new_mean, 0.5 * (new_cov + new_cov.T)
