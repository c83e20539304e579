"""``hybridslam import``: real-robot logs written as scenario files.

    hybridslam import mrclam DATASET_DIR --robot N -o FILE [--start S] [--duration D] [--dt 0.5]
        [--unknown-map] [--max-range R] [--fov F] [--motion-cov a,b,c] [--geometric-cov a,b]
        [--robot-prior-cov a,b,c] [--correct-range-bias] [--no-motion-compensation] [--odometry-delay S]
        [--measurement-noise-from {written,raw}] [--motion-noise-from {steps,drift}]
        [--identity-filter] [--merge-repeats] [--object-slots N] [--clutter-log-density {D,none}]
        [--unmapped-objects N] [--new-object-log-density D]
    hybridslam import kitti-tracking DIR --sequence N -o FILE [--unknown-map] [--every E]
        [--odometry {noisy-truth,orbslam3}] [--max-range R] [--fov F] [--min-logit L] (docs/studies/kitti.md)

:func:`register` adds the ``import`` command to the ``hybridslam`` parser; its errors are
:class:`~hybridslam.cli.CLIError` (one line, exit status 2) like every other command's.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ..datasets.kitti import ODOMETRY_SOURCES, KITTIError, import_kitti
from ..datasets.mrclam import MOTION_NOISE_SOURCES, NOISE_SOURCES, import_mrclam
from ..datasets.mrclam_files import MRCLAMError
from ..models.scenario import Scenario
from ..io.scenario import save_scenario
from .common import CLIError, check_writable, clutter_density

_GAP_NOTE_S = 0.5  # a longer stretch without odometry or ground truth is worth a line
_DRIFT_NOTE = 2.0
_NOISE_FROM = {"written": "detections as written", "raw": "raw measurements"}  # block-sum sd / calibrated sd above this is worth a line


def _variances(text: str | None, n: int, option: str) -> np.ndarray | None:
    """``n`` comma-separated positive variances (a diagonal covariance), or None."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != n or not all(math.isfinite(v) and v > 0 for v in values):
        raise CLIError(f"{option}: expected {n} positive comma-separated variances, got {text!r}")
    return np.diag(values)


def _horizons(drift: dict) -> str:
    """The drift horizons a calibration used, ``"5 s"`` or ``"5-40 s"``."""
    h = drift["horizons_s"]
    return f"{h[0]:g} s" if len(h) == 1 else f"{h[0]:g}-{h[-1]:g} s"


def _sds(cov: np.ndarray) -> str:
    return ", ".join(f"{s:.3g}" for s in np.sqrt(np.diag(cov)))


