"""The clutter hypothesis by default: ``sensor.clutter_log_density`` in a scenario file, read by
every estimator unless its ``clutter`` setting overrides it (``"none"``: off)."""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridslam as hs
from hybridslam.driver import run
from hybridslam.inference.gating import chi2_gate
from hybridslam.io.scenario import Discovery, ScenarioError, parse_scenario, scenario_to_json


def _with_copy(offset: float) -> hs.Scenario:
    """A paper scenario whose first step holds a copy of its first detection ``offset`` m farther
    (of no object): with one candidate per detection, at most one of the two can be the object's."""
    scenario = hs.simulate(2, steps=2, setup=hs.PaperSetup(max_detections=2, max_range=12.0))
    first = scenario.steps[0]
    near = dataclasses.replace(first.detections[0], range=first.detections[0].range + offset, true_object=None)
    steps = (dataclasses.replace(first, detections=(first.detections[0], near, first.detections[1])),)
    return scenario.replace(steps=steps + scenario.steps[1:])


@pytest.fixture(scope="module")
def duplicated() -> hs.Scenario:
    """The copy 0.3 m farther (one range sd): inside the object's gate."""
    return _with_copy(0.3)


@pytest.fixture(scope="module")
def outlier() -> hs.Scenario:
    """The copy 1.5 m farther (4.7 range sds): outside the 0.999 gate of every object."""
    return _with_copy(1.5)


def test_the_paper_files_declare_no_clutter_and_the_field_round_trips(duplicated):
    """A simulated (paper) file writes no ``sensor.clutter_log_density``: every estimator keeps the
    paper's model there. The field, when set, is read back; a bad value is an error naming it."""
    assert duplicated.clutter_log_density is None
    assert "clutter_log_density" not in scenario_to_json(duplicated)["sensor"]
    doc = scenario_to_json(duplicated.replace(clutter_log_density=-7.5))
    assert doc["sensor"]["clutter_log_density"] == -7.5
    assert parse_scenario(json.loads(json.dumps(doc))).clutter_log_density == -7.5
    doc["sensor"]["clutter_log_density"] = "high"
    with pytest.raises(ScenarioError, match="sensor.clutter_log_density: expected a number"):
        parse_scenario(doc)


