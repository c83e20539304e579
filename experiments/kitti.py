"""Real semantic data: every estimator on KITTI tracking with PointRCNN class scores (issue 45 §4-5).

Sequences are imported with :func:`hybridslam.datasets.kitti.import_kitti` (every ``--every``-th
frame, ``--max-range`` m, ground-truth increments with wheel-odometry-level noise: ORB-SLAM3 is
itself a SLAM estimate from the same cameras, whose errors are correlated in time, while the
noisy-truth odometry is white noise with a known covariance, what the estimators assume;
docs/studies/kitti.md). The map is known (the static labelled objects as priors) or unknown.

1. **Classifier models** (Eq. 2) fitted on the samples of ``--train`` sequences
   (:mod:`hybridslam.datasets.kitti_classifier`): ``learned`` (viewpoint-dependent MLP) and
   ``viewpoint-free``; their held-out log-likelihood on the study sequences beside ``none``
   (``classifier.csv``). The model files go to ``OUTPUT/models`` (derived from licensed data: not
   for the repository).
2. **Cells** (sequence, map, estimator): ``hybrid:learned``, ``hybrid:viewpoint-free``,
   ``hybrid:none`` (the hybrid belief with each classifier model), ``ml``, ``gpda``,
   ``max-mixture``, ``multimodal`` (with the learned model), ``isam2`` (``scripts/isam2_baseline.py``:
   iSAM2 + nearest neighbour, geometry only) and ``oracle`` (the same iSAM2 with every detection's
   true association, detections of no static object removed: the true-association limit).
   Per cell: APE / RPE of the online estimate and of the smoothed trajectory (no alignment: x_0 is
   the ground truth), map error (smoothed objects), right associations (a detection of a static
   object associated with it, a clutter detection, i.e. of a moving or unlabelled object, left
   unassociated; over all detections of the final best component's history) and the accuracy on
   static objects' detections alone, the mean association entropy, and the median ms per step.

Writes ``OUTPUT/cells.jsonl`` (one record per cell; a rerun skips the cells present),
``OUTPUT/results/ESTIMATOR/NNNN-MAP.json`` (result files), ``OUTPUT/kitti.csv``, prints the table as markdown and draws ``OUTPUT/kitti_NNNN.png``.

    python experiments/kitti.py --data /work/data/kitti -o runs/kitti [--sequences 6,8,10]
        [--train 0,1,2,3,4,5] [--every 2] [--max-range 30] [--maps known,unknown]
        [--estimators hybrid:learned,...] [--figure-sequence 10] [--redo] [--report-only]
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import math
import os
import time

import numpy as np
from matplotlib.figure import Figure

from hybridslam import driver
from hybridslam.analysis import trajectory
from hybridslam.analysis.map_error import map_error
from hybridslam.cli import cache
from hybridslam.datasets import kitti
from hybridslam.datasets.kitti_classifier import fit_kitti_models, heldout_scores
from hybridslam.estimators import make_estimator
from hybridslam.io.result import Result, load_result, parse_result, save_result
from hybridslam.io.scenario import Classifier, Scenario, Step, save_scenario
from hybridslam.models.learned import load_classifier, save_classifier

ESTIMATORS = ("odometry", "hybrid:learned", "hybrid:viewpoint-free", "hybrid:none", "ml", "gpda", "max-mixture",
              "multimodal", "isam2", "oracle")
MAIN = ("odometry", "hybrid:learned", "hybrid:none", "ml", "max-mixture", "multimodal", "isam2", "oracle")
SETTINGS: dict[str, dict] = {
    "ml": {}, "gpda": {}, "max-mixture": {},
    "multimodal": {"capacity": 16},
    "hybrid": {"capacity": 16, "gate": 3, "weights": "linearized"},
}
CLUTTER = ("hybrid", "multimodal")  # estimators with a clutter hypothesis (known map)


def _isam2():
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scripts", "isam2_baseline.py")
    spec = importlib.util.spec_from_file_location("isam2_baseline", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def fit_models(data: str, train, study, folder: str) -> dict[str, str]:
    """Fit (or reuse) the two classifier models; write classifier.csv; return their paths."""
    paths = {name: os.path.join(folder, "models", f"{name}.eqx") for name in ("learned", "viewpoint-free")}
    if all(os.path.exists(p) for p in paths.values()):
        return paths
    os.makedirs(os.path.dirname(paths["learned"]), exist_ok=True)
    t0 = time.perf_counter()
    train_samples = kitti.classifier_samples(data, train)
    held = kitti.classifier_samples(data, study)
    models = fit_kitti_models(*train_samples)
    for name, model in models.items():
        save_classifier(model, paths[name])
    rows = heldout_scores(models, *held)
    with open(os.path.join(folder, "classifier.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, ["model", "log_density", "class_log_posterior", "train_samples", "heldout_samples"])
        w.writeheader()
        for r in rows:
            w.writerow({**r, "train_samples": len(train_samples[0]), "heldout_samples": len(held[0])})
    print(f"classifier models fitted on {len(train_samples[0])} samples (sequences {list(train)}) in "
          f"{time.perf_counter() - t0:.0f} s; held out: {len(held[0])} samples of {list(study)}")
    for r in rows:
        print(f"  {r['model']:>15}: log density {r['log_density']:.3f} nats, log P(true class) "
              f"{r['class_log_posterior']:.4f}")
    return paths


def scenario_for(data: str, folder: str, sequence: int, map_: str, every: int, max_range: float) -> Scenario:
    path = os.path.join(folder, "scenarios", f"{sequence:04d}-{map_}.json")
    s = kitti.import_kitti(data, sequence, unknown_map=map_ == "unknown", every=every, max_range=max_range)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    save_scenario(s, path)
    return s


def oracle_scenario(s: Scenario) -> Scenario:
    """Only the detections of static objects: the true-association limit's input."""
    return s.replace(steps=tuple(Step(st.odometry, tuple(d for d in st.detections if d.true_object is not None))
                                 for st in s.steps))


