"""How the tracks of a batch share a program (vmap, or a map over chunks) and `hs.run_many`: the
same numbers as single runs, one compile for files of different lengths and detection counts.

Every run here has the settings and shapes of tests/test_sweep.py's tiny study (capacity 4,
``linearized``, the filter, ``mirror``, 2 detection slots, 3 steps): `hs.run_many`'s program is the
single runs' program of the strategies test, and MapBatches(1)'s is the tiny study's (shared through
the run's compilation cache and exported programs when both files run in one session)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import hybridslam as hs
from hybridslam import compilation
from hybridslam.models.classifier import AlphaK
from hybridslam.studies import batch as sweep
from hybridslam.studies.strategies import MapBatches, VmapBatches, default_strategy, parse_strategy

from .scripts import load_script

TINY = hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=4, classifier="mirror", max_detections=2)


@pytest.fixture(scope="module")
def many():
    """`hs.run_many` over files of 2-3 steps with 1 or 2 detection slots, with TINY's settings but the
    slots left to the files: (estimator, scenarios, seeds, runs, compiles it made). A fixture: the
    compile count needs the first use of its program in this module."""
    scenarios = [hs.simulate(20, steps=2, setup=hs.PaperSetup(max_detections=1)),
                 hs.simulate(21, steps=3), hs.simulate(22, steps=3)]
    estimator = hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=4, classifier="mirror")
    compiles = []
    real = compilation.compile_lowered
    # Another file of this worker may have compiled this program already (tests/test_sweep.py's single
    # runs): then none is compiled here, and at most one in any case.
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(compilation, "compile_lowered", lambda *a, **k: compiles.append(1) or real(*a, **k))
        runs = hs.run_many(estimator, scenarios, seed=[3, 4, 5])
    return estimator, scenarios, (3, 4, 5), runs, len(compiles)


def _close(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x, float), np.asarray(y, float), rtol=1e-9, atol=1e-12, equal_nan=True)


def test_strategies_by_backend_and_by_name():
    assert default_strategy("cpu") == MapBatches(1) and default_strategy("gpu") == VmapBatches()
    assert parse_strategy("vmap") == VmapBatches() and parse_strategy("map:3") == MapBatches(3)
    assert parse_strategy("auto") == default_strategy() == parse_strategy(None)
    for bad in ("map:0", "map:x", "vmap:2", "pmap"):
        with pytest.raises(ValueError, match="--batching"):
            parse_strategy(bad)


def test_run_many_compiles_once_and_equals_single_runs(many, monkeypatch):
    """Files of 2-3 steps with 1 or 2 detection slots: at most one compile for all of them (padded to the
    longest and widest), each run's numbers those of `hs.run` alone with the unpadded estimator."""
    estimator, scenarios, seeds, runs, compiled = many
    assert compiled <= 1
    assert [len(r.result.steps) for r in runs] == [2, 3, 3]
    assert all(r.result.timing["compile_s"] == 0 for r in runs[1:])
    compiles = []
    real = compilation.compile_lowered
    monkeypatch.setattr(compilation, "compile_lowered", lambda *a, **k: compiles.append(1) or real(*a, **k))
    shared = sweep.shared_shapes(estimator, scenarios)
    for s, seed, got in zip(scenarios, seeds, runs):
        # hs.run with the padded estimator runs the same executable (no compile); alone, unpadded, the
        # file of 2 steps and 1 detection slot compiles its own program (numbers to rounding).
        for want in [hs.run(shared, s, seed=seed).result] + ([hs.run(estimator, s, seed=seed).result] if seed == 3 else []):
            for a, b in zip(want.steps, got.result.steps, strict=True):
                assert [c.associations for c in a.components] == [c.associations for c in b.components]
                np.testing.assert_allclose([c.weight for c in a.components], [c.weight for c in b.components],
                                           rtol=1e-9, atol=1e-12)
                for key in a.metrics:
                    np.testing.assert_allclose(a.metrics[key], b.metrics[key], rtol=1e-9, atol=1e-12)
    assert len(compiles) == 1  # the padded runs reused run_many's executable; the unpadded one compiled


