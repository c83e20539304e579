"""Classifier models ``P(z^sem | c, viewpoint) = N(h_c(viewpoint), Σ_c(viewpoint))`` (Eq. 2).

One small interface, :class:`ClassifierModel`: a model gives, for a viewpoint, the mean
score vector of every class (``class_means``, shape ``(M, M)``, row ``c`` is ``h_c``) and the
square-root information of every class (``class_sqrt_informations``, shape ``(M, M, M)``, with
``Σ_c = (R_cᵀ R_c)⁻¹``). Everything the estimator needs — whitened residuals for Gauss-Newton,
log-likelihoods for the weights, samples for simulation — is derived from those two, so a new
model (e.g. a learned one) implements just them. The viewpoint is passed as the unit vector
``(cos θ, sin θ)`` of the angle θ of SCENARIO_FORMAT.md (continuous across ±π, no ``atan2``).
The categorical :class:`Confusion` model (thesis Eq. 2.14) is not Gaussian: it overrides
``residuals`` and ``sample`` instead.

Parameters (``alpha``, ``K``) are array leaves: changing them never recompiles.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from .unrolled import sum_last

_LOG_2PI = math.log(2.0 * math.pi)


class ClassifierModel(eqx.Module):
    """Base class. ``num_classes`` is static (it fixes shapes)."""

    num_classes: int = eqx.field(static=True)

    @abc.abstractmethod
    def class_means(self, viewpoint: Float[Array, "2"]) -> Float[Array, "M M"]:
        """``h_c(viewpoint)`` for every class ``c`` (row ``c``)."""

    @abc.abstractmethod
    def class_sqrt_informations(self, viewpoint: Float[Array, "2"]) -> Float[Array, "M M M"]:
        """Upper-triangular ``R_c`` with ``Σ_c(viewpoint) = (R_cᵀ R_c)⁻¹`` for every class."""

    @property
    def uses_scores(self) -> bool:
        """False for the geometry-only model, whose semantic factor is identically 1."""
        return True

    @property
    def residual_dim(self) -> int:
        """Entries of one class's semantic residual: ``M``, or ``M + 1`` where a model's normalizer
        depends on the viewpoint and rides in the residual (:class:`~.learned.Learned`)."""
        return self.num_classes

    @property
    def viewpoint_dependent(self) -> bool:
        """False where the semantic factor does not depend on the viewpoint, i.e. on the state: then
        class realizations change a factor graph's cost by a constant and not its solution, and
        components that differ only in their classes share one smoothing. True unless a model says so."""
        return True

    def residuals(
        self, scores: Float[Array, " M"], viewpoint: Float[Array, "2"]
    ) -> tuple[Float[Array, "M R"], Float[Array, " M"]]:
        """Whitened residuals ``R_c (z − h_c)`` (row ``c``) and log normalizers ``log|R_c| − M/2 log 2π``.

        For every class at once: ``log N(z; h_c, Σ_c) = −½‖r_c‖² + log_norm_c`` (Eq. 2). Everything
        downstream uses only this identity, so a model may write part of a viewpoint-dependent
        normalizer as one more residual entry (``R = residual_dim``; :class:`~.learned.Learned`):
        then a least-squares solve over the poses minimizes the whole negative log-likelihood.
        """
        h = self.class_means(viewpoint)
        r = self.class_sqrt_informations(viewpoint)
        diag = jnp.diagonal(r, axis1=-2, axis2=-1)
        log_norm = jnp.sum(jnp.log(jnp.abs(diag)), axis=-1) - 0.5 * self.num_classes * _LOG_2PI
        return sum_last(r * (scores[None, :] - h)[:, None, :]), log_norm

    def log_likelihood(
        self, scores: Float[Array, " M"], c: Int[ArrayLike, ""], viewpoint: Float[Array, "2"]
    ) -> Float[Array, ""]:
        """``log P(scores | c, viewpoint)``."""
        r, log_norm = self.residuals(scores, viewpoint)
        return log_norm[c] - 0.5 * jnp.sum(r[c] ** 2)

    def sample(self, key: jax.Array, c: Int[ArrayLike, ""], viewpoint: Float[Array, "2"]) -> Float[Array, " M"]:
        """Draw a score vector from the model (used by the simulator)."""
        r = self.class_sqrt_informations(viewpoint)[c]
        eps = jax.random.normal(key, (self.num_classes,), dtype=r.dtype)
        return self.class_means(viewpoint)[c] + jax.scipy.linalg.solve_triangular(r, eps, lower=False)


def _mirror_sqrt_information(k: Float[Array, ""]) -> Float[Array, "2 2"]:
    """``R = K [[1, -0.5], [0, 1]]`` of Eq. 18's covariance ``Σ_c = (RᵀR)⁻¹``."""
    return k * jnp.array([[1.0, -0.5], [0.0, 1.0]], dtype=jnp.result_type(k))