def associations(s: Scenario, result: Result) -> dict:
    """Right associations of the final best component (module docstring)."""
    final = result.steps[-1].components[0].associations
    known = s.discovery is None
    right = total = static_right = static_total = 0
    votes: dict[int, dict[int, int]] = {}
    for j, st in enumerate(s.steps):
        for i, d in enumerate(st.detections):
            o = int(final[j][i]) if i < len(final[j]) else -1
            if d.true_object is not None and o >= 0:
                votes.setdefault(o, {}).setdefault(d.true_object, 0)
                votes[o][d.true_object] += 1
    owner = {o: max(v, key=lambda t: (v[t], -t)) for o, v in votes.items()}  # unknown map: majority object
    for j, st in enumerate(s.steps):
        for i, d in enumerate(st.detections):
            o = int(final[j][i]) if i < len(final[j]) else -1
            total += 1
            if d.true_object is None:
                right += o < 0
                continue
            ok = o >= 0 and (o == d.true_object if known else owner.get(o) == d.true_object)
            right += ok
            static_right += ok
            static_total += 1
    return {"right": right / total if total else math.nan,
            "static_accuracy": static_right / static_total if static_total else math.nan,
            "detections": total, "static_detections": static_total}


def evaluate(s: Scenario, result: Result, truth_scenario: Scenario | None = None) -> dict:
    ref = s.true_robot_poses[1:]
    online = np.array([st.components[0].pose_mean for st in result.steps])
    out: dict = {"online": trajectory.trajectory_errors(ref, online)}
    if result.trajectory is not None:
        out["smoothed"] = trajectory.trajectory_errors(ref, np.asarray(result.trajectory)[1:])
    out["map_error"] = map_error(truth_scenario or s, result) if result.objects is not None else {}
    out["association"] = associations(truth_scenario or s, result)
    out["entropy"] = float(np.mean([st.metrics["entropy"] for st in result.steps]))
    step_s = np.asarray((result.timing or {}).get("step_s", [math.nan]))
    out["step_ms_median"] = 1e3 * float(np.median(step_s))
    return out


def run_cell(s: Scenario, name: str, models: dict[str, str]) -> tuple[dict, Result | None]:
    if name == "odometry":  # dead reckoning: the odometry composed from x_0
        poses = [s.robot_prior_mean]
        for st in s.steps:
            poses.append(kitti.compose(poses[-1], st.odometry))
        return {"online": trajectory.trajectory_errors(s.true_robot_poses[1:], np.array(poses[1:]))}, None
    if name in ("isam2", "oracle"):
        base = oracle_scenario(s) if name == "oracle" else s
        obj, _ = _isam2().run(base, true_associations=name == "oracle")
        result = parse_result(obj)
        return evaluate(base, result), result
    est, _, model = name.partition(":")
    model = model or "learned"
    classifier = Classifier("none") if model == "none" else Classifier("learned", path=os.path.abspath(models[model]))
    options = dict(SETTINGS[est])
    if est in CLUTTER and s.discovery is None:
        options["clutter"] = -math.log(s.max_range * s.fov)  # uniform over the sensor footprint
    scenario = s.replace(classifier=classifier)
    run = driver.run(make_estimator(est, **options), scenario)
    return evaluate(scenario, run.result), run.result


