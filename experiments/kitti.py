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

3. **Seeds** (``--seeds 0,1,2,3,4``): each cell runs once per draw of the noisy-truth odometry
   (the importer's ``seed``; detections and map are the same in every draw). Cells are keyed by
   seed; records without one (written before ``--seeds``) are seed 0.

Writes ``OUTPUT/cells.jsonl`` (one record per cell and seed; a rerun skips the cells present),
``OUTPUT/results/ESTIMATOR/NNNN-MAP[-seedS].json`` (result files), ``OUTPUT/kitti.csv`` (one row
per cell and seed), ``OUTPUT/kitti_summary.csv`` (per sequence, map and estimator: mean, sd, min
and max over the seeds), ``OUTPUT/kitti_goals.csv`` (issue 45's KITTI goals counted seed by seed:
:func:`goal_wins`), prints the tables as markdown and draws ``OUTPUT/kitti_NNNN.png`` (seed 0).

    python experiments/kitti.py --data /work/data/kitti -o runs/kitti [--sequences 6,8,10]
        [--train 0,1,2,3,4,5] [--every 2] [--max-range 30] [--maps known,unknown]
        [--estimators hybrid:learned,...] [--seeds 0,1,2] [--figure-sequence 10] [--redo] [--report-only]
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

import hybridslam as hs
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


def _tag(sequence: int, map_: str, seed: int) -> str:
    """File stem of a cell's scenario and result: seed 0 keeps the stem of single-seed runs."""
    return f"{sequence:04d}-{map_}" + (f"-seed{seed}" if seed else "")


def scenario_for(data: str, folder: str, sequence: int, map_: str, every: int, max_range: float,
                 seed: int = 0) -> Scenario:
    """Import one sequence with the odometry noise of ``seed``; write it to ``folder/scenarios``."""
    path = os.path.join(folder, "scenarios", f"{_tag(sequence, map_, seed)}.json")
    s = kitti.import_kitti(data, sequence, unknown_map=map_ == "unknown", every=every, max_range=max_range,
                           seed=seed)
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
    # The study's clutter hypothesis: the hybrid belief and multimodal on a known map, uniform over the
    # sensor footprint (the importer's default density); none for the others and on an unknown map
    # (there a detection is a known object or a new one), whatever the file declares.
    options["clutter"] = -math.log(s.max_range * s.fov) if est in CLUTTER and s.discovery is None else "none"
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
    return {"sequence": r["sequence"], "map": r["map"], "estimator": r["estimator"], "seed": r.get("seed", 0),
            "error": r.get("error", ""),
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


METRICS = ("ape_online_m", "ape_smoothed_m", "rpe_online_m", "map_error_m", "right_assoc", "static_assoc",
           "entropy", "step_ms_median")
SPREAD = ("ape_online_m", "ape_smoothed_m", "right_assoc", "static_assoc")  # shown as mean [min, max]


def cell_key(r: dict) -> tuple:
    """A cell's identity in cells.jsonl; records written before ``--seeds`` existed are seed 0."""
    return (r["sequence"], r["map"], r["estimator"], r["every"], r["max_range"], r.get("seed", 0))


def read_cells(path: str) -> dict[tuple, dict]:
    """The records of cells.jsonl by :func:`cell_key`; the last record of a cell counts."""
    done: dict[tuple, dict] = {}
    with open(path) as f:
        for n, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                r = json.loads(line)
                done[cell_key(r)] = r
            except (json.JSONDecodeError, KeyError, TypeError) as e:
                raise SystemExit(f"{path}:{n}: not a cell record ({type(e).__name__}: {e})") from None
    return done


def summarize(rows: list[dict]) -> list[dict]:
    """Per (sequence, map, estimator): each metric's mean, min and max over the seeds without error.

    A metric that is nan in a seed (e.g. no smoothed trajectory) is left out of that metric's
    statistics; ``seeds`` counts the seeds with a result, ``errors`` those that failed.
    """
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["sequence"], r["map"], r["estimator"]), []).append(r)
    out = []
    for (seq, map_, est), rs in groups.items():
        ok = [r for r in rs if not r["error"]]
        summary: dict = {"sequence": seq, "map": map_, "estimator": est, "seeds": len(ok),
                         "errors": len(rs) - len(ok), "seed_list": " ".join(str(r["seed"]) for r in sorted(rs, key=lambda r: r["seed"]))}
        for m in METRICS:
            v = np.array([r[m] for r in ok], dtype=float)
            v = v[np.isfinite(v)]
            summary[m] = float(v.mean()) if len(v) else math.nan
            summary[m + "_sd"] = float(v.std(ddof=1)) if len(v) > 1 else math.nan
            summary[m + "_min"] = float(v.min()) if len(v) else math.nan
            summary[m + "_max"] = float(v.max()) if len(v) else math.nan
        out.append(summary)
    return out


