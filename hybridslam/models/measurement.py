"""The measurement factor of one detection: geometric and semantic parts (Eq. 10).

Everything downstream — sampled weights (Eq. 16), linearized weights (thesis Eq. 4.14-4.15),
and the Gauss-Newton update (Eq. 9) — is written in terms of one function,
:func:`detection_residual`, which returns the *whitened* residual ``r`` and the log normalizer
so that ``log P(z | x, x^o, c) = -½‖r‖² + log_norm``.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax.scipy.special import log_ndtr, ndtr
from jaxtyping import Array, Bool, Float, Int

from .scenario import StackedSteps
from . import geometry
from .classifier import ClassifierModel
from .unrolled import sum_last

_LOG_2PI = math.log(2.0 * math.pi)


class SensorModel(eqx.Module):
    """Geometric noise, classifier and field of view. All parameters are traced arrays.

    ``visibility_temperature`` selects the object observation model ``P(β_k | x_k, X^o)``:
    ``None`` (the default) is the paper's 0/1 footprint (Sec. IV-B); an array ``(τ_r, τ_b)``
    (metres, radians) is its smooth relaxation, differentiable everywhere (see
    :func:`log_visibility`). Whether it is ``None`` is static (a different code path); the
    temperatures themselves are traced.
    """

    geometric_cov: Float[Array, "2 2"]
    classifier: ClassifierModel
    max_range: Float[Array, ""]
    fov: Float[Array, ""]
    visibility_temperature: Float[Array, "2"] | None = None

    @property
    def residual_dim(self) -> int:
        return 2 + self.classifier.residual_dim

    def geometric_sqrt_information(self) -> tuple[Float[Array, "2 2"], Float[Array, ""]]:
        """``W = L⁻¹`` with ``Σ_v = L Lᵀ``, and ``log|W| - log 2π`` (the 2-D normalizer)."""
        chol = jnp.linalg.cholesky(self.geometric_cov)
        w = jsl.solve_triangular(chol, jnp.eye(2, dtype=chol.dtype), lower=True)
        return w, -jnp.sum(jnp.log(jnp.diagonal(chol))) - _LOG_2PI


def detection_residuals(
    sensor: SensorModel,
    x: Float[Array, "3"],
    obj: Float[Array, "3"],
    z_geo: Float[Array, "2"],
    scores: Float[Array, " M"],
) -> tuple[Float[Array, "2"], Float[Array, "M Rs"], Float[Array, " M"]]:
    """Whitened residuals of one detection for every class hypothesis (Eq. 10).

    Returns the geometric residual ``W (z^geo − h^geo)``, the semantic residuals ``R_c (z^sem − h_c)``
    (row ``c``) and the log normalizer per class, so that
    ``log P(z | x, x^o, c) = −½‖r_geo‖² − ½‖r_sem[c]‖² + log_norm[c]``.
    """
    w, geo_norm = sensor.geometric_sqrt_information()
    d = geometry.geometric_residual(z_geo, geometry.range_bearing(x, obj))
    r_geo = sum_last(w * d[None, :])  # W @ d as unrolled adds: fuses under vmap, tiny dots do not
    r_sem, sem_norm = sensor.classifier.residuals(scores, geometry.viewpoint(x, obj))
    return r_geo, r_sem, geo_norm + sem_norm


def detection_residual(
    sensor: SensorModel,
    x: Float[Array, "3"],
    obj: Float[Array, "3"],
    z_geo: Float[Array, "2"],
    scores: Float[Array, " M"],
    c: Int[Array, ""],
) -> tuple[Float[Array, " R"], Float[Array, ""]]:
    """The stacked whitened residual ``[r_geo, r_sem[c]]`` (length ``sensor.residual_dim``: ``2 + M``, or
    ``2 + M + 1`` for a learned classifier) and log normalizer of class ``c``."""
    r_geo, r_sem, log_norm = detection_residuals(sensor, x, obj, z_geo, scores)
    pick = jnp.arange(r_sem.shape[0]) == c  # one-hot select: elementwise, no gather
    r_c = jnp.sum(jnp.where(pick[:, None], r_sem, 0.0), axis=0)
    return jnp.concatenate([r_geo, r_c]), jnp.sum(jnp.where(pick, log_norm, 0.0))


def slot_residuals(
    sensor: SensorModel,
    x: Float[Array, "3"],
    slot_objects: Float[Array, "Dmax 3"],
    z_geo: Float[Array, "Dmax 2"],
    scores: Float[Array, "Dmax M"],
    assign: Int[Array, " Dmax"],
    slot_class: Int[Array, " Dmax"],
) -> tuple[Float[Array, " DR"], Float[Array, ""]]:  # DR = Dmax · (residuals per slot)
    """The joint measurement factor of a step (Eq. 10): the stacked whitened residuals of every
    occupied slot (zeros for empty slots, ``assign < 0``) and the sum of their log normalizers.

    ``slot_objects[j]`` is the pose of the object that slot ``j`` is associated with.
    """
    per_det = jax.vmap(detection_residual, (None, None, 0, 0, 0, 0))
    r, log_norm = per_det(sensor, x, slot_objects, z_geo, scores, slot_class)
    occupied = assign >= 0
    return jnp.where(occupied[:, None], r, 0.0).reshape(-1), jnp.sum(jnp.where(occupied, log_norm, 0.0))


def in_view(sensor: SensorModel, x: Float[Array, "3"], obj: Float[Array, "3"]) -> Bool[Array, ""]:
    """The 0/1 object observation model ``P(β | x_k, x^o)`` for one object (Sec. IV-B)."""
    return geometry.visible(geometry.range_bearing(x, obj), sensor.max_range, sensor.fov)


def log_visibility(sensor: SensorModel, x: Float[Array, "3"], obj: Float[Array, "3"]) -> Float[Array, ""]:
    """``log P(object in view | x_k, x^o)``: the sensor's object observation model (Sec. IV-B).

    ``0`` or ``-inf`` for the paper's hard footprint (``visibility_temperature is None``);
    otherwise the smooth model of :func:`~hybridslam.geometry.log_smooth_visibility`.
    """
    rb = geometry.range_bearing(x, obj)
    if sensor.visibility_temperature is None:
        return jnp.where(geometry.visible(rb, sensor.max_range, sensor.fov), 0.0, -jnp.inf)
    return geometry.log_smooth_visibility(rb, sensor.max_range, sensor.fov, sensor.visibility_temperature)


def log_visibility_probability(
    sensor: SensorModel, range_bearing_: Float[Array, "2"], variance: Float[Array, "2"]
) -> Float[Array, ""]:
    """``log P(object in view)`` when its range and bearing are ``N(range_bearing_, diag(variance))``:
    the object observation model (Sec. IV-B) averaged over a linearized Gaussian predictive
    (``variance = diag(H Σ Hᵀ)``, m² and rad², of the robot pose and the object; no sensor noise).

    Finite wherever the mean is near the footprint, so screens and linearized weights rank a
    prediction just outside it low rather than impossible; ``-inf`` only where the bearing
    probability underflows. Range and bearing are taken as independent.
    """
    std = jnp.sqrt(variance + 1e-12)
    if sensor.visibility_temperature is not None:
        # Smooth footprint (geometry.log_smooth_visibility): σ(m/τ) ≈ Φ(m/(τ√(8/π))) (equal slope at 0),
        # and E[Φ(m/s)] over m ~ N(m̄, v) is Φ(m̄/√(s² + v)): the hard formula with a wider spread.
        # Both bearing edges share one Φ-difference (accurate while fov/2 ≫ τ_b).
        tau = jnp.maximum(sensor.visibility_temperature, 0.0)
        std = jnp.sqrt(std**2 + (8.0 / jnp.pi) * tau**2)
    log_in_range = log_ndtr((sensor.max_range - range_bearing_[0]) / std[0])
    half = 0.5 * sensor.fov
    p_bearing = ndtr((half - range_bearing_[1]) / std[1]) - ndtr((-half - range_bearing_[1]) / std[1])
    positive = p_bearing > 0.0
    # Double where: log(0) = -inf must not turn into a NaN gradient.
    return log_in_range + jnp.where(positive, jnp.log(jnp.where(positive, p_bearing, 1.0)), -jnp.inf)


class Detections(eqx.Module):
    """The detections ``Z_k`` of one step, padded to a fixed number of slots ``Dmax`` (or of ``*T``
    steps, stacked on leading axes)."""

    geo: Float[Array, "*T Dmax 2"]  # [range, bearing]
    scores: Float[Array, "*T Dmax M"]  # classifier output z^sem (Eq. 1)
    mask: Bool[Array, "*T Dmax"]  # which slots hold a detection

    def span(self) -> Int[Array, "*T"]:
        """The slots up to the last detection, its index + 1 (0 without one): the later slots are
        padding to the run's busiest step, which a step's association search skips."""
        slots = jnp.arange(1, self.mask.shape[-1] + 1)
        return jnp.max(jnp.where(self.mask, slots, 0), axis=-1)


def stacked_detections(stacked: StackedSteps) -> Detections:
    """All steps of a scenario as one :class:`Detections` with a leading time axis ``T``."""
    return Detections(
        jnp.asarray(stacked.geo, dtype=float), jnp.asarray(stacked.scores, dtype=float),
        jnp.asarray(stacked.mask),
    )
