"""Settings that only an estimator's ``init`` reads (``AbstractEstimator.init_settings``) change the
run, not the compiled step: ``init`` writes them into the state, and ``hs.run`` steps with
``estimator.stepping()``, the estimator with those settings at their defaults. If a step read one of
them from the estimator instead, the two runs below would give the same numbers (the stepped copy
holds the default) and the test would fail."""

from __future__ import annotations

import dataclasses

import pytest

import hybridslam as hs
from hybridslam.driver import run
from hybridslam.estimators.registry import ESTIMATORS


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_init_settings_are_fields_that_stepping_resets(name):
    cls = ESTIMATORS[name]
    fields = {f.name: f for f in dataclasses.fields(cls)}
    assert cls.init_settings and set(cls.init_settings) <= set(fields), cls.init_settings
    changed = {"clutter": -4.0, "new_landmark": "mahalanobis:9.21"}
    estimator = hs.make_estimator(name, **changed)
    stepping = estimator.stepping()
    for setting in changed:
        assert getattr(estimator, setting) == changed[setting]
        assert getattr(stepping, setting) == fields[setting].default
    others = [f for f in fields if f not in cls.init_settings]
    assert all(getattr(stepping, f) == getattr(estimator, f) for f in others)


def test_a_clutter_density_changes_the_run_not_the_program(scenario):
    """``ml`` on the paper setup's known map: with a clutter density far above every detection's
    likelihood every detection is clutter; far below, none is. One compiled step for both."""
    runs = [run(hs.make_estimator("ml", smoother="filter", clutter=c), scenario) for c in (50.0, -50.0)]
    rejected = [sum(int(info.rejected) for info in r.infos) for r in runs]
    detections = sum(len(s.detections) for s in scenario.steps)
    assert rejected == [detections, 0], rejected
    assert runs[1].result.timing["compile_s"] == 0.0


def test_a_prune_ratio_changes_the_run_not_the_program(scenario):
    """The hybrid belief keeps only the best child at ``prune_ratio=1`` and several at ``1e6``, with one
    compiled step for both (the ratio lives in the state's model)."""
    kept = []
    for ratio in (1.0, 1e6):
        r = run(hs.make_estimator("hybrid", smoother="filter", weights="linearized", capacity=4,
                                  prune_ratio=ratio), scenario)
        kept.append(max(len(step.components) for step in r.result.steps))
        compile_s = r.result.timing["compile_s"]
    assert kept[0] == 1 < kept[1], kept
    assert compile_s == 0.0
