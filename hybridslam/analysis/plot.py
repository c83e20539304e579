"""Plotting helpers for scenarios, result records and metric tables (matplotlib).

Everything here draws on an ``Axes`` it is given, or builds a standalone
``matplotlib.figure.Figure`` (rendered by Agg) and saves it to a file: no pyplot, no global
backend switch, nothing is ever shown. Used by ``hybridslam demo`` and by experiment scripts.
"""

from __future__ import annotations

import math
import os
import textwrap
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ..io.result import Result, StepRecord
from ..models.scenario import Scenario

# (column of metrics.csv, panel title, log-scale y axis)
METRIC_PANELS: tuple[tuple[str, str, bool], ...] = (
    ("entropy", r"association entropy $H(w)$", False),
    ("det_cov", r"$\det \Sigma$ of $x_k$ (best component) [m$^4$]", True),
    ("err_wmax", r"$\tilde{x}^{w_{\max}}$: error of best component [m]", False),
    ("err_wavg", r"$\tilde{x}^{w_{\mathrm{avg}}}$: weighted error [m]", False),
)


def covariance_ellipse(mean2: Sequence[float] | np.ndarray, cov2: np.ndarray, nsig: float = 2.0, num: int = 64) -> np.ndarray:
    """Points ``(num, 2)`` on the ``nsig``-sigma contour of the 2-D Gaussian ``N(mean2, cov2)``.

    The curve is closed (first point == last point), ready for ``ax.plot(*pts.T)``.
    """
    cov2 = 0.5 * (np.asarray(cov2, dtype=float) + np.asarray(cov2, dtype=float).T)
    vals, vecs = np.linalg.eigh(cov2)
    radii = nsig * np.sqrt(np.clip(vals, 0.0, None))
    t = np.linspace(0.0, 2.0 * np.pi, num)
    circle = np.stack([np.cos(t), np.sin(t)], axis=-1)
    return np.asarray(mean2, dtype=float)[:2] + (circle * radii) @ vecs.T


