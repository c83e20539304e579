"""Benchmark the sweep engine on the paper's full Fig. 5 study.

6 alphas x 3 classifier models x 50 tracks x 10 steps (9000 track-steps), each (alpha, model)
cell one batched, compiled run (hybridslam.studies.batch). Prints compile time (once per program: alpha is
traced, and mirror and independent share one), the time of the batched runs, the wall time of the whole
study (simulation and host work included) and track-steps per second. Runs into a fresh temporary
folder; asserts nothing.

    python scripts/bench_sweep.py [--weights sampled --samples 1000] [--tracks 50] [--capacity 16]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import jax

import hybridslam as hs
from hybridslam.studies import study


hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--alphas", default="0,0.1,0.2,0.3,0.4,0.5")
    parser.add_argument("--models", default="mirror,independent,none")
    parser.add_argument("--tracks", type=int, default=50)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--weights", default="sampled", choices=("sampled", "laplace-is", "linearized"))
    parser.add_argument("--samples", type=int, default=1000, help="n_s (sampled) or draws per candidate (laplace-is)")
    parser.add_argument("--capacity", type=int, default=16)
    a = parser.parse_args()
    estimator = hs.make_estimator("hybrid", weights=a.weights, capacity=a.capacity,
                                  samples=a.samples if a.weights != "linearized" else None)
    spec = study.AlphaStudy(
        alphas=tuple(float(x) for x in a.alphas.split(",")), models=tuple(a.models.split(",")), tracks=a.tracks,
        steps=a.steps, estimator=estimator)
    devices = jax.devices()
    print(f"{len(spec.alphas)} alphas x {len(spec.models)} models x {spec.tracks} tracks x {spec.steps} steps; "
          f"weights={a.weights}, samples={a.samples}, capacity={a.capacity}; {len(devices)} {devices[0].platform} device(s)")
    cells: list[tuple[str, float, float, int]] = []

    def on_cell(label: str, record: dict | None) -> None:
        if record is not None:
            dropped = sum(map(sum, record["diagnostics"]["dropped_capacity"]))
            cells.append((label, record["compile_s"], record["run_s"], dropped))
            print(f"  {label:<24} compile {record['compile_s']:6.1f} s   run {record['run_s']:6.2f} s"
                  + (f"   ({dropped} hypotheses lost to capacity)" if dropped else ""), flush=True)

    with tempfile.TemporaryDirectory() as folder:
        t0 = time.perf_counter()
        rows = study.run_alpha_study(spec, folder, on_cell=on_cell)
        wall = time.perf_counter() - t0
    compile_s = sum(c[1] for c in cells)
    run_s = sum(c[2] for c in cells)
    print(f"\ntrack-steps: {len(rows)}")
    print(f"compile: {compile_s:.1f} s ({sum(c[1] > 0 for c in cells)} compiles)")
    print(f"batched runs: {run_s:.1f} s = {len(rows) / run_s:.0f} track-steps/s ({1e3 * run_s / len(rows):.2f} ms each)")
    print(f"whole study wall time: {wall:.1f} s ({wall - compile_s:.1f} s without compiles)")


if __name__ == "__main__":
    main()