@pytest.mark.parametrize("name", ["ml", "gpda", "max-mixture"])
def test_the_single_gaussian_estimators_read_the_files_clutter_density(name, outlier):
    """With the file's clutter density the far copy is explained as clutter (``rejected``), nothing
    is skipped, and the settings line says which density; ``clutter="none"`` turns it off (its state
    is that of the file without the field, where nothing is rejected), and a number overrides the file's."""
    with_clutter = outlier.replace(clutter_log_density=-10.0)
    est = hs.make_estimator(name, gate=1, smoother="filter")
    assert "clutter=-10" in est.describe(with_clutter) and "clutter" not in est.describe(outlier)
    infos = run(est, with_clutter).infos
    assert int(infos[0].rejected) == 1 and int(infos[0].skipped) == 0
    # "none" is resolved when the state is built: the state equals the file's without a density, so
    # its steps are `est`'s on that file (ml's program is test_ml_without_a_clutter_density_...'s).
    off = hs.make_estimator(name, gate=1, smoother="filter", clutter="none").init(with_clutter)
    plain = est.init(outlier)
    assert not off.structure.clutter and off.structure == plain.structure
    assert float(off.params.clutter_log_density) == -np.inf
    for a, b in zip(jax.tree.leaves(off), jax.tree.leaves(plain), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(run(est, outlier).infos[0].rejected) == 0
    override = hs.make_estimator(name, clutter=-3.0)
    assert "clutter=-3" in override.describe(with_clutter)
    assert float(override.init(with_clutter).params.clutter_log_density) == -3.0


def test_ml_without_a_clutter_density_skips_the_copy_as_before(duplicated):
    """No field in the file: ml leaves the copy unassociated (``skipped``), as it always did."""
    infos = run(hs.make_estimator("ml", gate=1, smoother="filter"), duplicated).infos
    assert int(infos[0].skipped) == 1 and int(infos[0].rejected) == 0


def test_the_hybrid_belief_reads_the_files_clutter_density(duplicated):
    """The hybrid belief's default clutter setting is the file's: the copy is rejected as clutter."""
    est = hs.make_estimator("hybrid", gate=1, weights="linearized", smoother="filter")
    infos = run(est, duplicated.replace(clutter_log_density=-10.0)).infos
    assert int(infos[0].rejected) == 1 and int(infos[0].skipped) == 0
    with pytest.raises(ValueError, match="exhaustive enumeration has no clutter hypothesis"):
        hs.make_estimator("hybrid", exhaustive=True).init(duplicated.replace(clutter_log_density=-10.0))
    hs.make_estimator("hybrid", exhaustive=True, clutter="none").init(duplicated.replace(clutter_log_density=-10.0))


def test_an_unknown_maps_file_clutter_density_is_not_a_known_map_setting():
    """On an unknown map ml/gpda/max-mixture/multimodal's null hypothesis is a new object: the
    file's density is not used there, and an explicit one is refused naming the setting."""
    scenario = hs.simulate(0, steps=1, setup=hs.PaperSetup(max_detections=2)).replace(clutter_log_density=-5.0)
    unknown = scenario.replace(
        discovery=Discovery(4, -math.log(12.0), math.pi**2), object_prior_means=np.zeros((0, 3)),
        object_prior_covs=np.zeros((0, 3, 3)), class_prior=np.zeros((0, scenario.num_classes)),
        steps=tuple(dataclasses.replace(s, detections=tuple(dataclasses.replace(d, true_object=None)
                                                            for d in s.detections)) for s in scenario.steps),
        true_object_poses=None, true_classes=None)
    assert "clutter" not in hs.make_estimator("ml").describe(unknown)
    hs.make_estimator("ml").init(unknown)
    with pytest.raises(ValueError, match="clutter is for a known map"):
        hs.make_estimator("ml", clutter=-5.0).init(unknown)


def _read_far(offset: float) -> hs.Scenario:
    """A paper scenario whose first reading of its first object lies ``offset`` m farther than
    the simulator put it (no other reading of that object in the step), the robot's prior pose
    known to 1 cm: the offset is in range sds (0.32 m) alone."""
    scenario = hs.simulate(2, steps=2, setup=hs.PaperSetup(max_detections=2, max_range=12.0))
    scenario = scenario.replace(robot_prior_cov=np.diag([1e-4, 1e-4, 1e-6]))
    first = scenario.steps[0]
    far = dataclasses.replace(first.detections[0], range=first.detections[0].range + offset)
    steps = (dataclasses.replace(first, detections=(far,) + first.detections[1:]),)
    return scenario.replace(steps=steps + scenario.steps[1:])


def test_the_hybrid_beliefs_chi_square_gate_leaves_a_reading_beyond_it_to_clutter():
    """``gate_probability``: a reading 1.5 m off its object (d² ≈ 22, beyond the 0.999 gate) is the object's
    in the top child without the gate (clutter at log density -30 is far less likely) and clutter
    in every child with it, counted as rejected; on a file without clutter the setting changes
    nothing; a probability outside (0, 1) is refused naming the setting."""
    far = _read_far(1.5)
    sc = far.replace(clutter_log_density=-30.0)
    base = dict(gate=3, weights="linearized", smoother="filter")
    plain = run(hs.make_estimator("hybrid", **base), sc)
    gated = run(hs.make_estimator("hybrid", gate_probability=0.999, **base), sc)

    def far_reading(r) -> list[int]:
        return [int(c.associations[0][0]) for c in r.result.steps[0].components]

    assert far_reading(plain)[0] >= 0 and int(plain.infos[0].rejected) == 0
    assert all(a < 0 for a in far_reading(gated)) and int(gated.infos[0].rejected) == 1
    assert "gate_probability=0.999" in hs.make_estimator("hybrid", gate_probability=0.999, **base).describe(sc)
    without = run(hs.make_estimator("hybrid", gate_probability=0.999, **base), far).result.steps
    assert without == run(hs.make_estimator("hybrid", **base), far).result.steps
    with pytest.raises(ValueError, match="Hybrid.gate_probability"):
        hs.Hybrid(gate_probability=1.0)


@settings(max_examples=50, deadline=None)
@given(st.floats(1e-6, 1.0 - 1e-9))
def test_the_chi_square_gate_is_the_quantile_of_two_degrees_of_freedom(p):
    """``chi2_gate(p)``: the ``d²`` whose chi-square CDF at 2 degrees of freedom, ``1 − exp(−d²/2)``,
    is ``p`` (thesis Sec. 3.2.1; 0.999 is the 13.8 of the docs)."""
    q = chi2_gate(p)
    assert q > 0 and math.isclose(-math.expm1(-q / 2), p, rel_tol=1e-9)
    assert math.isclose(chi2_gate(0.999), 13.815510557964274, rel_tol=1e-12)
