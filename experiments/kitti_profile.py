"""Where a hybrid-belief step's time goes on a KITTI scenario: per-step wall and CPU time of variants.

Runs the hybrid belief of experiments/kitti.py (capacity 16, gate 3, linearized weights, clutter
``-log(max_range · fov)``) on one scenario file that experiments/kitti.py wrote, once per VARIANT:
``MODEL[+JSON]`` with MODEL ``learned``, ``viewpoint-free`` (files in ``MODELS``) or ``none``, and
JSON extra estimator options, e.g. ``learned+{"smoother":"filter"}``. Prints, per variant, the
median wall and CPU (process) ms per step after compilation, the distinct graphs smoothed per step
and the live components. CPU time is what a step costs the machine; on a shared machine the
wall time also holds the waits for a core (the CPU time includes XLA's worker threads).

    python experiments/kitti_profile.py runs/kitti/scenarios/0010-known.json learned \\
        'learned+{"smoother":"filter"}' none [--models runs/kitti/models]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np

import hybridslam as hs
from hybridslam import driver
from hybridslam.cli import cache
from hybridslam.estimators import make_estimator
from hybridslam.io.scenario import Classifier, load_scenario


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scenario")
    p.add_argument("variants", nargs="+")
    p.add_argument("--models", default=os.path.join("runs", "kitti", "models"))
    a = p.parse_args(argv)
    hs.setup()
    cache.enable()
    base = load_scenario(a.scenario)
    for spec in a.variants:
        model, _, extra_text = spec.partition("+")
        extra = json.loads(extra_text) if extra_text else {}
        classifier = (Classifier("none") if model == "none"
                      else Classifier("learned", path=os.path.abspath(os.path.join(a.models, f"{model}.eqx"))))
        s = base.replace(classifier=classifier)
        options = {"capacity": 16, "gate": 3, "weights": "linearized", "clutter": -math.log(s.max_range * s.fov),
                   **extra}
        cpu: list[float] = []
        last = [time.process_time()]

        def on_step(record, info, seconds, cpu=cpu, last=last):
            now = time.process_time()
            cpu.append(now - last[0])  # the step and the driver's record of it
            last[0] = now

        run = driver.run(make_estimator("hybrid", **options), s, on_step=on_step)
        timing = run.result.timing or {}
        wall_ms = 1e3 * np.asarray(timing["step_s"][1:])
        cpu_ms = 1e3 * np.asarray(cpu[1:])  # the first step's CPU time holds the compilation
        smoothed = np.array([int(getattr(i.details, "smoothings", 0)) for i in run.infos])
        alive = np.array([int(i.num_components) for i in run.infos])
        print(f"{spec}: compile {timing['compile_s']:.0f} s; per step median wall {np.median(wall_ms):.1f} ms, "
              f"CPU {np.median(cpu_ms):.1f} ms; smoothings {smoothed.mean():.2f} (max {smoothed.max()}), "
              f"components {alive.mean():.2f} (max {alive.max()})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