def mean_band(values: np.ndarray, z: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
    """Mean over axis 0 (ignoring NaN) and the half-width ``z · sd / √n`` of its 95% band.

    The half-width is NaN where fewer than two values are finite.
    """
    values = np.asarray(values, dtype=float)
    n = np.sum(np.isfinite(values), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nansum(values, axis=0) / np.where(n > 0, n, np.nan)
        sq = np.nansum((values - mean) ** 2, axis=0)
        sd = np.sqrt(sq / np.where(n > 1, n - 1, np.nan))
        return mean, z * sd / np.sqrt(n)


def _number(value: object) -> float:
    """A csv cell (str or number) as float; blank or missing -> NaN."""
    if value is None or value == "":
        return math.nan
    return float(value)  # type: ignore[arg-type]


def metric_curves(
    rows: Iterable[Mapping[str, object]], metric: str
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per model: the steps and a ``(tracks, steps)`` array of ``metric`` (NaN where missing)."""
    table: dict[str, dict[tuple[int, int], float]] = {}
    for row in rows:
        key = (int(_number(row["track"])), int(_number(row["step"])))
        table.setdefault(str(row["model"]), {})[key] = _number(row.get(metric))
    curves = {}
    for model, cells in table.items():
        tracks = sorted({t for t, _ in cells})
        steps = np.array(sorted({k for _, k in cells}))
        values = np.full((len(tracks), len(steps)), np.nan)
        for (t, k), v in cells.items():
            values[tracks.index(t), np.searchsorted(steps, k)] = v
        curves[model] = (steps, values)
    return curves


# Line style per model, so that coinciding curves stay distinguishable.
_STYLES = (("-", "o"), ("--", "s"), (":", "^"), ("-.", "D"))


def _line_with_band(ax: Axes, x: np.ndarray, values: np.ndarray, i: int, label: str, log: bool) -> None:
    """Line ``i`` (color and style by index): the mean over rows of ``values`` and its 95% band."""
    mean, half = mean_band(values)
    color, (ls, marker) = f"C{i}", _STYLES[i % len(_STYLES)]
    ax.plot(x, mean, ls=ls, marker=marker, color=color, ms=4, lw=1.8, mfc="none", label=label)
    lo, hi = mean - half, mean + half
    if log:  # keep the band on the positive axis
        lo = np.where(lo > 0, lo, mean / 10.0)
    ax.fill_between(x, lo, hi, color=color, alpha=0.15, lw=0)


def plot_metrics(rows: Iterable[Mapping[str, object]], path: str | os.PathLike) -> None:
    """Four panels (H(w), det Σ, x̃^wmax, x̃^wavg) against the step, one line per model.

    ``rows`` are ``metrics.csv``-like mappings (keys ``model, track, step`` and the metric
    columns; values may be strings). Each line is the mean over tracks, with a shaded 95% band
    ``mean ± 1.96 · sd / √n`` (none for a single track). Saves the figure to ``path``.
    """
    rows = list(rows)
    models = list(dict.fromkeys(str(r["model"]) for r in rows))  # first-seen order
    fig = Figure(figsize=(11, 7.8), layout="constrained")
    axes = fig.subplots(2, 2)
    num_tracks = 0
    for ax, (metric, title, log) in zip(axes.flat, METRIC_PANELS):
        curves = metric_curves(rows, metric)
        for i, model in enumerate(models):
            steps, values = curves[model]
            num_tracks = max(num_tracks, values.shape[0])
            _line_with_band(ax, steps, values, i, model, log)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("step k")
        if log:
            ax.set_yscale("log")
        else:  # start at 0, with a margin so curves lying on 0 stay visible
            top = ax.get_ylim()[1]
            ax.set_ylim(-0.03 * top, top)
        ax.grid(True, alpha=0.3)
        ax.xaxis.get_major_locator().set_params(integer=True)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=len(models), fontsize=9,
               title=f"classifier model: mean over {num_tracks} track(s); shaded: 95% band, mean ± 1.96·sd/√n")
    fig.savefig(path, dpi=120)


def plot_map(ax: Axes, scenario: Scenario, *, trajectory: bool = True) -> None:
    """The map (prior means, and true object poses when known) and the true trajectory (dashed)."""
    prior = np.asarray(scenario.object_prior_means)
    ax.plot(prior[:, 0], prior[:, 1], "s", mfc="none", mec="0.45", ms=9, label="object prior mean")
    truth = scenario.true_object_poses
    if truth is not None:
        truth = np.asarray(truth)
        ax.plot(truth[:, 0], truth[:, 1], "ks", ms=5, label="object (true)")
        ax.quiver(truth[:, 0], truth[:, 1], np.cos(truth[:, 2]), np.sin(truth[:, 2]),
                  angles="xy", scale_units="xy", scale=1.5, width=0.004, color="k")
    heading = prior[:, 2] if truth is None else truth[:, 2]
    for n, (x, y) in enumerate(prior[:, :2]):  # label on the side away from the heading arrow
        offset = (-11 * np.cos(heading[n]) - 3, -11 * np.sin(heading[n]) - 3)
        ax.annotate(str(n), (x, y), xytext=offset, textcoords="offset points", fontsize=8, color="0.3")
    if trajectory and scenario.true_robot_poses is not None:
        poses = np.asarray(scenario.true_robot_poses)
        ax.plot(poses[:, 0], poses[:, 1], "--", color="0.2", lw=1.2, label="true trajectory")
        ax.plot(poses[0, 0], poses[0, 1], "k^", ms=6)


def plot_pose_mixture(ax: Axes, record: StepRecord, *, color: str = "C0", label: str | None = None,
                      nsig: float = 2.0, max_width: float = 3.5) -> None:
    """The robot-pose mixture of one StepRecord: an ``nsig``-sigma ellipse and a dot per component.

    Line width grows with the component weight (``0.4 + max_width · w``).
    """
    for i, c in enumerate(record.components):
        pts = covariance_ellipse(c.pose_mean[:2], np.asarray(c.pose_cov)[:2, :2], nsig)
        lw = 0.4 + max_width * c.weight
        ax.plot(pts[:, 0], pts[:, 1], "-", color=color, lw=lw, label=label if i == 0 else None)
        ax.plot(c.pose_mean[0], c.pose_mean[1], "o", color=color, ms=1.5 + 4.0 * c.weight)


def plot_posterior(ax: Axes, scenario: Scenario, record: StepRecord | Sequence[StepRecord], *,
                   colors: Sequence[str] | None = None, title: str | None = None, nsig: float = 2.0) -> None:
    """Map, true trajectory and the pose mixture of one or several StepRecords on ``ax``.

    Each record's components are drawn as ``nsig``-sigma covariance ellipses of the robot
    position (line width grows with weight), one color per record, labelled by its step; the
    true pose at that step (when known) is a cross of the same color.
    """
    records = [record] if isinstance(record, StepRecord) else list(record)
    colors = list(colors) if colors is not None else [f"C{i}" for i in range(len(records))]
    plot_map(ax, scenario)
    truth = scenario.true_robot_poses
    for rec, color in zip(records, colors):
        best = rec.components[0].weight if rec.components else float("nan")
        plot_pose_mixture(ax, rec, color=color, nsig=nsig,
                          label=f"k={rec.k}: {len(rec.components)} comp., w_max={best:.2f}")
        if truth is not None and rec.k < len(truth):
            ax.plot(truth[rec.k, 0], truth[rec.k, 1], "x", color=color, ms=9, mew=2.0)
    ax.set_aspect("equal", adjustable="box")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if title:
        ax.set_title(title, fontsize=10)


def plot_posterior_panels(scenario: Scenario, records: Mapping[str, Sequence[StepRecord]],
                          path: str | os.PathLike, nsig: float = 2.0) -> None:
    """One :func:`plot_posterior` panel per model (``records[model]`` = the steps to show); saves to ``path``.

    Panels are stacked vertically and share both axes, so models compare at a glance.
    """
    n = max(len(records), 1)
    fig = Figure(figsize=(10.5, 0.6 + 3.7 * n), layout="constrained")
    axes = fig.subplots(n, 1, squeeze=False, sharex=True, sharey=True)[:, 0]
    for ax, (model, recs) in zip(axes, records.items()):
        plot_posterior(ax, scenario, recs, nsig=nsig, title=f"classifier: {model}")
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    for ax in axes[:-1]:
        ax.set_xlabel("")
    fig.suptitle(f"Robot pose mixture: {nsig:g}-sigma ellipses, line width ~ weight; x = true pose at that step",
                 fontsize=11)
    fig.savefig(path, dpi=120, bbox_inches="tight")  # "tight" keeps the outside legends


def alpha_curves(rows: Iterable[Mapping[str, object]], metric: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per model: the alphas and a ``(tracks, alphas)`` array of each track's mean of ``metric`` over its steps.

    ``rows`` are ``table.csv``-like mappings of an alpha study (keys ``alpha, model, track, step``).
    """
    cells: dict[str, dict[float, dict[int, list[float]]]] = {}
    for row in rows:
        per_alpha = cells.setdefault(str(row["model"]), {}).setdefault(_number(row["alpha"]), {})
        per_alpha.setdefault(int(_number(row["track"])), []).append(_number(row.get(metric)))
    curves = {}
    for model, by_alpha in cells.items():
        alphas = np.array(sorted(by_alpha))
        tracks = sorted({t for a in by_alpha.values() for t in a})
        values = np.full((len(tracks), len(alphas)), np.nan)
        for j, a in enumerate(alphas):
            for t, vals in by_alpha[a].items():
                finite = [v for v in vals if math.isfinite(v)]
                values[tracks.index(t), j] = np.mean(finite) if finite else np.nan
        curves[model] = (alphas, values)
    return curves


def plot_alpha_sweep(rows: Iterable[Mapping[str, object]], path: str | os.PathLike, *, title: str | None = None) -> None:
    """The paper's Fig. 5: H(w), det Σ, x̃^wmax, x̃^wavg against alpha, one line per classifier model.

    Each point is the mean over tracks of the track's mean over its steps, with a shaded 95%
    band ``mean ± 1.96 · sd / √n`` over tracks. Saves the figure to ``path``.
    """
    rows = list(rows)
    models = list(dict.fromkeys(str(r["model"]) for r in rows))
    fig = Figure(figsize=(11, 7.8), layout="constrained")
    axes = fig.subplots(2, 2)
    num_tracks, num_steps = 0, max((int(_number(r["step"])) for r in rows), default=0)
    for ax, (metric, panel, log) in zip(axes.flat, METRIC_PANELS):
        curves = alpha_curves(rows, metric)
        for i, model in enumerate(models):
            alphas, values = curves[model]
            num_tracks = max(num_tracks, values.shape[0])
            _line_with_band(ax, alphas, values, i, model, log)
        ax.set_title(panel, fontsize=10)
        ax.set_xlabel(r"viewpoint dependence $\alpha$ (Eq. 18)")
        if log:
            ax.set_yscale("log")
        else:
            top = ax.get_ylim()[1]
            ax.set_ylim(-0.03 * top, top)
        ax.grid(True, alpha=0.3)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=max(len(models), 1), fontsize=9,
               title=f"classifier model: mean over {num_tracks} track(s) of the mean over steps 1-{num_steps}; "
                     "shaded: 95% band, mean ± 1.96·sd/√n")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=120)


def _true_landmarks(scenario: Scenario) -> tuple[np.ndarray, np.ndarray] | None:
    """True landmark positions (N, 2) and classes (N,): ``true_objects`` of an unknown map, else the objects'."""
    if scenario.true_objects is not None:
        return (np.array([p[:2] for p, _ in scenario.true_objects]).reshape(-1, 2),
                np.array([c for _, c in scenario.true_objects], dtype=int))
    if scenario.true_object_poses is not None and scenario.true_classes is not None:
        return np.asarray(scenario.true_object_poses)[:, :2], np.asarray(scenario.true_classes, dtype=int)
    return None


def plot_trajectory(ax_or_path: Axes | str | os.PathLike, scenario: Scenario, result: Result | None = None,
                    title: str | None = None, *, landmarks: tuple[np.ndarray, np.ndarray] | None = None,
                    label: str = "estimate") -> None:
    """A trajectory panel like the thesis's Fig. 5-3a-c, on an ``Axes`` or saved to a file path.

    Ground truth dashed black, the estimate (the highest-weight component's pose after each step,
    :func:`hybridslam.trajectory.trajectory_from_result`) solid, true landmarks as filled circles and
    estimated ``landmarks`` (positions ``(L, 2)``, classes ``(L,)``, class -1 = unknown: grey), when
    given, as rings, both colored by class. ``result=None`` draws the scenario alone.
    """
    from .trajectory import trajectory_from_result

    if isinstance(ax_or_path, Axes):
        ax, fig, path = ax_or_path, None, None
    else:
        fig = Figure(figsize=(8.0, 5.0), layout="constrained")
        ax, path = fig.subplots(), ax_or_path
    color = lambda c: "0.55" if c < 0 else f"C{c}"  # noqa: E731
    truth = _true_landmarks(scenario)
    if truth is not None:
        for c in np.unique(truth[1]):
            pts = truth[0][truth[1] == c]
            ax.plot(pts[:, 0], pts[:, 1], "o", color=color(c), ms=6, label=f"landmark, class {c}")
    if landmarks is not None:
        pos, cls = np.asarray(landmarks[0], dtype=float).reshape(-1, 2), np.asarray(landmarks[1], dtype=int)
        for c in np.unique(cls):
            pts = pos[cls == c]
            ax.plot(pts[:, 0], pts[:, 1], "o", mfc="none", mec=color(c), mew=1.5, ms=10,
                    label=f"estimated landmark, class {c}" if c >= 0 else "estimated landmark, class open")
    if scenario.true_robot_poses is not None:
        poses = np.asarray(scenario.true_robot_poses)
        ax.plot(poses[:, 0], poses[:, 1], "--", color="k", lw=1.2, label="ground truth")
    if result is not None and result.steps:
        _, est = trajectory_from_result(result)
        start = np.asarray(scenario.robot_prior_mean)[None, :2]
        est = np.concatenate([start, est[:, :2]])
        ax.plot(est[:, 0], est[:, 1], "-", color="C3", lw=1.5, label=label)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if title:
        ax.set_title(title, fontsize=10)
    if fig is not None and path is not None:
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
        fig.savefig(path, dpi=120)


def _objects_with_detections(result: Result) -> np.ndarray:
    """Indices of the final top component's objects that some detection is associated with."""
    top = result.steps[-1].components[0]
    named = np.concatenate([np.asarray(a, dtype=int).ravel() for a in top.associations] + [np.zeros(0, int)])
    return np.unique(named[named >= 0])


def plot_run(scenario: Scenario, result: Result, path: str | os.PathLike, *,
             title: str | None = None) -> None:
    """One run of one estimator on one figure, saved to ``path`` (what ``hybridslam run --plot`` and
    ``hybridslam plot RESULT --scenario SCENARIO`` draw).

    Left, the map (:func:`plot_trajectory`): true landmarks and trajectory, the online estimate (the
    highest-weight component's ``x_k`` after each step), and, when the result has them (smoothers),
    the smoothed trajectory ``x_0..x_T`` and the estimated objects with a detection (rings colored by
    the final component's class, grey where it is open), with the online final pose's 2-sigma ellipse. Right,
    per step ``k``: the translation error (m) of the online and smoothed estimates against the ground
    truth (when the scenario has it), and the number of components with the association entropy
    ``H(w)`` (nats). Raises ``ValueError`` when the result's steps do not match the scenario's.
    """
    if len(result.steps) != scenario.num_steps or not result.steps:
        raise ValueError(f"result: {len(result.steps)} steps, but the scenario has {scenario.num_steps}: "
                         "not a run of this scenario")
    from .trajectory import smoothed_trajectory_from_result, trajectory_from_result

    fig = Figure(figsize=(13.0, 6.0), layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=(1.7, 1.0))
    ax_map, ax_err = fig.add_subplot(grid[:, 0]), fig.add_subplot(grid[0, 1])
    ax_comp = fig.add_subplot(grid[1, 1], sharex=ax_err)
    top = result.steps[-1].components[0]
    landmarks = None
    if result.objects is not None:
        used = _objects_with_detections(result)
        used = used[used < len(result.objects)]  # objects is indexed like classes (the file format)
        landmarks = (np.asarray(result.objects, float)[used, :2], np.asarray(top.classes, dtype=int)[used])
    plot_trajectory(ax_map, scenario, result, landmarks=landmarks, label="online (best component)")
    smoothed = smoothed_trajectory_from_result(result)
    if smoothed is not None:
        poses = np.asarray(result.trajectory, dtype=float)
        ax_map.plot(poses[:, 0], poses[:, 1], "-", color="C0", lw=1.5, label="smoothed")
    ellipse = covariance_ellipse(top.pose_mean[:2], np.asarray(top.pose_cov)[:2, :2])
    ax_map.plot(ellipse[:, 0], ellipse[:, 1], "-", color="C3", lw=1.0, label="online final pose, 2 sd")
    ax_map.legend(fontsize=8, loc="best")
    stamps, online = trajectory_from_result(result)
    if scenario.true_robot_poses is not None:
        truth = np.asarray(scenario.true_robot_poses, dtype=float)
        error = lambda poses: np.linalg.norm(poses[:, :2] - truth[1:, :2], axis=1)  # noqa: E731
        ax_err.plot(stamps, error(online), "-", color="C3", label="online")
        if smoothed is not None:
            ax_err.plot(smoothed[0], error(smoothed[1]), "-", color="C0", label="smoothed (after the last step)")
        ax_err.legend(fontsize=8)
    else:
        ax_err.text(0.5, 0.5, "no ground truth in the scenario", ha="center", va="center",
                    transform=ax_err.transAxes)
    ax_err.set_ylabel("translation error [m]")
    ax_err.grid(True, alpha=0.3)
    counts = [s.metrics.get("num_components", len(s.components)) for s in result.steps]
    ax_comp.step(stamps, counts, where="mid", color="C2", label="components")
    ax_comp.set_ylabel("components", color="C2")
    ax_comp.set_xlabel("step k")
    ax_comp.grid(True, alpha=0.3)
    ax_h = ax_comp.twinx()
    entropy = [_number(s.metrics.get("entropy", math.nan)) for s in result.steps]
    ax_h.plot(stamps, entropy, ".-", color="C4")
    ax_h.set_ylabel(r"association entropy $H(w)$", color="C4")
    ax_comp.set_ylim(0, 1.15 * max(counts, default=1) + 0.5)
    ax_h.set_ylim(bottom=0)
    ax_map.set_title(title if title is not None else textwrap.fill(result.estimator, 120), fontsize=9)
    fig.savefig(path, dpi=120)
