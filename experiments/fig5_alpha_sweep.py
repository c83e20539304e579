"""Fig. 5 of Tchuiev et al. (2019): H(w), det Σ, x̃^wmax, x̃^wavg against alpha, with 95% bands.

The paper's statistical study (Sec. V): 50 paper-setup tracks of 10 steps from a common start;
for each alpha of Eq. 18 the scores are sampled from the ``mirror`` model with that alpha, and
the estimator runs with ``mirror`` (viewpoint-dependent), ``independent`` (viewpoint-independent,
moment-matched) and ``none`` (geometry only). Each point is the mean over tracks of the track's
mean over its steps. Resumable: the study is recorded in ``output/fig5`` (cells.jsonl, table.csv);
run it again to finish an interrupted one or to redraw. Prints the numbers it plots.

    python experiments/fig5_alpha_sweep.py [-o runs/figures] [--tracks 50] [--weights laplace-is]
"""

from __future__ import annotations

import argparse
import os

import numpy as np

import hybridslam as hs
from hybridslam.analysis import plot
from hybridslam.cli.tables import alpha_summary
from hybridslam.studies import study


hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def main(output: str = os.path.join("runs", "figures"), tracks: int = 50, steps: int = 10,
         weights: str = "laplace-is", samples: int | None = None, capacity: int = 16) -> str:
    """Run (or resume) the study, draw ``output/fig5_alpha_sweep.png``; return the path."""
    estimator = hs.make_estimator("hybrid", weights=weights, samples=samples, capacity=capacity)
    spec = study.AlphaStudy(tracks=tracks, steps=steps, estimator=estimator)
    folder = os.path.join(output, "fig5")

    def on_cell(label: str, record: dict | None) -> None:
        if record is not None:
            print(f"  {label}: compile {record['compile_s']:.1f} s, run {record['run_s']:.1f} s", flush=True)
            for line in study.cell_warnings(record):
                print(f"  WARNING {label}: {line}")

    rows = study.run_alpha_study(spec, folder, on_cell=on_cell)
    path = os.path.join(output, "fig5_alpha_sweep.png")
    plot.plot_alpha_sweep(rows, path, title=f"Fig. 5: {tracks} tracks x {steps} steps, weights {weights}")
    print(f"\nmean over {tracks} tracks of each track's mean over steps 1-{steps} (± 95% half-width)")
    print(alpha_summary(rows))
    print("\npaired over tracks (same trajectories and scores), mirror minus none: mean ± 95% half-width "
          "(share of tracks where mirror is lower)")
    for metric in ("entropy", "det_cov", "err_wmax", "err_wavg"):
        curves = plot.alpha_curves(rows, metric)
        alphas, mirror = curves["mirror"]
        diff = mirror - curves["none"][1]
        half = 1.96 * np.std(diff, axis=0, ddof=1) / np.sqrt(diff.shape[0])
        cells = [f"{a:g}: {d:+.3g} ±{h:.2g} ({100 * np.mean(diff[:, j] < 0):.0f}%)"
                 for j, (a, d, h) in enumerate(zip(alphas, diff.mean(axis=0), half))]
        print(f"  {metric:<9} " + "; ".join(cells))
    print(f"wrote {path} (table: {os.path.join(folder, study.TABLE)})")
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", default=os.path.join("runs", "figures"))
    parser.add_argument("--tracks", type=int, default=50)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--weights", default="laplace-is", choices=("laplace-is", "sampled", "linearized"))
    parser.add_argument("--samples", type=int, default=None)
    parser.add_argument("--capacity", type=int, default=16)
    a = parser.parse_args()
    main(a.output, a.tracks, a.steps, a.weights, a.samples, a.capacity)
