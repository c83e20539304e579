"""Fit a learned viewpoint-dependent classifier model (Eq. 2) from logged samples.

    python scripts/fit_classifier.py samples.csv -o model.eqx [--hidden 16,16] [--seed 0]
    python scripts/fit_classifier.py samples.npz -o model.eqx
    python scripts/fit_classifier.py --simulate-mirror 4000 [--alpha 0.25 --K 15] -o model.eqx

A CSV has a header row with the columns ``class,viewpoint,score_0,...,score_{M-1}`` (viewpoint
angle in radians, SCENARIO_FORMAT.md; other columns are ignored); an NPZ holds the arrays
``classes`` (N,), ``viewpoints`` (N,) and ``scores`` (N, M). ``--simulate-mirror N`` draws N samples
from the paper's mirror model (Eq. 18) instead, so the fit can be checked against the truth.
Prints the final mean negative log-likelihood and, when simulated, the fitted vs true mean and
covariance at a few viewpoints. Use the model file in a scenario as
``"classifier": {"model": "learned", "path": "model.eqx"}`` (docs/learned_classifier.md).
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import sys
import time
from typing import NoReturn

import jax
import jax.numpy as jnp
import numpy as np

import hybridslam as hs
from hybridslam.models.learned import mean_nll, sample_scores, viewpoint_features

hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

Samples = tuple[np.ndarray, np.ndarray, np.ndarray]


def _error(message: str) -> NoReturn:
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def read_csv(path: str) -> Samples:
    """``class,viewpoint,score_0,...`` rows; errors name the file, line and column."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        _error(f"{path}: cannot read: {getattr(e, 'strerror', None) or e}")
    if not rows:
        _error(f"{path}: empty file (expected a header row class,viewpoint,score_0,...)")
    header = [h.strip() for h in rows[0]]
    score_cols = sorted((int(m.group(1)) for h in header if (m := re.fullmatch(r"score_(\d+)", h))))
    missing = [c for c in ("class", "viewpoint") if c not in header]
    if not score_cols:
        missing.append("score_0")
    elif score_cols != list(range(len(score_cols))):
        gap = next(i for i in range(len(score_cols) + 1) if i not in score_cols)
        missing.append(f"score_{gap}")
    if missing:
        _error(f"{path}: missing column(s) {', '.join(missing)} (header: {','.join(header)})")
    names = ["class", "viewpoint", *(f"score_{i}" for i in score_cols)]
    index = [header.index(n) for n in names]
    data = np.empty((len(rows) - 1, len(names)))
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            _error(f"{path}:{line}: expected {len(header)} fields, got {len(row)}")
        for j, (name, i) in enumerate(zip(names, index)):
            try:
                data[line - 2, j] = float(row[i])
            except ValueError:
                _error(f"{path}:{line}: column {name}: expected a number, got {row[i]!r}")
    if len(data) == 0:
        _error(f"{path}: no samples after the header")
    classes = data[:, 0]
    bad = np.flatnonzero(classes != np.round(classes))
    if bad.size:
        _error(f"{path}:{bad[0] + 2}: column class: expected an integer, got {classes[bad[0]]!r}")
    return classes.astype(np.int64), data[:, 1], data[:, 2:]