class _AlphaK(ClassifierModel):
    """Two classes parameterized by the viewpoint-dependence ``alpha`` and sharpness ``K`` (Eq. 18)."""

    alpha: Float[Array, ""]
    K: Float[Array, ""]

    def __init__(self, alpha: float | Array, K: float | Array):
        self.num_classes = 2
        self.alpha = jnp.asarray(alpha, dtype=float)
        self.K = jnp.asarray(K, dtype=float)


class Mirror(_AlphaK):
    """The paper's viewpoint-dependent model of a mirror-symmetric object (Eq. 18), M = 2.

    With ``s = sin²(θ/2)``: ``h_0 = [α s + (1 − α), α − α s]`` and ``h_1`` its mirror image;
    ``Σ_c = (RᵀR)⁻¹``, ``R = K [[1, −0.5], [0, 1]]`` for both classes.
    """

    def class_means(self, viewpoint):
        s = 0.5 * (1.0 - viewpoint[0])  # sin²(θ/2) = (1 − cos θ) / 2
        h0 = jnp.stack([self.alpha * s + (1.0 - self.alpha), self.alpha - self.alpha * s])
        return jnp.stack([h0, h0[::-1]])

    def class_sqrt_informations(self, viewpoint):
        return jnp.broadcast_to(_mirror_sqrt_information(self.K), (2, 2, 2))


class Independent(_AlphaK):
    """Viewpoint-independent Gaussian per class: the moment-matched average of :class:`Mirror`.

    Averaging Eq. 18 over a uniform viewpoint, ``E[sin²(θ/2)] = 1/2`` and
    ``Var[sin²(θ/2)] = 1/8``, so ``h̄_0 = [1 − α/2, α/2]`` (``h̄_1`` mirrored) and
    ``Σ̄ = Σ_c + (α²/8) [[1, −1], [−1, 1]]`` — the paper's "viewpoint-independent model" (Sec. V).
    """

    @property
    def viewpoint_dependent(self) -> bool:
        return False

    def class_means(self, viewpoint):
        h0 = jnp.stack([1.0 - self.alpha / 2.0, self.alpha / 2.0])
        return jnp.stack([h0, h0[::-1]])

    def covariance(self) -> Float[Array, "2 2"]:
        r = _mirror_sqrt_information(self.K)
        spread = jnp.array([[1.0, -1.0], [-1.0, 1.0]], dtype=r.dtype)
        return jnp.linalg.inv(r.T @ r) + self.alpha**2 / 8.0 * spread

    def class_sqrt_informations(self, viewpoint):
        # R = L⁻¹ with Σ = L Lᵀ gives Rᵀ R = Σ⁻¹.
        chol = jnp.linalg.cholesky(self.covariance())
        r = jax.scipy.linalg.solve_triangular(chol, jnp.eye(2, dtype=chol.dtype), lower=True)
        return jnp.broadcast_to(r, (2, 2, 2))


