"""Seed-to-seed stability of the association weights: sampled (Eq. 16) vs laplace-is (vs linearized).

On paper-layout scenarios with the paper's broad robot prior (Σ_p = diag(100, 100, 0.04)), each
weight method is run twice with different seeds on the same files. Per step we compare the two
association posteriors P(β_1:k | H_k) (Eq. 8): whether their top hypotheses agree, and their
total-variation distance. Each method is also compared with a reference: laplace-is with 1024
draws per child. Prints a table; asserts nothing.

    python scripts/weights_stability.py [--scenarios 10] [--steps 10] [--classifiers mirror none]
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict

from tqdm import tqdm

import hybridslam as hs


hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def association_posteriors(result: hs.Result) -> list[dict[tuple, float]]:
    """Per step, P(β_1:k | H_k): component weights summed over class realizations (Eq. 8)."""
    out = []
    for record in result.steps:
        p: dict[tuple, float] = defaultdict(float)
        for c in record.components:
            p[tuple(tuple(a) for a in c.associations)] += c.weight
        out.append(dict(p))
    return out


def compare(a: list[dict], b: list[dict]) -> tuple[list[bool], list[float]]:
    agree, tv = [], []
    for p, q in zip(a, b):
        agree.append(max(p, key=p.get) == max(q, key=q.get))
        tv.append(0.5 * sum(abs(p.get(h, 0.0) - q.get(h, 0.0)) for h in set(p) | set(q)))
    return agree, tv


def run(scenario: hs.Scenario, classifier: str, weights: str, seed: int, samples: int | None = None) -> list[dict]:
    """Association posteriors of one run (capacity 64; ``samples``: the draws of the weight method,
    ``None`` for its default)."""
    result = hs.run_estimator(
        scenario, "hybrid", classifier=classifier, weights=weights, samples=samples, seed=seed, capacity=64,
        max_detections=2,
    ).result
    return association_posteriors(result)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", type=int, default=10, help="simulated tracks per classifier")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--classifiers", nargs="+", default=["mirror", "none"])
    parser.add_argument("--methods", nargs="+", default=["sampled", "laplace-is", "linearized"])
    parser.add_argument("--accuracy", type=int, default=4, help="scenarios for the accuracy-vs-draws table (0: skip)")
    args = parser.parse_args()

    cases = [(seed, clf) for clf in args.classifiers for seed in range(args.scenarios)]
    stats: dict[str, dict[str, list]] = {m: defaultdict(list) for m in args.methods}
    for seed, clf in tqdm(cases, desc="scenarios"):
        scenario = hs.simulate(1000 + seed, steps=args.steps)
        reference = run(scenario, clf, "laplace-is", 0, samples=1024)
        for method in args.methods:
            first = run(scenario, clf, method, 1)
            second = run(scenario, clf, method, 2)
            agree, tv = compare(first, second)
            ref_agree, ref_tv = compare(first, reference)
            s = stats[method]
            s["agree"] += agree
            s["tv"] += tv
            s["ref_agree"] += ref_agree
            s["ref_tv"] += ref_tv
            s["unstable_cases"].append(not all(agree))

    n = len(cases)
    print(f"\n{n} scenario configurations (paper layout and prior; classifiers {', '.join(args.classifiers)}), "
          f"{args.steps} steps each; seed 1 vs seed 2; reference: laplace-is, 1024 draws/child")
    header = (f"{'method':>11} {'top agrees':>11} {'mean TV':>8} {'max TV':>7} {'cases w/ disagreement':>22} "
              f"{'top = ref':>10} {'mean TV ref':>12}")
    print(header)
    for method, s in stats.items():
        print(f"{method:>11} {100 * statistics.mean(s['agree']):>10.1f}% {statistics.mean(s['tv']):>8.4f} "
              f"{max(s['tv']):>7.3f} {sum(s['unstable_cases']):>12d} of {n:<7d} "
              f"{100 * statistics.mean(s['ref_agree']):>9.1f}% {statistics.mean(s['ref_tv']):>12.4f}")
    if args.accuracy:
        accuracy_table(args.accuracy, args.steps, args.classifiers)


def accuracy_table(num_scenarios: int, steps: int, classifiers: list[str]) -> None:
    """Mean TV distance to the reference as a function of the number of draws, per method."""
    draws = {"sampled": [100, 1000, 10000], "laplace-is": [16, 64, 256]}
    errors: dict[tuple[str, int], list[float]] = defaultdict(list)
    cases = [(seed, clf) for clf in classifiers for seed in range(num_scenarios)]
    for seed, clf in tqdm(cases, desc="accuracy"):
        scenario = hs.simulate(1000 + seed, steps=steps)
        reference = run(scenario, clf, "laplace-is", 0, samples=1024)
        for method, counts in draws.items():
            for n in counts:
                errors[(method, n)] += compare(run(scenario, clf, method, 1, samples=n), reference)[1]
    print(f"\naccuracy against the reference ({len(cases)} scenario configurations, {steps} steps): mean TV")
    for method, counts in draws.items():
        cells = "  ".join(f"{n:>5} draws: {statistics.mean(errors[(method, n)]):.4f}" for n in counts)
        print(f"{method:>11}  {cells}")


if __name__ == "__main__":
    main()
