"""The summary tables the study commands print (``sweep``, ``demo``)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .common import fmt


def _mean(rows: Sequence[dict], key: str) -> float:
    vals = []
    for r in rows:
        v = r.get(key)
        if v is None or v == "":
            continue
        v = float(v)
        if not math.isnan(v):
            vals.append(v)
    return float(np.mean(vals)) if vals else math.nan


def summary_table(rows: Sequence[dict], models: Sequence[str]) -> str:
    """Per model: the mean over tracks of each metric at each track's last step, and the mean step
    time where the rows carry one (``step_ms``; batched file studies do not)."""
    header = (f"{'model':<12} {'tracks':>6} {'H(w)':>8} {'det_cov':>11} {'err_wmax':>9} "
              f"{'err_wavg':>9} {'comps':>6} {'step_ms':>8}")
    lines = [header, "-" * len(header)]
    for model in models:
        mine = [r for r in rows if r["model"] == model]
        if not mine:
            continue
        last: dict = {}
        for r in mine:  # each track's (scenario's) last step
            track = r.get("scenario", r.get("track"))
            if track not in last or int(r["step"]) > int(last[track]["step"]):
                last[track] = r
        final = list(last.values())
        lines.append(
            f"{model:<12} {len(final):>6} {fmt(_mean(final, 'entropy'), '.4f'):>8} "
            f"{fmt(_mean(final, 'det_cov'), '.4e'):>11} {fmt(_mean(final, 'err_wmax'), '.4f'):>9} "
            f"{fmt(_mean(final, 'err_wavg'), '.4f'):>9} {fmt(_mean(final, 'num_components'), '.2f'):>6} "
            f"{fmt(_mean(mine, 'step_ms'), '.1f'):>8}"
        )
    return "\n".join(lines)


def alpha_summary(rows: Sequence[dict]) -> str:
    """Per (alpha, model): mean ± 95% half-width over tracks of each track's mean over its steps."""
    # Imported here: matplotlib costs every other command 0.3-0.5 s of start-up.
    from ..analysis import plot

    header = f"{'alpha':>6} {'model':<12} {'tracks':>6} {'H(w)':>15} {'det_cov':>11} {'err_wmax':>15} {'err_wavg':>15}"
    lines = [header, "-" * len(header)]
    curves = {m: plot.alpha_curves(rows, m) for m in ("entropy", "det_cov", "err_wmax", "err_wavg")}
    models = list(dict.fromkeys(str(r["model"]) for r in rows))
    alphas = sorted({float(r["alpha"]) for r in rows})
    for a in alphas:
        for model in models:
            cells = []
            for metric, spec in (("entropy", ".3f"), ("det_cov", ".3e"), ("err_wmax", ".3f"), ("err_wavg", ".3f")):
                xs, values = curves[metric][model]
                j = int(np.searchsorted(xs, a))
                mean, half = plot.mean_band(values[:, j : j + 1])
                text = fmt(float(mean[0]), spec)
                if metric != "det_cov" and not math.isnan(float(half[0])):
                    text += f" ±{float(half[0]):.3f}"
                cells.append(text)
            n = curves["entropy"][model][1].shape[0]
            lines.append(f"{a:>6g} {model:<12} {n:>6} {cells[0]:>15} {cells[1]:>11} {cells[2]:>15} {cells[3]:>15}")
    return "\n".join(lines)
