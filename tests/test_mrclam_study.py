"""The MRCLAM study script's bookkeeping (``experiments/mrclam.py``): its association scores and the
keys its resumable records are found by. Nothing here runs an estimator."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import hybridslam as hs

from .scripts import load_script


@pytest.fixture(scope="module")
def study():
    return load_script("experiments/mrclam.py", "mrclam_study")


# (estimated object, true landmark) per detection: object 0 holds landmarks 0, 0 and 1 (mixed),
# objects 1 and 2 both hold landmark 1 (a duplicate), one detection is unassociated.
PAIRS = [(0, 0), (0, 0), (0, 1), (1, 1), (2, 1), (-1, 2)]


def test_unknown_map_scores_purity_duplicates_and_merges(study):
    score = study._score(PAIRS, known_map=False)
    assert score == {"accuracy": 4 / 6, "detections": 6, "unassociated": 1, "num_objects": 3,
                     "duplicate_objects": 1, "mixed_objects": 1}


def test_known_map_scores_the_object_index(study):
    score = study._score(PAIRS, known_map=True)
    assert score == {"accuracy": 3 / 6, "detections": 6, "unassociated": 1, "num_objects": 3,
                     "duplicate_objects": 0, "mixed_objects": 0}
    empty = study._score([], known_map=False)
    assert math.isnan(empty["accuracy"]) and empty["mixed_objects"] == 0


def test_the_drift_calibration_gets_its_own_files_and_keys(study):
    plain = study.scenario_name("data/MRCLAM_Dataset7", 3, 20.0, 100.0, "unknown:50")
    drift = study.scenario_name("data/MRCLAM_Dataset7", 3, 20.0, 100.0, "unknown:50", "drift")
    assert plain == "MRCLAM_Dataset7_robot3_t20_d100_unknown_slots50.json"
    assert drift == "MRCLAM_Dataset7_robot3_t20_d100_unknown_slots50_motion-drift.json"
    key = study.cell_key("MRCLAM_Dataset7", 3, 20.0, 100.0, "unknown", "ml", "full")
    # The importer's calibration is part of the key: cells of files calibrated otherwise rerun.
    assert key["noise"] == {"measurement_noise_from": "written", "motion_noise_from": "steps"}
    assert study.cell_key("MRCLAM_Dataset7", 3, 20.0, 100.0, "unknown", "ml", "full", "drift") == {
        **key, "noise": {"measurement_noise_from": "written", "motion_noise_from": "drift"}}


def test_a_file_of_an_older_calibration_is_imported_anew(study, tmp_path):
    data = Path(__file__).resolve().parent / "data" / "mrclam"
    path, fresh = study.scenario(str(tmp_path), str(data), 1, 0.0, 40.0, "known")
    assert study._calibration(fresh) == study.NOISE_CALIBRATION
    metadata = {**fresh.metadata}
    metadata["generator"] = {**metadata["generator"], "calibration": {
        k: v for k, v in metadata["generator"]["calibration"].items() if k not in study.NOISE_CALIBRATION}}
    hs.save_scenario(fresh.replace(metadata=metadata, geometric_cov=2 * fresh.geometric_cov), path)
    again_path, again = study.scenario(str(tmp_path), str(data), 1, 0.0, 40.0, "known")
    assert again_path == path and again == fresh and hs.load_scenario(path) == fresh