def mrclam_summary(path: str, s: Scenario) -> str:
    """The lines ``hybridslam import mrclam`` prints about the scenario it wrote to ``path``."""
    g = s.metadata["generator"]
    cal, counts, dr, data = g["calibration"], g["counts"], g["dead_reckoning"], g["data"]
    per_step = [len(st.detections) for st in s.steps]
    seen = {d.true_object for st in s.steps for d in st.detections}
    num_landmarks = s.num_objects if s.discovery is None else len(s.true_objects or ())
    start, bias = g["start_s"], cal["range_bias_m"]
    corrected = "corrected" if cal["range_bias_corrected"] else "not corrected: --correct-range-bias"
    end = start + g["duration_s"]
    window = (f"wrote {path}: {g['dataset']} robot {g['robot']}, {start:g}-{end:g} s after "
              f"its first odometry record, {s.num_steps} steps of {g['dt_s']:g} s, {g['map']} map of "
              f"{num_landmarks} landmarks"
              + ("" if s.discovery is None else f" ({s.discovery.max_objects} object slots: --object-slots)"))
    filtered = g.get("identities", {}).get("identity_filter", True)
    unnamed = sum(d.true_object is None for st in s.steps for d in st.detections)
    if filtered:
        detections = (f"detections: {sum(per_step)} of {len(seen - {None})} landmarks, "
                      f"{np.mean(per_step):.2f} per step (max {max(per_step)}); identity filter (oracle-assisted): "
                      f"dropped {counts['robot_robot']} robot-robot, {counts['unknown_barcode']} unknown barcode, "
                      f"{counts['beyond_sensor']} beyond the sensor, {counts['superseded']} superseded "
                      "(same landmark, same step)")
    else:
        detections = (f"detections: {sum(per_step)}, {np.mean(per_step):.2f} per step (max {max(per_step)}), "
                      f"every reading: {unnamed} of no landmark (other robots: {counts['robot_robot']} readings, "
                      f"unknown barcodes: {counts['unknown_barcode']}; no true_object), "
                      f"{counts.get('merged', 0)} repeats merged by geometry (--merge-repeats), "
                      f"{counts['beyond_sensor']} beyond the sensor; clutter log density "
                      + ("none" if s.clutter_log_density is None else f"{s.clutter_log_density:.3g}"))
    source = ("" if cal["geometric_cov"] == "given"
              else f" from the {_NOISE_FROM[cal['measurement_noise_from']]}")
    drift_source = (f", from the {_horizons(cal['odometry_drift_sd_per_step'])} drift"
                    if cal["motion_cov"] == "calibrated" and cal["motion_noise_from"] == "drift" else "")
    geometric = (f"geometric_cov ({cal['geometric_cov']}{source}): sd {_sds(s.geometric_cov)} (m, rad); "
                 f"range bias {bias:+.3f} m ({corrected})")
    dead_reckoning = (f"dead reckoning at the end of the window: {dr['final_position_error_m']:.3f} m, "
                      f"{dr['final_heading_error_rad']:+.3f} rad off the ground truth "
                      f"(path {dr['path_length_m']:.2f} m)")
    lines = [
        window, detections, f"sensor: max_range {s.max_range:g} m, fov {s.fov:g} rad",
        f"motion_cov ({cal['motion_cov']}{drift_source}): sd {_sds(s.motion_cov)} (m, m, rad per step)",
        geometric, dead_reckoning,
    ]
    gaps = [f"{name} {data[key]:.2f} s" for name, key in (("odometry", "odometry_max_gap_s"),
                                                          ("ground truth", "groundtruth_max_gap_s"))
            if data[key] > _GAP_NOTE_S]
    drift = cal.get("odometry_drift_sd_per_step")
    if drift and np.any(np.asarray(drift["sd"]) > _DRIFT_NOTE * np.sqrt(np.diag(s.motion_cov))):
        sds = ", ".join(f"{v:.3g}" for v in drift["sd"])
        lines.append(f"note: odometry errors are correlated in time: summed over {_horizons(drift)} "
                     f"they grow like sd {sds} per step, more than {_DRIFT_NOTE:g}x motion_cov's; dead "
                     "reckoning drifts faster than it says (--motion-noise-from drift, --motion-cov)")
    if gaps:
        lines.append(f"note: longest gap without records in the window: {', '.join(gaps)}")
    return "\n".join(lines)


def _noise(args: argparse.Namespace) -> dict[str, Any]:
    """``--motion-cov`` and ``--geometric-cov`` as covariances (``None``: the importer's own)."""
    return {"motion_cov": _variances(args.motion_cov, 3, "--motion-cov"),
            "geometric_cov": _variances(args.geometric_cov, 2, "--geometric-cov")}


def _write(output: str, build: Callable[[], Scenario], error: type[ValueError],
           summary: Callable[[str, Scenario], str]) -> int:
    """Import (``build``), write the scenario to ``output`` and print its ``summary``; the importer's
    ``error`` is a :class:`CLIError` (checked first: ``output`` can be written)."""
    check_writable(output)
    try:
        scenario = build()
    except error as e:
        raise CLIError(str(e)) from None
    save_scenario(scenario, output)
    print(summary(output, scenario))
    return 0