@pytest.mark.slow  # three compiles: the extended suite, CI
def test_map_over_tracks_gives_the_vmapped_numbers(many):
    """Three tracks (the last one shorter, padded) as one vmap, one by one and in chunks of two (the
    third chunk padded): the same traces. Alone, the padded track gets run_many's program."""
    scenarios = [hs.simulate(t, steps=3 if t < 2 else 2, alpha=0.4) for t in range(3)]
    estimator = sweep.batched(TINY, scenarios)
    inputs = sweep.batch_inputs(estimator, scenarios, seeds=[0, 1, 2])
    runs = {s.describe(): sweep.run_batch(estimator, inputs, strategy=s)
            for s in (VmapBatches(), MapBatches(1), MapBatches(2))}
    assert {r.strategy for r in runs.values()} == {"vmap", "map:1", "map:2"}
    for name in ("map:1", "map:2"):
        _close(runs["vmap"].trace, runs[name].trace)
    # The batch ran `mirror` as the study's AlphaK (batch.shared_classifier); alone, by name, the
    # padded track gets run_many's estimator and its compiled program.
    assert isinstance(estimator.classifier, AlphaK)
    single = sweep.shared_shapes(TINY, scenarios)
    assert single == sweep.shared_shapes(many[0], many[1])
    alone = hs.run(single, scenarios[2], seed=2).result.steps
    got = sweep.step_records(runs["map:1"].trace, 2, scenarios[2])
    assert len(got) == 2
    for a, b in zip(alone, got):
        assert [c.associations for c in a.components] == [c.associations for c in b.components]
        np.testing.assert_allclose([c.weight for c in a.components], [c.weight for c in b.components], rtol=1e-9)


def test_run_many_checks_its_seeds():
    with pytest.raises(ValueError, match="2 seeds for 1 scenarios"):
        hs.run_many(TINY, [hs.simulate(0, steps=2)], seed=[1, 2])


def test_cpu_split_only_before_the_backend_starts_and_when_nobody_chose(monkeypatch):
    """`split_cpu_into_cores` sets no count once JAX's backends run (as here), for one core, or when
    XLA_FLAGS already names one."""
    from hybridslam.studies import strategies

    devices = len(jax.devices())
    monkeypatch.setenv(strategies.CPU_DEVICES_ENV, "3")
    assert strategies.split_cpu_into_cores() == 0 and len(jax.devices()) == devices
    monkeypatch.setenv(strategies.CPU_DEVICES_ENV, "1")
    assert strategies.split_cpu_into_cores() == 0
    monkeypatch.setenv(strategies.CPU_DEVICES_ENV, "4")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    assert strategies.split_cpu_into_cores() == 0
    monkeypatch.setenv(strategies.CPU_DEVICES_ENV, "four")
    with pytest.raises(ValueError, match="HYBRIDSLAM_CPU_DEVICES='four'"):
        strategies.split_cpu_into_cores()


def test_hard_files_are_the_issue_s_files(tmp_path):
    """bench_goals' files-hard workload: paper layout, a tight robot prior, `mirror` at alpha 0.25,
    10 steps of at most 4 detections, seeded (the same files twice)."""
    bench = load_script("scripts/bench_goals.py", "bench_goals")
    paths = bench.hard_files(str(tmp_path), count=6)
    (tmp_path / "again").mkdir()
    again = bench.hard_files(str(tmp_path / "again"), count=1)
    scenarios = [hs.load_scenario(p) for p in paths]
    for s in scenarios:
        np.testing.assert_allclose(np.diag(s.robot_prior_cov), [1.0, 1.0, 0.04])
        assert s.num_steps == 10 and s.num_objects == 6 and s.max_detections <= 4
        assert s.classifier.model == "mirror" and s.classifier.alpha == 0.25
    assert max(s.max_detections for s in scenarios) >= 3
    with open(again[0], encoding="utf-8") as a, open(paths[0], encoding="utf-8") as b:
        assert a.read() == b.read()