def goal_wins(rows: list[dict], model: str = "hybrid:learned") -> list[dict]:
    """Issue 45's three KITTI goals counted seed by seed, per (sequence, map).

    Over the seeds where ``model``, ``isam2``, ``hybrid:none`` and ``oracle`` all have a result:
    ``ape30_online`` / ``ape30_smoothed``: the model's APE at most 0.7 x iSAM2's (30% below);
    ``assoc_above_none``: its right associations strictly above ``hybrid:none``'s;
    ``limit15_online`` / ``limit15_smoothed``: its APE at most 1.5 x the true-association limit's.
    Each is a count of seeds; ``seeds`` is how many were compared.
    """
    by: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        if not r["error"]:
            by.setdefault((r["sequence"], r["map"], r["seed"]), {})[r["estimator"]] = r
    out: dict[tuple, dict] = {}
    for (seq, map_, seed), cells in sorted(by.items()):
        if not all(n in cells for n in (model, "isam2", "hybrid:none", "oracle")):
            continue
        h, i, n, o = cells[model], cells["isam2"], cells["hybrid:none"], cells["oracle"]
        w = out.setdefault((seq, map_), {"sequence": seq, "map": map_, "estimator": model, "seeds": 0,
                                         "ape30_online": 0, "ape30_smoothed": 0, "assoc_above_none": 0,
                                         "limit15_online": 0, "limit15_smoothed": 0})
        w["seeds"] += 1
        w["ape30_online"] += h["ape_online_m"] <= 0.7 * i["ape_online_m"]
        w["ape30_smoothed"] += h["ape_smoothed_m"] <= 0.7 * i["ape_smoothed_m"]
        w["assoc_above_none"] += h["right_assoc"] > n["right_assoc"]
        w["limit15_online"] += h["ape_online_m"] <= 1.5 * o["ape_online_m"]
        w["limit15_smoothed"] += h["ape_smoothed_m"] <= 1.5 * o["ape_smoothed_m"]
    return [{k: int(v) if isinstance(v, (bool, np.bool_)) else v for k, v in w.items()} for w in out.values()]


def _spread(s: dict, m: str) -> str:
    if s["seeds"] > 1 and m in SPREAD and math.isfinite(s[m]):
        return f"{s[m]:.3f} [{s[m + '_min']:.3f}, {s[m + '_max']:.3f}]"
    return _fmt(s[m])


def markdown_summary(summary: list[dict]) -> str:
    """The table over seeds: mean, and [min, max] for the APE and association columns."""
    cols = ["sequence", "map", "estimator", "seeds", *METRICS]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for s in summary:
        cells = [str(s[c]) + (f" ({s['errors']} failed)" if c == "seeds" and s["errors"] else "")
                 for c in cols[:4]]
        lines.append("| " + " | ".join(cells + [_spread(s, m) for m in METRICS]) + " |")
    return "\n".join(lines)