def cmd_import_mrclam(args: argparse.Namespace) -> int:
    """Write one robot's MRCLAM log as a scenario file and print a summary."""
    covs = {**_noise(args), "robot_prior_cov": _variances(args.robot_prior_cov, 3, "--robot-prior-cov")}
    return _write(args.output, lambda: import_mrclam(
        args.dataset, args.robot, start=args.start, duration=args.duration, dt=args.dt,
        unknown_map=args.unknown_map, max_range=args.max_range, fov=args.fov,
        correct_range_bias=args.correct_range_bias, motion_compensation=args.motion_compensation,
        odometry_delay=args.odometry_delay, max_objects=args.max_objects,
        measurement_noise_from=args.measurement_noise_from, motion_noise_from=args.motion_noise_from,
        identity_filter=args.identity_filter, merge_repeats=args.merge_repeats,
        clutter_log_density=args.clutter_log_density, unmapped_objects=args.unmapped_objects,
        new_object_log_density=args.new_object_log_density, **covs),
        MRCLAMError, mrclam_summary)


def _source(sources: argparse._SubParsersAction, name: str, summary: str, description: str,
            dataset: tuple[str, str], part: tuple[str, str]) -> argparse.ArgumentParser:
    """An ``import`` subcommand with what every one takes: its data folder (``dataset``: metavar,
    help), the part of it to write (``part``: an int option, its help) and ``-o``."""
    p = sources.add_parser(name, help=summary, description=description)
    p.add_argument("dataset", metavar=dataset[0], help=dataset[1])
    p.add_argument(part[0], type=int, required=True, help=part[1])
    p.add_argument("-o", "--output", required=True, help="scenario file to write")
    return p


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``import`` (with its ``mrclam`` and ``kitti-tracking`` subcommands) to the ``hybridslam`` subcommands."""
    p = subparsers.add_parser("import", help="write a real-robot log as a scenario file (MRCLAM, KITTI tracking)")
    sources = p.add_subparsers(dest="source", required=True, metavar="{mrclam,kitti-tracking}")
    m = _source(sources, "mrclam", "one robot of a UTIAS MRCLAM dataset folder",
                "One robot's log of a UTIAS MRCLAM dataset folder as a scenario: a step every --dt seconds, "
                "exact odometry arcs, landmark detections, noise calibrated from the ground truth.",
                ("DATASET_DIR", "folder with Barcodes.dat, Landmark_Groundtruth.dat, "
                                "RobotN_{Odometry,Measurement,Groundtruth}.dat"),
                ("--robot", "robot 1-5"))
    m.add_argument("--start", type=float, default=0.0,
                   help="x_0 this many seconds after the robot's first odometry record (default 0)")
    m.add_argument("--duration", type=float, default=None,
                   help="seconds of steps (default: to the end of the data)")
    m.add_argument("--dt", type=float, default=0.5, help="seconds between steps (default 0.5)")
    m.add_argument("--unknown-map", action="store_true",
                   help="no prior objects: a discovery section, the landmarks under true_objects")
    m.add_argument("--object-slots", "--max-objects", dest="max_objects", type=int, default=None, metavar="N",
                   help="with --unknown-map: object slots (default: the most detections in a step + 10; with "
                        "--identity-filter the surveyed landmarks + 10); duplicates of a landmark take slots too, "
                        "and the estimators warn when they are full")
    m.add_argument("--unmapped-objects", type=int, default=0, metavar="N",
                   help="known map: room for N objects the survey does not hold (another robot standing still, "
                        "read at every step, is one; a discovery section beside the landmarks; default 0)")
    m.add_argument("--new-object-log-density", type=float, default=None, metavar="D",
                   help="discovery.new_object_log_density written with --unknown-map or --unmapped-objects: the "
                        "log density over [range, bearing] of a new object's detection, its prior probability "
                        "included (default: -log(max_range * fov), uniform over the footprint)")
    m.add_argument("--identity-filter", action="store_true",
                   help="oracle-assisted: keep only readings whose barcode names a landmark, one per landmark "
                        "and step (the barcodes are identities the estimators are meant not to know)")
    m.add_argument("--merge-repeats", action="store_true",
                   help="merge an object's repeated readings within a step by geometry alone (readings of "
                        "other sensor frames within the noise gate; default: keep every reading)")
    m.add_argument("--clutter-log-density", type=clutter_density, default=None, metavar="{D,none}",
                   help="sensor.clutter_log_density written (default: log(0.5 / (max_range * fov)); none with "
                        "--identity-filter); 'none' writes no clutter hypothesis")
    m.add_argument("--max-range", type=float, default=None,
                   help="sensor range in metres; farther detections are dropped (default: from the data)")
    m.add_argument("--fov", type=float, default=None,
                   help="field of view in radians; detections outside are dropped (default: from the data)")
    m.add_argument("--motion-cov", default=None, metavar="VXX,VYY,VTT",
                   help="odometry variances per step (m^2, m^2, rad^2) instead of the calibrated ones")
    m.add_argument("--geometric-cov", default=None, metavar="VRR,VBB",
                   help="range and bearing variances (m^2, rad^2) instead of the calibrated ones")
    m.add_argument("--robot-prior-cov", default=None, metavar="VXX,VYY,VTT",
                   help="variances of the prior on x_0 (default 1e-4 each)")
    m.add_argument("--correct-range-bias", action="store_true",
                   help="subtract the median range residual (against the ground truth) from the ranges")
    m.add_argument("--no-motion-compensation", dest="motion_compensation", action="store_false",
                   help="write each detection as measured, not re-expressed from the step's pose")
    m.add_argument("--odometry-delay", type=float, default=0.0,
                   help="seconds added to the odometry times (its velocity commands lead the ground truth "
                        "by ~0.17 s); default 0")
    m.add_argument("--measurement-noise-from", choices=NOISE_SOURCES, default="written",
                   help="calibrate geometric_cov from the detections as written, at their step times "
                        "(default), or from the raw measurements at their own times")
    m.add_argument("--motion-noise-from", choices=MOTION_NOISE_SOURCES, default=None,
                   help="calibrate motion_cov from the per-step odometry errors (steps) or from their "
                        "sums over 5-40 s (drift: larger, as the errors are correlated in time); default: "
                        "drift for a file with a clutter hypothesis (the default conversion) and a window "
                        "of 25 s or more, steps otherwise (--identity-filter, --clutter-log-density none)")
    m.set_defaults(func=cmd_import_mrclam)
    register_kitti(sources)


def kitti_summary(path: str, s: Scenario) -> str:
    """The lines ``hybridslam import kitti-tracking`` prints about the scenario it wrote to ``path``."""
    g = s.metadata["generator"]
    c, cal, fr = g["counts"], g["calibration"], g["frames"]
    n = s.num_objects if s.discovery is None else len(s.true_objects or ())
    return "\n".join([
        (f"wrote {path}: KITTI tracking {g['sequence']}, frames {fr['start']}-{fr['end']} every {fr['every']}, "
        f"{s.num_steps} steps, {g['map']} map of {n} static objects, odometry {g['odometry']}"),
        (f"detections: {c['written']} written ({c['static_object']} of static objects, {c['moving_object']} of "
        f"moving ones ({c['moving_tracks']} moving tracks: clutter to a static map), {c['other_type']} of other "
        f"types, {c['unmatched']} matching no label); dropped {c['beyond_sensor']} beyond the sensor, "
        f"{c['below_min_logit']} below --min-logit; {c['raw_detections']} raw, {c['merged_detections']} "
        "after merging the three detectors"),
        (f"sensor: max_range {s.max_range:g} m, fov {s.fov:g} rad; clutter log density "
         + ("none" if s.clutter_log_density is None else f"{s.clutter_log_density:.3g}")
         + ("" if s.discovery is None else f"; {s.discovery.max_objects} object slots (--max-objects)")),
        f"motion_cov ({cal['motion_cov']}): sd {_sds(s.motion_cov)} (m, m, rad per step)",
        f"geometric_cov ({cal['geometric_cov']}): sd {_sds(s.geometric_cov)} (m, rad)",
        (f"dead reckoning at the end: {g['dead_reckoning']['final_position_error_m']:.2f} m off the ground truth "
        f"(path {g['dead_reckoning']['path_length_m']:.1f} m)")]
        + (["WARNING: the sequence has no static labelled object, so the known map is empty and the estimators "
            "refuse the file; import it with --unknown-map"] if s.discovery is None and n == 0 else []))


def cmd_import_kitti(args: argparse.Namespace) -> int:
    """Write one KITTI tracking sequence as a scenario file and print a summary."""
    covs = _noise(args)
    return _write(args.output, lambda: import_kitti(
        args.dataset, args.sequence, unknown_map=args.unknown_map, start=args.start, end=args.end,
        every=args.every, odometry=args.odometry, seed=args.seed, max_range=args.max_range, fov=args.fov,
        min_logit=args.min_logit, merge_radius=args.merge_radius, match_iou=args.match_iou,
        static_tolerance=args.static_tolerance, max_objects=args.max_objects,
        clutter_log_density=args.clutter_log_density, **covs), KITTIError, kitti_summary)


def register_kitti(sources: argparse._SubParsersAction) -> None:
    """Add ``import kitti-tracking``."""
    k = _source(sources, "kitti-tracking", "one KITTI tracking sequence with PointRCNN detections",
                "One KITTI tracking sequence as a scenario: planar IMU poses, PointRCNN detections (three "
                "detectors merged) as range, bearing and class scores, the static labelled objects as the map "
                "(docs/studies/kitti.md says how to assemble DIR).",
                ("DIR", "folder with label_02/, calib/, detections/pointrcnn_{Car,Pedestrian,Cyclist}_val/, "
                        "egomotion/ and orbslam3/NNNN/CameraTrajectory.txt"),
                ("--sequence", "sequence number (0 for 0000)"))
    k.add_argument("--unknown-map", action="store_true",
                   help="no prior objects: a discovery section, the static objects under true_objects")
    k.add_argument("--max-objects", type=int, default=None, metavar="N",
                   help="with --unknown-map: object slots (default: the most detections in one step + 20)")
    k.add_argument("--clutter-log-density", type=clutter_density, default=None, metavar="{D,none}",
                   help="sensor.clutter_log_density written (default: -log(max_range * fov), uniform over the "
                        "sensor's footprint); 'none' writes no clutter hypothesis")
    k.add_argument("--start", type=int, default=0, help="frame of x_0 (default 0)")
    k.add_argument("--end", type=int, default=None, help="last frame (default: the sequence's last)")
    k.add_argument("--every", type=int, default=1, help="frames per step (default 1: 10 Hz)")
    k.add_argument("--odometry", choices=ODOMETRY_SOURCES, default="noisy-truth",
                   help="noisy-truth (default): ground-truth increments plus wheel-odometry-level noise; "
                        "orbslam3: ORB-SLAM3 increments, motion_cov calibrated against the ground truth")
    k.add_argument("--seed", type=int, default=0, help="seed of the noisy-truth odometry (default 0)")
    k.add_argument("--max-range", type=float, default=30.0, help="sensor range in metres (default 30)")
    k.add_argument("--fov", type=float, default=1.6, help="field of view in radians (default 1.6)")
    k.add_argument("--min-logit", type=float, default=None,
                   help="drop detections whose strongest logit is below this (default: keep all)")
    k.add_argument("--merge-radius", type=float, default=1.0,
                   help="boxes of different detectors closer than this (m) are one detection (default 1)")
    k.add_argument("--match-iou", type=float, default=0.25,
                   help="3D IoU a detection needs with a label to be matched (ground truth; default 0.25)")
    k.add_argument("--static-tolerance", type=float, default=1.0,
                   help="a track is static when every world position is this close (m) to its median")
    k.add_argument("--motion-cov", default=None, metavar="VXX,VYY,VTT",
                   help="odometry variances per step (m^2, m^2, rad^2)")
    k.add_argument("--geometric-cov", default=None, metavar="VRR,VBB",
                   help="range and bearing variances (m^2, rad^2) instead of the calibrated ones")
    k.set_defaults(func=cmd_import_kitti)
