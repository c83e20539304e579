"""A study's batched program kept on disk (hybridslam.studies.exported): a second study of the same
shapes runs without tracing the step, and gets the same numbers."""

from __future__ import annotations

import dataclasses
import os

import jax
import numpy as np

import hybridslam as hs
from hybridslam import driver
from hybridslam.studies import batch as sweep
from hybridslam.studies import exported
from hybridslam.studies.strategies import MapBatches

TINY = hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=4, classifier="mirror", max_detections=2)


def test_second_study_loads_the_exported_program_without_tracing(monkeypatch, tmp_path):
    folder = jax.config.jax_compilation_cache_dir  # the suite's persistent cache (tests/conftest.py)
    assert folder
    monkeypatch.setattr(exported, "FOLDER", f"exported-{tmp_path.name}")  # this test's files only
    exported.clear()  # another file of this worker may hold this program already (tests/test_sweep.py)
    # tests/test_sweep.py's tiny study's shapes: its XLA executable, from the run's cache when both files run.
    scenarios = [hs.simulate(t, steps=3, alpha=0.4) for t in range(3)]
    estimator = sweep.batched(TINY, scenarios)
    inputs = sweep.batch_inputs(estimator, scenarios, seeds=[0, 1, 2])
    first = sweep.run_batch(estimator, inputs, strategy=MapBatches(1))
    assert len(os.listdir(os.path.join(folder, exported.FOLDER))) == 1

    exported.clear()
    driver.clear_compiled()  # a fresh process, as far as compiled programs go

    def no_trace(*args, **kwargs):
        raise AssertionError("traced the step again")

    monkeypatch.setattr(jax.export, "export", no_trace)
    monkeypatch.setattr(exported, "compiled", no_trace)
    second = sweep.run_batch(estimator, inputs, strategy=MapBatches(1))
    for a, b in zip(jax.tree.leaves(first.trace), jax.tree.leaves(second.trace), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert type(second.trace) is type(first.trace)


def test_the_key_names_what_fixes_the_program():
    scenarios = [hs.simulate(0, steps=2)]
    estimator = sweep.batched(TINY, scenarios)
    batch = sweep.batch_inputs(estimator, scenarios, seeds=[0])
    key = exported.cache_key(sweep._run_batch, (estimator, batch, MapBatches(1)))
    assert key is not None and key == exported.cache_key(sweep._run_batch, (estimator, batch, MapBatches(1)))
    other = dataclasses.replace(estimator, capacity=5)
    assert exported.cache_key(sweep._run_batch, (other, batch, MapBatches(1))) != key
    assert exported.cache_key(sweep._run_batch, (estimator, batch, MapBatches(2))) != key
    longer = sweep.batch_inputs(estimator, [hs.simulate(0, steps=2)] * 2, seeds=[0, 1])
    assert exported.cache_key(sweep._run_batch, (estimator, longer, MapBatches(1))) != key
    # A static part whose repr names an address is no stable description: no key, no file.
    assert exported.cache_key(sweep._run_batch, (estimator, batch, MapBatches(1), object())) is None