def read_npz(path: str) -> Samples:
    """Arrays ``classes`` (N,), ``viewpoints`` (N,), ``scores`` (N, M)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            missing = [k for k in ("classes", "viewpoints", "scores") if k not in f.files]
            if missing:
                _error(f"{path}: missing array(s) {', '.join(missing)} (has: {', '.join(f.files) or 'none'})")
            return f["classes"], f["viewpoints"], f["scores"]
    except (OSError, ValueError) as e:
        _error(f"{path}: cannot read as .npz: {getattr(e, 'strerror', None) or e}")


def write_csv(path: str, samples: Samples) -> None:
    classes, viewpoints, scores = (np.asarray(a) for a in samples)
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["class", "viewpoint", *(f"score_{i}" for i in range(scores.shape[1]))])
        for c, v, z in zip(classes, viewpoints, scores):
            w.writerow([int(c), repr(float(v)), *(repr(float(x)) for x in z)])


def _covariances(model: hs.ClassifierModel, features: jnp.ndarray) -> jnp.ndarray:
    r = jax.vmap(model.class_sqrt_informations)(features)
    return jnp.linalg.inv(jnp.swapaxes(r, -1, -2) @ r)  # Σ_c = (R_cᵀ R_c)⁻¹


def compare(fitted: hs.ClassifierModel, true: hs.ClassifierModel) -> None:
    """Fitted vs true h_c and Σ_c at a few viewpoints, then the worst errors over 72 viewpoints."""
    fmt = lambda a: "[" + ", ".join(f"{x:7.4f}" for x in np.ravel(a)) + "]"  # noqa: E731
    degrees = np.array([0.0, 45.0, 90.0, 135.0, 180.0])
    feats = viewpoint_features(np.deg2rad(degrees))
    h_fit, h_true = jax.vmap(fitted.class_means)(feats), jax.vmap(true.class_means)(feats)
    s_fit, s_true = _covariances(fitted, feats), _covariances(true, feats)
    print("\nclass  viewpoint  mean fitted          mean true            cov fitted (row-major)"
          "                cov true")
    for c in range(true.num_classes):
        for i, deg in enumerate(degrees):
            print(f"{c:5d}  {deg:7.0f}°  {fmt(h_fit[i, c]):20s} {fmt(h_true[i, c]):20s} "
                  f"{fmt(s_fit[i, c]):37s} {fmt(s_true[i, c])}")
    grid = viewpoint_features(jnp.linspace(-jnp.pi, jnp.pi, 72, endpoint=False))
    err = jnp.abs(jax.vmap(fitted.class_means)(grid) - jax.vmap(true.class_means)(grid))
    s_fit, s_true = _covariances(fitted, grid), _covariances(true, grid)
    rel = jnp.linalg.norm(s_fit - s_true, axis=(-2, -1)) / jnp.linalg.norm(s_true, axis=(-2, -1))
    print(f"\nover 72 viewpoints x {true.num_classes} classes: mean |h error| {float(err.mean()):.4f} "
          f"(max {float(err.max()):.4f}); covariance relative error ‖ΔΣ‖_F/‖Σ‖_F "
          f"mean {float(rel.mean()):.3f} (max {float(rel.max()):.3f})")


def _hidden(text: str) -> tuple[int, ...]:
    try:
        widths = tuple(int(w) for w in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated layer widths like 16,16, got {text!r}") from None
    if not widths or min(widths) < 1:
        raise argparse.ArgumentTypeError(f"expected positive layer widths, got {text!r}")
    return widths


def _prior(text: str) -> float | None:
    if text.lower() == "none":
        return None
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number or 'none', got {text!r}")
    return value


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("samples", nargs="?", help="samples file (.csv or .npz)")
    p.add_argument("-o", "--output", required=True, help="model file to write (e.g. model.eqx)")
    p.add_argument("--hidden", type=_hidden, default=(16, 16), help="hidden layer widths (default 16,16)")
    p.add_argument("--seed", type=int, default=0, help="initial weights (and simulated samples)")
    p.add_argument("--weight-prior-std", type=_prior, default=0.35,
                   help="σ_w of the Gaussian prior on the weights; 'none' for plain maximum likelihood")
    p.add_argument("--max-steps", type=int, default=2000, help="BFGS step budget")
    p.add_argument("--simulate-mirror", type=int, metavar="N", help="fit N samples drawn from the mirror model")
    p.add_argument("--alpha", type=float, default=0.25, help="mirror model alpha (Eq. 18)")
    p.add_argument("--K", type=float, default=15.0, help="mirror model K (Eq. 18)")
    p.add_argument("--write-samples", metavar="CSV", help="also write the simulated samples as CSV")
    args = p.parse_args(argv)

    true = None
    if (args.samples is None) == (args.simulate_mirror is None):
        p.error("give a samples file or --simulate-mirror N (not both)")
    if args.simulate_mirror is not None:
        if args.simulate_mirror < 4:
            p.error("--simulate-mirror: expected at least 4 samples")
        if not (math.isfinite(args.K) and args.K > 0 and math.isfinite(args.alpha)):
            p.error("--alpha must be finite and --K positive")
        true = hs.Mirror(args.alpha, args.K)
        samples = sample_scores(true, args.simulate_mirror, jax.random.PRNGKey(args.seed))
        source = f"{args.simulate_mirror} samples from mirror(alpha={args.alpha:g}, K={args.K:g})"
        if args.write_samples:
            write_csv(args.write_samples, samples)
            source += f", written to {args.write_samples}"
    elif args.samples.endswith(".npz"):
        samples, source = read_npz(args.samples), args.samples
    elif args.samples.endswith(".csv"):
        samples, source = read_csv(args.samples), args.samples
    else:
        p.error(f"{args.samples}: expected a .csv or .npz file")

    classes, viewpoints, scores = (np.asarray(a) for a in samples)
    if scores.ndim != 2:
        _error(f"{source}: scores: expected an (N, M) array, got shape {scores.shape}")
    print(f"{source}: {scores.shape[0]} samples, {scores.shape[1]} classes; "
          f"hidden={','.join(map(str, args.hidden))}, seed={args.seed}, weight_prior_std={args.weight_prior_std}")
    t0 = time.perf_counter()
    try:
        model = hs.fit_classifier(classes, viewpoints, scores, hidden=args.hidden, seed=args.seed,
                                  weight_prior_std=args.weight_prior_std, max_steps=args.max_steps)
    except ValueError as e:
        _error(f"{source}: {e}")
    jax.block_until_ready(model)
    seconds = time.perf_counter() - t0
    nll = float(mean_nll(model, classes, viewpoints, scores))
    line = f"fit in {seconds:.1f} s (compile included); final mean NLL {nll:.4f}"
    if true is not None:
        line += f" (true model on the same samples: {float(mean_nll(true, classes, viewpoints, scores)):.4f})"
    print(line)
    try:
        hs.save_classifier(model, args.output)
    except OSError as e:
        _error(f"{args.output}: cannot write: {e.strerror or e}")
    print(f"wrote {args.output}")
    if true is not None:
        compare(model, true)


if __name__ == "__main__":
    main()