class AlphaK(_AlphaK):
    """:class:`Mirror` (``dependence`` 1) or :class:`Independent` (``dependence`` 0) with the choice a
    traced leaf, so that one compiled program serves both (a study's cells of the two models).

    Each model's ``h_c`` and ``R_c`` are computed as that model computes them and the one
    ``dependence`` names is selected (exactly, not blended). ``viewpoint_dependent`` is True for
    both: components that differ only in their classes are then smoothed apart even under the
    independent model, whose class realizations change a graph's cost by a constant only, so its
    smoothed solutions are those of :class:`Independent` (to rounding; more solves).
    """

    dependence: Float[Array, ""]  # 1.0: Mirror, 0.0: Independent

    def __init__(self, alpha: float | Array, K: float | Array, dependence: float | Array):
        super().__init__(alpha, K)
        self.dependence = jnp.asarray(dependence, dtype=float)

    def _parts(self) -> tuple[Mirror, Independent]:
        return Mirror(self.alpha, self.K), Independent(self.alpha, self.K)  # type: ignore[call-arg]

    def class_means(self, viewpoint):
        mirror, independent = self._parts()
        return jnp.where(self.dependence > 0.5, mirror.class_means(viewpoint),
                         independent.class_means(viewpoint))

    def class_sqrt_informations(self, viewpoint):
        mirror, independent = self._parts()
        return jnp.where(self.dependence > 0.5, mirror.class_sqrt_informations(viewpoint),
                         independent.class_sqrt_informations(viewpoint))


class NoClassifier(ClassifierModel):
    """Geometry only: scores are ignored (the paper's passive DA-BSP baseline, Sec. V)."""

    def __init__(self, num_classes: int):
        self.num_classes = num_classes

    @property
    def uses_scores(self) -> bool:
        return False

    @property
    def viewpoint_dependent(self) -> bool:
        return False

    def class_means(self, viewpoint):
        return jnp.zeros((self.num_classes, self.num_classes))

    def class_sqrt_informations(self, viewpoint):
        return jnp.zeros((self.num_classes,) * 3)

    def residuals(self, scores, viewpoint):
        m = self.num_classes
        return jnp.zeros((m, m), scores.dtype), jnp.zeros((m,), scores.dtype)


class Confusion(ClassifierModel):
    """The detector's confusion matrix (thesis Eq. 2.14-2.15): ``P(label = i | class = c) = matrix[i, c]``.

    The detection's predicted label is ``argmax(scores)`` (ties: the lowest index), so
    ``log P(scores | c) = log matrix[argmax(scores), c]`` for every viewpoint. There is no Gaussian
    semantic part: :meth:`residuals` gives zero whitened residuals, so the Gauss-Newton update
    (Eq. 9) sees only the geometry, and the log normalizers carry the whole categorical likelihood,
    so :meth:`log_likelihood` and every weight method work unchanged.

    ``class_means`` row ``c`` is the expected one-hot score vector under class ``c`` (column ``c`` of
    the matrix); ``class_sqrt_informations`` is zero (no Gaussian factor, as in :class:`NoClassifier`),
    so draw scores with :meth:`sample`, which returns the one-hot vector of a label drawn from
    column ``c``. ``matrix`` is a traced leaf: a sweep over accuracies never recompiles.
    """

    matrix: Float[Array, "M M"]  # matrix[label, class]; columns sum to 1

    def __init__(self, matrix: Float[ArrayLike, "M M"] | list):
        m = jnp.asarray(matrix, dtype=float)
        if m.ndim != 2 or m.shape[0] != m.shape[1]:
            raise ValueError(f"classifier.matrix: expected a square matrix, got shape {m.shape}")
        self.num_classes = int(m.shape[0])
        self.matrix = m

    @property
    def viewpoint_dependent(self) -> bool:
        return False

    def class_means(self, viewpoint):
        return self.matrix.T

    def class_sqrt_informations(self, viewpoint):
        return jnp.zeros((self.num_classes,) * 3, self.matrix.dtype)

    def residuals(self, scores, viewpoint):
        """Zero residuals and ``log matrix[argmax(scores), c]`` per class ``c`` (Eq. 2.14)."""
        m = self.num_classes
        label = jnp.argmax(scores) == jnp.arange(m)  # one-hot select: no gather under vmap
        log_norm = jnp.sum(jnp.where(label[:, None], jnp.log(self.matrix), 0.0), axis=0)
        return jnp.zeros((m, m), scores.dtype), log_norm

    def sample(self, key, c, viewpoint):
        """The one-hot score vector of a label drawn from ``Cat(matrix[:, c])`` (Eq. 2.14)."""
        label = jax.random.categorical(key, jnp.log(self.matrix[:, c]))
        return jax.nn.one_hot(label, self.num_classes, dtype=self.matrix.dtype)
