"""The scenario's ``sensor.detection_probability`` (docs/file_format.md): read, written, validated,
written by the hallway simulator, and the probability the loop-closure search's negative
information uses (the file's, else 0.9)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridslam.estimators.loops import misses as loop_misses, settings as loop_settings
from hybridslam.io.scenario import ScenarioError, parse_scenario, scenario_to_json
from hybridslam.sim.hallway import hallway

from .test_scenario import minimal


def test_the_field_is_optional_and_round_trips():
    s = parse_scenario(minimal())
    assert s.detection_probability is None
    assert "detection_probability" not in scenario_to_json(s)["sensor"]  # older files are written as they were
    obj = minimal()
    obj["sensor"]["detection_probability"] = 0.75
    s = parse_scenario(obj)
    assert s.detection_probability == 0.75
    assert scenario_to_json(s) == obj


@pytest.mark.parametrize("value", [0.0, -0.1, 1.5, "high", math.inf])
def test_a_bad_probability_names_the_field(value):
    obj = minimal()
    obj["sensor"]["detection_probability"] = value
    with pytest.raises(ScenarioError, match=r"sensor\.detection_probability"):
        parse_scenario(obj)


def test_the_hallway_detects_every_landmark_in_view():
    s = hallway(0, steps=6)
    assert s.detection_probability == 1.0
    assert parse_scenario(scenario_to_json(s)).detection_probability == 1.0


def test_the_loop_closure_search_takes_the_files_probability_else_0_9():
    with_field = hallway(0, steps=6)
    without = with_field.replace(detection_probability=None)
    default = loop_settings.LoopClosureSettings()
    assert default.for_scenario(with_field).detection_probability == 1.0
    assert default.for_scenario(without).detection_probability == loop_settings.DEFAULT_DETECTION_PROBABILITY == 0.9
    given_p = loop_settings.LoopClosureSettings(detection_probability=0.5)
    assert given_p.for_scenario(with_field).detection_probability == 0.5  # the setting overrides the file
    # a file without the field keeps the old term: log(0.1) per miss surely in view
    assert _misses(3, default.for_scenario(without)) == pytest.approx(3 * math.log(0.1))
    # a sensor that never misses: each miss costs log(min_miss_probability), finite
    assert _misses(2, default.for_scenario(with_field)) == pytest.approx(2 * math.log(0.1))
    sharp = loop_settings.LoopClosureSettings(min_miss_probability=0.01)
    assert _misses(2, sharp.for_scenario(with_field)) == pytest.approx(2 * math.log(0.01))
    # a sensor that misses often charges a miss less than the floor
    half = without.replace(detection_probability=0.5)
    assert _misses(1, default.for_scenario(half)) == pytest.approx(math.log(0.5))
    assert _misses(5, loop_settings.LoopClosureSettings(detection_probability=0.0)) == 0.0


def _misses(count: int, settings: loop_settings.LoopClosureSettings) -> float:
    """The negative information of ``count`` (step, object) pairs surely in view and undetected."""
    in_view = np.zeros((count + 1, 1))
    in_view[1:] = 1.0
    return loop_misses.miss_log_likelihood(in_view, np.full((count, 1), -1), 1, settings)


@pytest.mark.parametrize("bad", [dict(detection_probability=1.2), dict(detection_probability=-0.1),
                                 dict(min_miss_probability=0.0), dict(min_miss_probability=2.0),
                                 dict(misses="mean"), dict(fov_margin=(0.5, -1.0))])
def test_bad_settings_name_the_setting(bad):
    with pytest.raises(ValueError, match=f"LoopClosureSettings.{next(iter(bad))}"):
        loop_settings.LoopClosureSettings(**bad)