def markdown_goals(wins: list[dict]) -> str:
    cols = ["sequence", "map", "estimator", "seeds", "ape30_online", "ape30_smoothed", "assoc_above_none",
            "limit15_online", "limit15_smoothed"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for w in wins:
        lines.append("| " + " | ".join(str(w[c]) if c in cols[:4] else f"{w[c]}/{w['seeds']}" for c in cols) + " |")
    return "\n".join(lines)


def run_sequence(a: argparse.Namespace, seq: int, map_: str, seed: int, names: list[str], models: dict[str, str],
                 done: dict[tuple, dict], cells_path: str, figure_seq: int) -> None:
    """Run the missing cells of one (sequence, map, seed); append each to cells.jsonl."""
    s = scenario_for(a.data, a.output, seq, map_, a.every, a.max_range, seed)
    results: dict[str, Result] = {}
    tag = _tag(seq, map_, seed)
    for name in names:
        record: dict = {"sequence": seq, "map": map_, "estimator": name, "every": a.every,
                        "max_range": a.max_range, "seed": seed}
        key = cell_key(record)
        if key in done and not a.redo:
            continue
        t0 = time.perf_counter()
        try:
            record["metrics"], result = run_cell(s, name, models)
            if result is not None:
                results[name] = result
                path = os.path.join(a.output, "results", name.replace(":", "-"), f"{tag}.json")
                os.makedirs(os.path.dirname(path), exist_ok=True)
                save_result(result, path)
        except Exception as e:  # noqa: BLE001 - a failing cell is a result, not a crash
            record["error"] = f"{type(e).__name__}: {e}".splitlines()[0][:300]
        record["wall_s"] = time.perf_counter() - t0
        print(json.dumps(row(record)), flush=True)
        with open(cells_path, "a") as f:  # the last record of a cell counts
            f.write(json.dumps(record) + "\n")
        done[key] = record
    if seq == figure_seq and map_ == "known" and seed == 0:
        for name in ("hybrid:learned", "hybrid:none", "isam2", "oracle"):
            path = os.path.join(a.output, "results", name.replace(":", "-"), f"{tag}.json")
            if name not in results and os.path.exists(path):
                results[name] = load_result(path)
        if "hybrid:learned" in results:
            figure(s, results, os.path.join(a.output, f"kitti_{seq:04d}.png"), f"KITTI {seq:04d}, known map")


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
    p.add_argument("--seeds", default="0", help="odometry noise draws, comma-separated (e.g. 0,1,2,3,4): "
                   "the table gives each cell's mean and spread over them")
    p.add_argument("--figure-sequence", type=int, default=None)
    p.add_argument("--report-only", action="store_true", help="print and write the table of cells.jsonl; run nothing")
    p.add_argument("--redo", action="store_true", help="run the cells again even where cells.jsonl has them")
    a = p.parse_args(argv)
    sequences = [int(x) for x in a.sequences.split(",")]
    train = [int(x) for x in a.train.split(",")]
    names = a.estimators.split(",")
    maps = a.maps.split(",")
    try:
        seeds = [int(x) for x in a.seeds.split(",")]
    except ValueError:
        p.error(f"--seeds: expected comma-separated integers, got {a.seeds!r}")
    for n in names:
        if n not in ESTIMATORS:
            p.error(f"--estimators: unknown {n!r} (known: {', '.join(ESTIMATORS)})")
    os.makedirs(a.output, exist_ok=True)
    hs.setup()  # float64, before any array
    cache.enable()  # a rerun reads the compiled steps from disk
    models: dict[str, str] = {}
    if not a.report_only:
        models = fit_models(a.data, train, sequences, a.output)
        for path in models.values():
            load_classifier(path)  # fails here, not in every cell, if a file is broken
    cells_path = os.path.join(a.output, "cells.jsonl")
    done = read_cells(cells_path) if os.path.exists(cells_path) else {}
    figure_seq = a.figure_sequence if a.figure_sequence is not None else sequences[-1]
    for seed in seeds if not a.report_only else ():
        for seq in sequences:
            for map_ in maps:
                run_sequence(a, seq, map_, seed, names, models, done, cells_path, figure_seq)
    rows = [row(r) for r in done.values()
            if r["sequence"] in sequences and r["map"] in maps and r.get("seed", 0) in seeds]
    if not rows:
        print(f"no cells of sequences {sequences}, maps {maps}, seeds {seeds} in {cells_path}")
        return 1
    rows.sort(key=lambda r: (r["sequence"], r["map"], ESTIMATORS.index(r["estimator"]), r["seed"]))
    write_tables(rows, a.output)
    return 0


def write_tables(rows: list[dict], folder: str) -> None:
    """kitti.csv (one row per cell and seed), kitti_summary.csv and kitti_goals.csv; print the tables."""
    summary = summarize(rows)
    wins = goal_wins(rows)
    for name, table in (("kitti.csv", rows), ("kitti_summary.csv", summary), ("kitti_goals.csv", wins)):
        if table:
            with open(os.path.join(folder, name), "w", newline="") as f:
                w = csv.DictWriter(f, list(table[0]))
                w.writeheader()
                w.writerows(table)
    if len({r["seed"] for r in rows}) == 1:
        print(markdown(rows))
    print(markdown_summary(summary))
    if wins:
        print()
        print(markdown_goals(wins))


if __name__ == "__main__":
    raise SystemExit(main())