def _stat(d: dict, *keys, default=math.nan):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


def row(r: dict) -> dict:
    m = r.get("metrics", {})
    return {"sequence": r["sequence"], "map": r["map"], "estimator": r["estimator"], "error": r.get("error", ""),
            "ape_online_m": _stat(m, "online", "ape_translation", "mean"),
            "ape_smoothed_m": _stat(m, "smoothed", "ape_translation", "mean"),
            "rpe_online_m": _stat(m, "online", "rpe_translation", "mean"),
            "map_error_m": _stat(m, "map_error", "mean_m"),
            "right_assoc": _stat(m, "association", "right"),
            "static_assoc": _stat(m, "association", "static_accuracy"),
            "entropy": m.get("entropy", math.nan), "step_ms_median": m.get("step_ms_median", math.nan),
            "wall_s": r.get("wall_s", math.nan)}


def _fmt(v) -> str:
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def markdown(rows: list[dict]) -> str:
    cols = ["sequence", "map", "estimator", "ape_online_m", "ape_smoothed_m", "rpe_online_m", "map_error_m",
            "right_assoc", "static_assoc", "entropy", "step_ms_median"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r[c]) if not r["error"] or c in cols[:3] else "error" for c in cols) + " |")
    return "\n".join(lines)


def figure(s: Scenario, results: dict[str, Result], path: str, title: str) -> None:
    """Map, trajectories and the hybrid (learned) belief's associations of one sequence."""
    fig = Figure(figsize=(12, 9))
    ax, bx = fig.subplots(2, 1)
    truth = s.true_robot_poses
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=2, label="ground truth")
    dr = [truth[0]]
    for st in s.steps:
        dr.append(kitti.compose(dr[-1], st.odometry))
    dr_arr = np.array(dr)
    ax.plot(dr_arr[:, 0], dr_arr[:, 1], color="0.6", ls="--", label="odometry")
    colors = {"hybrid:learned": "tab:red", "hybrid:none": "tab:orange", "isam2": "tab:blue", "oracle": "tab:green"}
    for name, res in results.items():
        if res.trajectory is not None and name in colors:
            t = np.asarray(res.trajectory)
            ax.plot(t[:, 0], t[:, 1], color=colors[name], lw=1, label=f"{name} (smoothed)")
    objs = s.true_object_poses if s.true_object_poses is not None else np.array([p for p, _ in s.true_objects or ()])
    if len(objs):
        ax.plot(objs[:, 0], objs[:, 1], "ks", mfc="none", ms=8, label="static objects (labels)")
    res = results.get("hybrid:learned")
    if res is not None and res.objects is not None and len(res.objects):
        o = np.asarray(res.objects)
        ax.plot(o[:, 0], o[:, 1], "r+", ms=9, label="hybrid:learned objects")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{title}: map and trajectories (m)")
    ax.legend(fontsize=7, loc="best")
    # Associations of the hybrid's final best component: each detection drawn where it falls from
    # the ground-truth pose, coloured by right / wrong / clutter.
    if res is not None:
        final = res.steps[-1].components[0].associations
        ax2 = bx
        ax2.plot(truth[:, 0], truth[:, 1], "k-", lw=1)
        for j, st in enumerate(s.steps):
            x = truth[j + 1]
            for i, d in enumerate(st.detections):
                p = x[:2] + d.range * np.array([math.cos(x[2] + d.bearing), math.sin(x[2] + d.bearing)])
                o = int(final[j][i])
                if d.true_object is None:
                    c = "0.7" if o < 0 else "tab:purple"
                else:
                    c = "tab:green" if o == d.true_object or s.discovery is not None and o >= 0 else "tab:red"
                ax2.plot(p[0], p[1], ".", color=c, ms=3)
        ax2.plot([], [], ".", color="tab:green", label="static object, associated")
        ax2.plot([], [], ".", color="tab:red", label="static object, wrong / unassociated")
        ax2.plot([], [], ".", color="0.7", label="clutter, rejected")
        ax2.plot([], [], ".", color="tab:purple", label="clutter, associated")
        ax2.set_aspect("equal", adjustable="datalim")
        ax2.legend(fontsize=7, loc="best")
        ax2.set_title("hybrid:learned associations (detections from the true poses)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=os.environ.get("KITTI_DIR", "/work/data/kitti"))
    p.add_argument("-o", "--output", default=os.path.join("runs", "kitti"))
    p.add_argument("--sequences", default="6,8,10")
    p.add_argument("--train", default="0,1,2,3,4,5")
    p.add_argument("--every", type=int, default=2)
    p.add_argument("--max-range", type=float, default=30.0)
    p.add_argument("--maps", default="known,unknown")
    p.add_argument("--estimators", default=",".join(MAIN))
    p.add_argument("--figure-sequence", type=int, default=None)
    p.add_argument("--report-only", action="store_true", help="print and write the table of cells.jsonl; run nothing")
    p.add_argument("--redo", action="store_true", help="run the cells again even where cells.jsonl has them")
    a = p.parse_args(argv)
    sequences = [int(x) for x in a.sequences.split(",")]
    train = [int(x) for x in a.train.split(",")]
    names = a.estimators.split(",")
    for n in names:
        if n not in ESTIMATORS:
            p.error(f"--estimators: unknown {n!r} (known: {', '.join(ESTIMATORS)})")
    os.makedirs(a.output, exist_ok=True)
    cache.enable()  # a rerun reads the compiled steps from disk
    if not a.report_only:
        models = fit_models(a.data, train, sequences, a.output)
        for path in models.values():
            load_classifier(path)  # fails here, not in every cell, if a file is broken
    cells_path = os.path.join(a.output, "cells.jsonl")
    done: dict[tuple, dict] = {}
    if os.path.exists(cells_path):
        with open(cells_path) as f:
            for line in f:
                r = json.loads(line)
                done[(r["sequence"], r["map"], r["estimator"], r["every"], r["max_range"])] = r
    figure_seq = a.figure_sequence if a.figure_sequence is not None else sequences[-1]
    for seq in sequences if not a.report_only else ():
        for map_ in a.maps.split(","):
            s = scenario_for(a.data, a.output, seq, map_, a.every, a.max_range)
            results: dict[str, Result] = {}
            for name in names:
                key = (seq, map_, name, a.every, a.max_range)
                if key in done and not a.redo:
                    continue
                t0 = time.perf_counter()
                record: dict = {"sequence": seq, "map": map_, "estimator": name, "every": a.every,
                                "max_range": a.max_range}
                try:
                    record["metrics"], result = run_cell(s, name, models)
                    if result is not None:
                        results[name] = result
                        path = os.path.join(a.output, "results", name.replace(":", "-"), f"{seq:04d}-{map_}.json")
                        os.makedirs(os.path.dirname(path), exist_ok=True)
                        save_result(result, path)
                except Exception as e:  # noqa: BLE001 - a failing cell is a result, not a crash
                    record["error"] = f"{type(e).__name__}: {e}".splitlines()[0][:300]
                record["wall_s"] = time.perf_counter() - t0
                print(json.dumps(row(record)), flush=True)
                if key not in done or a.redo:  # the last record of a cell counts
                    with open(cells_path, "a") as f:
                        f.write(json.dumps(record) + "\n")
                done[key] = record
            if seq == figure_seq and map_ == "known":
                for name in ("hybrid:learned", "hybrid:none", "isam2", "oracle"):
                    path = os.path.join(a.output, "results", name.replace(":", "-"), f"{seq:04d}-{map_}.json")
                    if name not in results and os.path.exists(path):
                        results[name] = load_result(path)
            if seq == figure_seq and map_ == "known" and "hybrid:learned" in results:
                figure(s, results, os.path.join(a.output, f"kitti_{seq:04d}.png"), f"KITTI {seq:04d}, known map")
    rows = [row(r) for r in done.values() if r["sequence"] in sequences and r["map"] in a.maps.split(",")]
    rows.sort(key=lambda r: (r["sequence"], r["map"], ESTIMATORS.index(r["estimator"])))
    with open(os.path.join(a.output, "kitti.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
