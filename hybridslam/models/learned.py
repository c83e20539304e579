"""Learned viewpoint-dependent classifier models: ``h_c`` and ``Σ_c`` of Eq. 2 fitted from data.

Sec. III: "the viewpoint-dependent functions h_c and Σ_c are learned offline". :class:`Learned`
is a small MLP from the viewpoint features ``(cos θ, sin θ)`` to, for every class ``c``, the mean
``h_c`` and an upper-triangular square-root information ``R_c`` whose diagonal is ``exp`` of a
network output. So ``Σ_c = (R_cᵀ R_c)⁻¹`` holds exactly as :class:`ClassifierModel` asks, ``R_c``
is always invertible, and ``log|R_c|`` (the Gaussian's normalizer) is a plain sum of outputs.

:func:`fit_classifier` maximizes the likelihood of Eq. 2 over logged samples
``(class, viewpoint, scores)`` with full-batch BFGS (optimistix). :func:`save_classifier` and
:func:`load_classifier` keep a model in one file: a JSON header line, then the weights as written
by ``equinox.tree_serialise_leaves`` (docs/learned_classifier.md).
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Sequence
from typing import NoReturn

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .classifier import ClassifierModel

FILE_FORMAT = "hybridslam-learned-classifier/1"


def _head_size(m: int) -> int:
    """Outputs per class: the mean (M), log-diagonal of ``R_c`` (M), strictly-upper entries."""
    return m + m + m * (m - 1) // 2


class Learned(ClassifierModel):
    """Eq. 2 with ``h_c`` and ``Σ_c`` given by an MLP of the viewpoint ``(cos θ, sin θ)``.

    ``layers`` are the hidden layers (``tanh``: smooth, so BFGS sees a smooth objective) and the
    linear output layer, ``M · (2M + M(M−1)/2)`` outputs: per class the mean, the log-diagonal of
    ``R_c`` and its strictly-upper entries (row-major). Every weight is a traced array leaf.
    """

    layers: tuple[eqx.nn.Linear, ...]

    def __init__(self, num_classes: int, hidden: Sequence[int] = (16, 16), *, key: PRNGKeyArray):
        """Random weights (``eqx.nn.Linear``'s initialization); :func:`fit_classifier` trains them."""
        if not (isinstance(num_classes, int) and num_classes >= 1):
            raise ValueError(f"num_classes: expected a positive int, got {num_classes!r}")
        hidden = tuple(hidden)
        if not all(isinstance(h, int) and h >= 1 for h in hidden):
            raise ValueError(f"hidden: expected positive layer widths, got {hidden!r}")
        sizes = (2, *hidden, num_classes * _head_size(num_classes))
        keys = jax.random.split(key, len(sizes) - 1)
        self.num_classes = num_classes
        self.layers = tuple(eqx.nn.Linear(a, b, key=k) for a, b, k in zip(sizes[:-1], sizes[1:], keys))

    @property
    def hidden(self) -> tuple[int, ...]:
        """Widths of the hidden layers (the file header stores them to rebuild the skeleton)."""
        return tuple(int(layer.out_features) for layer in self.layers[:-1])

    def _heads(self, viewpoint: Float[ArrayLike, "2"]) -> tuple[Float[Array, "M M"], Float[Array, "M M"], Float[Array, "M P"]]:
        """Network outputs split per class: means, log-diagonals of ``R_c``, strictly-upper entries."""
        x = jnp.asarray(viewpoint)
        for layer in self.layers[:-1]:
            x = jnp.tanh(layer(x))
        m = self.num_classes
        out = self.layers[-1](x).reshape(m, _head_size(m))
        return out[:, :m], out[:, m : 2 * m], out[:, 2 * m :]

    def class_means(self, viewpoint):
        return self._heads(viewpoint)[0]

    def class_sqrt_informations(self, viewpoint):
        _, log_diag, upper = self._heads(viewpoint)
        m = self.num_classes
        rows, cols = np.triu_indices(m, k=1)
        eye = jnp.eye(m, dtype=log_diag.dtype)
        r = jnp.exp(log_diag)[:, :, None] * eye[None]
        return r.at[:, rows, cols].set(upper)

    @property
    def residual_dim(self) -> int:
        """``M + 1``: the semantic residual also carries the normalizer's viewpoint dependence."""
        return self.num_classes + 1

    def log_det_bound(self) -> Float[Array, " M"]:
        """``b_c ≥ log|R_c(θ)|`` for every viewpoint, from the weights alone.

        ``log|R_c| = Σ_i d_ci`` is a linear layer's output summed over the log-diagonal heads, and that
        layer's inputs (``tanh`` units, or the features ``(cos θ, sin θ)`` without a hidden layer) lie in
        ``[−1, 1]``: so ``|Σ_i d_ci| ≤ Σ_j |Σ_i W_cij| + |Σ_i b_ci|``.
        """
        last = self.layers[-1]
        m, size = self.num_classes, _head_size(self.num_classes)
        w = jnp.sum(last.weight.reshape(m, size, -1)[:, m : 2 * m], axis=1)  # (M, inputs)
        bound = jnp.sum(jnp.abs(w), axis=-1)
        if last.bias is not None:
            bound = bound + jnp.abs(jnp.sum(last.bias.reshape(m, size)[:, m : 2 * m], axis=-1))
        return bound

    def _whitened(self, scores, viewpoint) -> tuple[Float[Array, "M M"], Float[Array, " M"]]:
        """``R_c (z − h_c)`` row by row straight from the heads, ``exp(d_ci) e_ci + Σ_{j>i} U_cij e_cj``
        with ``e_c = z − h_c``, and ``log|R_c| = Σ_i d_ci``: no ``M × M × M`` matrix, no scatter and
        no second network pass (the step evaluates this for every component, detection slot and
        candidate object, and differentiates it)."""
        h, log_diag, upper = self._heads(viewpoint)
        m = self.num_classes
        e = jnp.asarray(scores)[None, :] - h  # (classes, M)
        position = {(int(i), int(j)): p for p, (i, j) in enumerate(zip(*np.triu_indices(m, k=1)))}
        rows = []
        for i in range(m):
            acc = jnp.exp(log_diag[:, i]) * e[:, i]
            for j in range(i + 1, m):  # the base class's order of summation over j
                acc = acc + upper[:, position[i, j]] * e[:, j]
            rows.append(acc)
        return jnp.stack(rows, axis=-1), jnp.sum(log_diag, axis=-1)

    def residuals(self, scores, viewpoint):
        """:meth:`ClassifierModel.residuals` (Eq. 2) from one evaluation of the network, with the
        normalizer's viewpoint dependence as one more entry.

        ``log N(z; h_c(θ), Σ_c(θ)) = −½‖R_c(z − h_c)‖² + log|R_c(θ)| − M/2 log 2π``, and ``log|R_c(θ)|``
        varies with the viewpoint, i.e. with the robot's and the object's poses. A least-squares
        solve sees only ``½‖r‖²``, so the last entry is ``e_c = √(2 (b_c + 1 − log|R_c(θ)|))`` with
        the bound ``b_c`` of :meth:`log_det_bound` (``e_c ≥ √2``: real, with a bounded derivative).
        Then ``½ e_c² = b_c + 1 − log|R_c(θ)|``, the returned normalizer is the constant
        ``b_c + 1 − M/2 log 2π``, and ``−½‖r_c‖² + log_norm_c`` is Eq. 2's log-density: the smoother
        minimizes the model's whole negative log-likelihood, and Gauss-Newton's gradient of the
        normalizer term is exact.
        """
        r, log_det = self._whitened(scores, viewpoint)
        b = self.log_det_bound() + 1.0
        extra = jnp.sqrt(2.0 * (b - log_det))
        return jnp.concatenate([r, extra[:, None]], axis=-1), b - 0.5 * self.num_classes * math.log(2 * math.pi)

    def log_likelihood(self, scores, c, viewpoint):
        """``log P(scores | c, viewpoint)`` (Eq. 2) without the residual's extra entry (fitting uses it)."""
        r, log_det = self._whitened(scores, viewpoint)
        pick = jnp.arange(self.num_classes) == c
        return (jnp.sum(jnp.where(pick, log_det - 0.5 * jnp.sum(r**2, axis=-1), 0.0))
                - 0.5 * self.num_classes * math.log(2 * math.pi))


# --------------------------------------------------------------------------- #
# Fitting
# --------------------------------------------------------------------------- #


def _check_samples(
    classes: Int[np.ndarray, " N"], viewpoints: Float[np.ndarray, " N"], scores: Float[np.ndarray, "N M"],
    num_classes: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Shapes and values of the training samples, checked before anything is traced."""
    classes, viewpoints, scores = np.asarray(classes), np.asarray(viewpoints), np.asarray(scores)
    if scores.ndim != 2:
        raise ValueError(f"scores: expected an (N, M) array, got shape {scores.shape}")
    n, m = scores.shape
    m = m if num_classes is None else num_classes
    if scores.shape[1] != m:
        raise ValueError(f"scores: expected {m} columns (one per class), got {scores.shape[1]}")
    for name, a in (("classes", classes), ("viewpoints", viewpoints)):
        if a.shape != (n,):
            raise ValueError(f"{name}: expected shape ({n},) to match scores, got {a.shape}")
    if n == 0:
        raise ValueError("no samples")
    if not np.issubdtype(classes.dtype, np.integer):
        if not (np.issubdtype(classes.dtype, np.floating) and np.array_equal(classes, np.round(classes))):
            raise ValueError(f"classes: expected integers, got dtype {classes.dtype}")
        classes = classes.astype(np.int64)
    bad = np.flatnonzero((classes < 0) | (classes >= m))
    if bad.size:
        raise ValueError(f"classes[{bad[0]}]: expected an integer in [0, {m}), got {classes[bad[0]]}")
    for name, a in (("viewpoints", viewpoints), ("scores", scores)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: not all finite")
    counts = np.bincount(classes, minlength=m)
    if counts.min() < 2:
        c = int(np.argmin(counts))
        raise ValueError(f"classes: class {c} has {counts[c]} samples; every class needs at least 2")
    return classes.astype(np.int32), viewpoints.astype(np.float64), scores.astype(np.float64), m


def viewpoint_features(angles: Float[Array, "*batch"]) -> Float[Array, "*batch 2"]:
    """The model input ``(cos θ, sin θ)`` of viewpoint angles θ (radians, SCENARIO_FORMAT.md)."""
    angles = jnp.asarray(angles, dtype=float)
    return jnp.stack([jnp.cos(angles), jnp.sin(angles)], axis=-1)


@eqx.filter_jit
def mean_nll(
    model: ClassifierModel, classes: Int[Array, " N"], viewpoints: Float[Array, " N"], scores: Float[Array, "N M"]
) -> Float[Array, ""]:
    """Mean negative log-likelihood ``−(1/N) Σ_i log N(z_i; h_{c_i}(θ_i), Σ_{c_i}(θ_i))`` (Eq. 2)."""
    log_lik = jax.vmap(model.log_likelihood)(
        jnp.asarray(scores, dtype=float), jnp.asarray(classes), viewpoint_features(viewpoints)
    )
    return -jnp.mean(log_lik)


@eqx.filter_jit
def sample_scores(
    model: ClassifierModel, num_samples: int, key: PRNGKeyArray
) -> tuple[Int[Array, " N"], Float[Array, " N"], Float[Array, "N M"]]:
    """``num_samples`` draws ``(class, viewpoint, scores)`` from ``model`` (Eq. 2).

    Classes take turns (``i mod M``, balanced); viewpoint angles are uniform on ``[−π, π)``. What
    a detector logged while circling objects of known class would give, for a model known exactly.
    """
    m = model.num_classes
    k_view, k_scores = jax.random.split(key)
    classes = jnp.arange(num_samples) % m
    angles = jax.random.uniform(k_view, (num_samples,), minval=-jnp.pi, maxval=jnp.pi)
    keys = jax.random.split(k_scores, num_samples)
    return classes, angles, jax.vmap(model.sample)(keys, classes, viewpoint_features(angles))


def _start_at_constant_fit(model: Learned, classes: np.ndarray, scores: np.ndarray) -> Learned:
    """Set the output layer to the viewpoint-independent Gaussian fit of each class.

    The output weights are shrunk so the network starts near that fit: BFGS then only learns the
    viewpoint dependence, instead of first travelling from random means and scales.
    """
    m = model.num_classes
    bias = []
    for c in range(m):
        z = scores[classes == c]
        mean = z.mean(axis=0)
        cov = np.atleast_2d(np.cov(z, rowvar=False, bias=True))
        cov = cov + 1e-6 * (np.trace(cov) / m + 1e-6) * np.eye(m)  # few or collinear samples
        # Σ⁻¹ = L Lᵀ (L lower) = Rᵀ R with R = Lᵀ upper-triangular, positive diagonal.
        r = np.linalg.cholesky(np.linalg.inv(cov)).T
        bias.append(np.concatenate([mean, np.log(np.diag(r)), r[np.triu_indices(m, k=1)]]))
    last = model.layers[-1]
    return eqx.tree_at(
        lambda mdl: (mdl.layers[-1].weight, mdl.layers[-1].bias),
        model,
        (0.01 * last.weight, jnp.asarray(np.concatenate(bias), dtype=last.weight.dtype)),
    )


def _objective(y: Float[Array, " P"], args) -> Float[Array, ""]:
    """What :func:`fit_classifier` minimizes, at the flat weights ``y``: the mean NLL plus the prior.

    Module-level, with everything else in ``args``, so fits of equal shapes reuse one compiled solve.
    """
    unravel, skeleton, decay, data = args
    model = eqx.combine(unravel(y), skeleton)
    return mean_nll(model, *data) + decay * sum(jnp.sum(layer.weight**2) for layer in model.layers)


def fit_classifier(
    classes: Int[np.ndarray, " N"],
    viewpoints: Float[np.ndarray, " N"],
    scores: Float[np.ndarray, "N M"],
    *,
    num_classes: int | None = None,
    hidden: Sequence[int] = (16, 16),
    seed: int = 0,
    weight_prior_std: float | None = 0.35,
    max_steps: int = 2000,
    rtol: float = 1e-4,
    atol: float = 1e-4,
) -> Learned:
    """Fit a :class:`Learned` model to samples of Eq. 2 by (penalized) maximum likelihood.

    ``classes`` ``(N,)`` are true classes in ``[0, M)``, ``viewpoints`` ``(N,)`` viewpoint angles in
    radians (SCENARIO_FORMAT.md), ``scores`` ``(N, M)`` the classifier outputs; ``num_classes``
    defaults to ``M``. Every class needs at least 2 samples.

    Minimizes :func:`mean_nll` plus ``‖W‖² / (2 σ_w² N)`` over the weight matrices ``W``
    (``σ_w = weight_prior_std``; ``None`` for plain maximum likelihood): the MAP estimate under a
    Gaussian prior on the weights, whose pull fades as ``N`` grows. Full-batch ``optimistix.BFGS``
    starts from the constant per-class Gaussian fit and stops when an accepted step changes the
    weights (RMS) and the objective by less than ``atol + rtol·|value|``, or after ``max_steps``
    (then a ``RuntimeWarning`` says so and the last iterate is returned). Deterministic: the same
    data and ``seed`` give the same weights.
    """
    classes, viewpoints, scores, m = _check_samples(classes, viewpoints, scores, num_classes)
    if weight_prior_std is not None and not weight_prior_std > 0:
        raise ValueError(f"weight_prior_std: expected a positive number or None, got {weight_prior_std!r}")
    model = _start_at_constant_fit(Learned(m, hidden, key=jax.random.PRNGKey(seed)), classes, scores)
    params, skeleton = eqx.partition(model, eqx.is_inexact_array)
    # One flat vector: BFGS keeps a dense inverse Hessian, on a flat y a single P x P matrix
    # instead of one block per pair of weight arrays.
    flat, unravel = ravel_pytree(params)
    # Without the prior the covariance heads chase sampling noise (docs/learned_classifier.md).
    decay = 0.0 if weight_prior_std is None else 0.5 / (weight_prior_std**2 * classes.shape[0])
    data = (jnp.asarray(classes), jnp.asarray(viewpoints), jnp.asarray(scores))
    args = (unravel, skeleton, jnp.asarray(decay), data)
    # The RMS norm: with the default max norm one weight wandering along a flat direction of the
    # network keeps the solve going long after the objective has settled.
    solver: optx.AbstractMinimiser = optx.BFGS(rtol=rtol, atol=atol, norm=optx.rms_norm)
    solution: optx.Solution = optx.minimise(_objective, solver, flat, args, max_steps=max_steps, throw=False)
    fitted = eqx.combine(unravel(solution.value), skeleton)
    final = float(mean_nll(fitted, *data))
    if not math.isfinite(final):
        raise ValueError(f"fit_classifier: the fit diverged (mean NLL {final}); try another seed or smaller hidden layers")
    if not bool(solution.result == optx.RESULTS.successful):
        why = (
            f"reached max_steps={max_steps}"
            if bool(solution.result == optx.RESULTS.max_steps_reached)
            else optx.RESULTS[solution.result]  # type: ignore[misc]  # RESULTS[...] is its message
        )
        warnings.warn(
            f"fit_classifier: BFGS stopped before meeting rtol/atol ({why}); returning the last "
            f"iterate, mean NLL {final:.6g}",
            RuntimeWarning,
            stacklevel=2,
        )
    return fitted


# --------------------------------------------------------------------------- #
# Files
# --------------------------------------------------------------------------- #


def save_classifier(model: Learned, path: str | os.PathLike) -> None:
    """Write ``model`` to ``path``: one JSON header line, then the weights (``.eqx`` leaves)."""
    if not isinstance(model, Learned):
        raise TypeError(f"save_classifier: expected a Learned model, got {type(model).__name__}")
    header = {"format": FILE_FORMAT, "num_classes": model.num_classes, "hidden": list(model.hidden),
              "activation": "tanh", "input": "cos_sin_viewpoint"}
    with open(path, "wb") as f:
        f.write((json.dumps(header) + "\n").encode())
        eqx.tree_serialise_leaves(f, model)


def load_classifier(path: str | os.PathLike) -> Learned:
    """Read a model written by :func:`save_classifier`.

    Raises ``ValueError`` naming ``path`` and what is wrong (missing file, not a learned-classifier
    file, weights truncated or not matching the header, non-finite weights).
    """
    where = repr(os.fspath(path))

    def fail(what: str, cause: BaseException | None = None) -> NoReturn:
        raise ValueError(f"learned classifier {where}: {what}") from cause

    try:
        f = open(path, "rb")
    except OSError as e:
        fail(f"cannot read: {e.strerror or e}", e)
    with f:
        try:
            header = json.loads(f.readline(4096).decode())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            fail(f"not a {FILE_FORMAT} file (no JSON header line)", e)
        if not isinstance(header, dict) or header.get("format") != FILE_FORMAT:
            got = header.get("format") if isinstance(header, dict) else header
            fail(f"expected format {FILE_FORMAT!r}, got {got!r}")
        m, hidden = header.get("num_classes"), header.get("hidden")
        if not (isinstance(m, int) and m >= 1):
            fail(f"header num_classes: expected a positive integer, got {m!r}")
        if not (isinstance(hidden, list) and all(isinstance(h, int) and h >= 1 for h in hidden)):
            fail(f"header hidden: expected a list of positive layer widths, got {hidden!r}")
        if header.get("activation", "tanh") != "tanh":
            fail(f"header activation: only 'tanh' is supported, got {header['activation']!r}")
        like = eqx.filter_eval_shape(Learned, m, tuple(hidden), key=jax.random.PRNGKey(0))
        try:
            model = eqx.tree_deserialise_leaves(f, like)
        except (ValueError, EOFError, OSError, RuntimeError, TypeError) as e:
            fail(f"weights are truncated or do not match the header (num_classes={m}, hidden={hidden})", e)
        if f.read(1):
            fail("trailing data after the weights (weights do not match the header?)")
    if not all(bool(jnp.all(jnp.isfinite(a))) for a in jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))):
        fail("weights are not all finite")
    return model
