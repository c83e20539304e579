"""Fig. 4 of Tchuiev et al. (2019): one 25-step example with and without the classifier model.

Top rows: the mixture posterior P(x_k | H_k) (Eq. 6) at k = 1, 5, 15, 25 as 2-sigma covariance
ellipses whose line width grows with the component weight, with the ground-truth trajectory.
Bottom row: P(β_1:k | H_k) (Eq. 8) of every association hypothesis that survives pruning in
either run, without the classifier model (``none``, blue) and with it (``mirror``, red); the
ground-truth association history is marked with a green circle. Prints, per step, the
entropy H(w) and the probability of the true association in both runs.

    python experiments/fig4_posterior.py [-o runs/figures] [--seed 6] [--steps 25]
"""

from __future__ import annotations

import argparse
import os

import numpy as np
from matplotlib.figure import Figure

import hybridslam as hs
from hybridslam.analysis.plot import plot_posterior
from hybridslam.io.result import StepRecord

hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

SHOW = (1, 5, 15, 25)
# Shorter, straighter steps than the Fig. 5 tracks, so that 25 steps stay inside the map.
SETUP = hs.PaperSetup(step_length=0.65, turn_std=0.08)
RUNS = (("none", "without classifier model (none)", "tab:blue"), ("mirror", "with classifier model (mirror)", "tab:red"))


def association_marginals(record: StepRecord) -> dict[tuple, float]:
    """P(β_1:k | H_k) (Eq. 8): component weights summed over class realizations, per history."""
    out: dict[tuple, float] = {}
    for c in record.components:
        key = tuple(tuple(a) for a in c.associations)
        out[key] = out.get(key, 0.0) + c.weight
    return out


def true_history(scenario: hs.Scenario, k: int) -> tuple:
    return tuple(tuple(int(d.true_object) for d in step.detections) for step in scenario.steps[:k])


def main(output: str = os.path.join("runs", "figures"), seed: int = 6, steps: int = 25,
         weights: str = "laplace-is") -> str:
    """Run both models on one track, draw Fig. 4 into ``output/fig4_posterior.png``; return the path."""
    scenario = hs.simulate(seed, steps=steps, setup=SETUP)
    show = [k for k in SHOW if k <= steps]
    runs = {model: hs.run_estimator(scenario, "hybrid", seed=seed, classifier=model, capacity=64,
                                    weights=weights).result
            for model, _, _ in RUNS}

    print(f"track seed {seed}, {steps} steps, weights {weights}")
    print(f"{'k':>3} {'dets':>4} | {'H(w) none':>9} {'P(true) none':>12} | {'H(w) mirror':>11} {'P(true) mirror':>14}")
    for k in range(1, steps + 1):
        cells = []
        for model, _, _ in RUNS:
            rec = runs[model].steps[k - 1]
            cells += [rec.metrics["entropy"], association_marginals(rec).get(true_history(scenario, k), 0.0)]
        print(f"{k:>3} {len(scenario.steps[k - 1].detections):>4} | {cells[0]:>9.3f} {cells[1]:>12.3f} | "
              f"{cells[2]:>11.3f} {cells[3]:>14.3f}")

    fig = Figure(figsize=(4.3 * len(show), 7.6), layout="constrained")
    grid = fig.subplots(3, len(show), squeeze=False, gridspec_kw={"height_ratios": [0.85, 0.85, 1]})
    for row, (model, label, color) in enumerate(RUNS):
        for col, k in enumerate(show):
            ax = grid[row, col]
            rec = runs[model].steps[k - 1]
            plot_posterior(ax, scenario, rec, colors=[color])
            ax.set_title(f"k = {k}, {model}: {len(rec.components)} comp., w_max = {rec.components[0].weight:.2f}",
                         fontsize=9)
            if col or row:
                ax.set_ylabel("")
            if row == 0:
                ax.set_xlabel("")
    for col, k in enumerate(show):
        ax = grid[2, col]
        marg = {model: association_marginals(runs[model].steps[k - 1]) for model, _, _ in RUNS}
        truth = true_history(scenario, k)
        hyps = sorted(set(marg["none"]) | set(marg["mirror"]), key=lambda h: -(marg["none"].get(h, 0) + marg["mirror"].get(h, 0)))
        x = np.arange(len(hyps))
        for i, (model, label, color) in enumerate(RUNS):
            ax.bar(x + (i - 0.5) * 0.4, [marg[model].get(h, 0.0) for h in hyps], 0.4, color=color, label=label)
        if truth in hyps:
            j = hyps.index(truth)
            top = max(marg[m].get(truth, 0.0) for m, _, _ in RUNS)
            ax.plot(j, top + 0.06, "o", mfc="none", mec="green", ms=12, mew=2, label="ground truth")
        ax.set_xticks(x, [f"β{j}" for j in range(len(hyps))], fontsize=7)
        ax.set_ylim(0, 1.15)
        ax.set_title(f"P(β_1:{k} | H_{k}): {len(hyps)} hypotheses", fontsize=9)
        ax.grid(True, axis="y", alpha=0.3)
        if col == 0:
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"Posterior over x_k and over data association (track seed {seed}); line width ~ weight", fontsize=11)
    os.makedirs(output, exist_ok=True)
    path = os.path.join(output, "fig4_posterior.png")
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", default=os.path.join("runs", "figures"))
    parser.add_argument("--seed", type=int, default=6)
    parser.add_argument("--steps", type=int, default=25)
    parser.add_argument("--weights", default="laplace-is", choices=("laplace-is", "sampled", "linearized"))
    a = parser.parse_args()
    main(a.output, a.seed, a.steps, a.weights)
