"""The sweep engine: batched runs equal single runs, kill-and-resume, sharding over 4 devices and
over two processes.

One tiny study (3 alphas x 1 model x 3 tracks x 3 steps, capacity 4, deterministic
``linearized`` weights so that there is one short compile) is run once in this process; the
other tests compare against its table, and run their batches, file studies and single runs in its
shapes and settings, so that they reuse its programs (JAX compiles dominate: see tests/conftest.py).
The subprocesses share the run's persistent compilation cache and the study's exported program
(:mod:`hybridslam.studies.exported`): a one-device subprocess of the same settings traces and
compiles nothing.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

import hybridslam as hs
from hybridslam import cli
from hybridslam.studies import batch as sweep
from hybridslam.studies import study
from hybridslam.studies.strategies import CPU_DEVICES_ENV

TINY = dict(alphas=(0.1, 0.4, 0.7), models=("mirror",), tracks=3, steps=3)
ESTIMATOR = hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=4)
CLI_ARGS = ["--alphas", "0.1,0.4,0.7", "--models", "mirror", "--tracks", "3", "--steps", "3",
            "--capacity", "4", "--weights", "linearized", "--smoother", "filter"]
# The CLI in a child process that SIGKILLs itself right after its first cell record reaches the
# disk, half way through writing the second one (a real kill, at a deterministic point).
KILLED_AFTER_ONE_CELL = """
import os, signal, sys
from hybridslam import cli
from hybridslam.studies import study
append = study.Records.append
def append_then_die(self, record):
    if self.done:
        with open(self.path, "a", encoding="utf-8") as f:
            f.write('{"cell": {"alpha": 0.4, "mo')
        os.kill(os.getpid(), signal.SIGKILL)
    append(self, record)
study.Records.append = append_then_die
sys.exit(cli.main(sys.argv[1:]))
"""
# The CLI without its plot (drawn from the table in this process: test_cli_plot_and_sweep_errors).
WITHOUT_PLOT = """
import sys
from hybridslam import cli
from hybridslam.cli import sweep
sweep.draw = lambda folder, rows: []
sys.exit(cli.main(sys.argv[1:]))
"""
# The tiny study in each of two processes (``jax.distributed`` on CPU, gloo collectives): the cluster
# recipe of docs/sweeps.md on two local processes of one CPU device each.
TWO_PROCESSES = """
import sys
import jax
pid, port, folder = int(sys.argv[1]), sys.argv[2], sys.argv[3]
jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=2, process_id=pid)
import hybridslam as hs
from hybridslam.studies import study
spec = study.AlphaStudy(alphas=(0.1, 0.4, 0.7), models=("mirror",), tracks=3, steps=3,
                        estimator=hs.Hybrid(weights=hs.Linearized(), capacity=4, smoother=hs.Filter()))
rows = study.run_alpha_study(spec, folder)
print("process", jax.process_index(), "of", jax.process_count(), "devices", len(jax.devices()), "rows", len(rows))
"""


def _alone(scenario: hs.Scenario, seed: int) -> hs.Result:
    """``hybridslam.run`` of one track with the tiny study's settings (one program for 3-step tracks and shorter)."""
    return hs.run_estimator(scenario, classifier="mirror", capacity=4, weights="linearized", seed=seed,
                            max_detections=2, max_steps=3, smoother="filter").result


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The uninterrupted single-device run: (folder, table text, rows)."""
    folder = str(tmp_path_factory.mktemp("tiny"))
    rows = study.run_alpha_study(study.AlphaStudy(**TINY, estimator=ESTIMATOR), folder)
    with open(os.path.join(folder, study.TABLE), encoding="utf-8") as f:
        return folder, f.read(), rows


@pytest.fixture(scope="module")
def cache_env(shared_compilation_cache):
    """The subprocesses' environment: the run's compilation cache and XLA flags (conftest: the flags are
    part of the cache's key), one CPU device (the CLI would otherwise split the host into one per core)."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if "xla_force_host_platform_device_count" not in f]
    return dict(os.environ, XLA_FLAGS=" ".join(flags), **{CPU_DEVICES_ENV: "1"})


def _same_table(got: str, expected: str) -> None:
    """Equal keys, metrics to 1e-9 (other devices or processes run other programs: rounding may differ)."""
    exp_rows = [line.split(",") for line in expected.splitlines()]
    got_rows = [line.split(",") for line in got.splitlines()]
    assert [r[:5] for r in got_rows] == [r[:5] for r in exp_rows]
    for e, g in zip(exp_rows[1:], got_rows[1:]):
        np.testing.assert_allclose([float(v or "nan") for v in g[5:]], [float(v or "nan") for v in e[5:]],
                                   rtol=1e-9, atol=1e-12, equal_nan=True)


def _sweep_cmd(folder: str, *extra: str, python: tuple[str, ...] = ("-m", "hybridslam")) -> list[str]:
    return [sys.executable, *python, "sweep", *CLI_ARGS, *extra, "-o", folder]


def test_table_layout(tiny):
    folder, text, rows = tiny
    lines = text.splitlines()
    assert lines[0] == ",".join(study.ALPHA_COLUMNS)
    assert len(lines) == 1 + 3 * 3 * 3 == 1 + len(rows)
    keys = [(r["alpha"], r["track"], r["step"]) for r in rows]
    assert keys == [(a, t, k) for a in TINY["alphas"] for t in range(3) for k in (1, 2, 3)]
    assert {r["seed"] for r in rows} == {0, 1, 2}
    records = [json.loads(line) for line in pathlib.Path(folder, study.RECORDS).read_text(encoding="utf-8").splitlines()]
    assert records[0]["format"] == study.RECORD_FORMAT and len(records) == 1 + 3
    assert [r["cell"] for r in records[1:]] == [{"alpha": a, "model": "mirror"} for a in TINY["alphas"]]


def test_batched_run_equals_single_runs(tiny):
    """A track in a batch gets the numbers `hybridslam.run` gives it alone (same seed)."""
    scenarios = [hs.simulate(t, steps=3, alpha=0.4) for t in range(3)]
    estimator = sweep.batched(hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=4, classifier="mirror", max_detections=2),
                              scenarios)
    run = sweep.run_batch(estimator, sweep.batch_inputs(estimator, scenarios, seeds=[0, 1, 2]))
    assert run.compile_s == 0.0  # the study compiled this shape already: one executable per shape
    for t in (0, 2):
        alone = _alone(scenarios[t], t).steps
        batched = sweep.step_records(run.trace, t, scenarios[t])
        for a, b in zip(alone, batched):
            assert [c.associations for c in a.components] == [c.associations for c in b.components]
            np.testing.assert_allclose([c.weight for c in a.components], [c.weight for c in b.components],
                                       rtol=1e-9, atol=1e-12)
            for key in a.metrics:
                np.testing.assert_allclose(a.metrics[key], b.metrics[key], rtol=1e-9, atol=1e-12)


@pytest.mark.slow  # a batch width of its own, 20 s of compiles: the extended suite, CI
def test_wide_batches_run_as_slices(tiny, monkeypatch):
    """More tracks than MAX_TRACKS_PER_DEVICE: equal slices in sequence, same numbers. (Slices of one
    track: the program the memory test below splits into; tracks padded to fill a batch are
    test_sharded_over_four_devices_equals_one's, on the same code path.)"""
    scenarios = [hs.simulate(t, steps=3, alpha=0.4) for t in range(3)]
    estimator = sweep.batched(hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=4, classifier="mirror", max_detections=2),
                              scenarios)
    inputs = sweep.batch_inputs(estimator, scenarios, seeds=[0, 1, 2])
    whole = sweep.run_batch(estimator, inputs).trace
    monkeypatch.setattr(sweep, "MAX_TRACKS_PER_DEVICE", 1)
    plans = []
    sliced = sweep.run_batch(estimator, inputs, on_plan=plans.append).trace
    assert (plans[0].slices, plans[0].width) == (3, 1)
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(sliced)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.slow  # the batch width of the test above: the extended suite, CI
def test_batches_too_big_for_memory_are_split(tiny, monkeypatch):
    """A batch whose compiled program needs more memory than the budget runs as smaller slices (halved
    until it fits, here down to one track each), with the same numbers, and says so."""
    scenarios = [hs.simulate(t, steps=3, alpha=0.4) for t in range(3)]
    estimator = sweep.batched(hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=4, classifier="mirror", max_detections=2),
                              scenarios)
    inputs = sweep.batch_inputs(estimator, scenarios, seeds=[0, 1, 2])
    whole = sweep.run_batch(estimator, inputs)
    assert whole.plan.slices == 1
    monkeypatch.setattr(sweep, "memory_budget", lambda mesh: 1)
    plans = []
    split = sweep.run_batch(estimator, inputs, on_plan=plans.append)
    assert plans[0].slices == 3 and plans[0].width == 1 and "3 batch(es) of 1" in plans[0].describe(3)
    for a, b in zip(jax.tree.leaves(whole.trace), jax.tree.leaves(split.trace)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.slow  # a sweep killed in a subprocess (the study's program from the caches): the extended suite, CI
def test_resume_after_kill_gives_the_same_table(tiny, tmp_path, cache_env, capsys):
    """A real kill (a process's SIGKILL half way through a record), then ``hybridslam sweep`` again on
    the folder (here in this process) ends with the table of the run that never stopped."""
    _, expected, _ = tiny
    folder = str(tmp_path / "killed")
    killed = subprocess.run(_sweep_cmd(folder, python=("-c", KILLED_AFTER_ONE_CELL)), env=cache_env,
                            capture_output=True, text=True, timeout=300)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    records = os.path.join(folder, study.RECORDS)
    text = pathlib.Path(records).read_text(encoding="utf-8")
    assert text.count("\n") == 2 and not text.endswith("\n")  # header, one cell, half a line
    with open(os.path.join(folder, study.TABLE), encoding="utf-8") as f:
        assert f.read() == "\n".join(expected.splitlines()[:1 + 9]) + "\n"  # the finished cell's rows

    capsys.readouterr()
    assert cli.main(["sweep", *CLI_ARGS, "-o", folder]) == 0
    assert "resuming: 1 of 3 cells already recorded" in capsys.readouterr().out
    with open(os.path.join(folder, study.TABLE), encoding="utf-8") as f:
        assert f.read() == expected
    lines = pathlib.Path(records).read_text(encoding="utf-8").splitlines()
    assert len(lines) == 1 + 3 and all(json.loads(line) for line in lines)


@pytest.mark.slow  # a sweep in a subprocess over four host devices: the extended suite, CI
def test_sharded_over_four_devices_equals_one(tiny, tmp_path, cache_env):
    _, expected, _ = tiny
    env = dict(cache_env, XLA_FLAGS=f"{cache_env['XLA_FLAGS']} --xla_force_host_platform_device_count=4".strip())
    folder = str(tmp_path / "sharded")
    # 3 tracks on 4 devices also exercises the padding.
    out = subprocess.run(_sweep_cmd(folder, python=("-c", WITHOUT_PLOT)), env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "4 device(s)" in out.stdout
    records = [json.loads(line) for line in pathlib.Path(folder, study.RECORDS).read_text(encoding="utf-8").splitlines()][1:]
    assert all(r["devices"] == 4 for r in records)
    with open(os.path.join(folder, study.TABLE), encoding="utf-8") as f:
        _same_table(f.read(), expected)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # two processes compiling the sweep, a minute: the extended suite, CI
def test_two_processes_give_the_single_process_table(tiny, tmp_path, cache_env):
    """The tiny study across two local processes (``jax.distributed``, one CPU device each) gives the
    single-process table; only process 0 writes it."""
    _, expected, _ = tiny
    two = tmp_path / "two"
    port = str(_free_port())
    procs = [subprocess.Popen([sys.executable, "-c", TWO_PROCESSES, str(i), port, str(two)], env=cache_env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
        assert "of 2 devices 2 rows 27" in out, out
    _same_table((two / study.TABLE).read_text(encoding="utf-8"), expected)
    records = (two / study.RECORDS).read_text(encoding="utf-8").splitlines()
    assert len(records) == 1 + 3 and all('"devices": 2' in line for line in records[1:])


def test_other_settings_are_refused(tiny):
    folder, _, _ = tiny
    with pytest.raises(study.StudyError, match=r"capacity: 4 there, 8 now"):
        study.Records(folder, study.AlphaStudy(**TINY, estimator=hs.Hybrid(weights=hs.Linearized(), smoother=hs.Filter(), capacity=8)).header())


def test_a_subset_of_the_grid_reuses_finished_cells(tiny):
    """Another grid on the same folder runs only its new cells (here none: a subset)."""
    folder, _, rows = tiny
    calls = []
    subset = study.AlphaStudy(alphas=(0.4,), models=("mirror",), tracks=3, steps=3, estimator=ESTIMATOR)
    again = study.run_alpha_study(subset, folder, on_cell=lambda *a: calls.append(a))
    assert calls == [] and again == [r for r in rows if r["alpha"] == 0.4]


@pytest.mark.slow  # a file study and single runs in the tiny study's programs: the extended suite, CI
def test_scenario_files_give_result_files_equal_to_single_runs(tiny, tmp_path):
    """`--scenarios`: files of equal shape run as one batch; each gets the result `run` would write."""
    files = tmp_path / "logs"
    files.mkdir()
    # Files of different lengths run in one batch: the shorter ones are padded with inactive steps.
    scenarios = {f"log{t}": hs.simulate(10 + t, steps=3 if t < 2 else 2, alpha=0.4) for t in range(3)}
    for name, s in scenarios.items():
        hs.save_scenario(s, str(files / f"{name}.json"))
    out = str(tmp_path / "out")
    spec = study.FileStudy(tuple(study.scenario_paths(str(files))), None, 7, ESTIMATOR)
    rows = study.run_file_study(spec, out)
    assert len(rows) == 3 + 3 + 2 and {r["scenario"] for r in rows} == {f"{n}.json" for n in scenarios}
    record = json.loads(pathlib.Path(out, study.RECORDS).read_text(encoding="utf-8").splitlines()[1])
    assert record["compile_s"] == 0.0  # padded to 3 steps and 2 slots: the tiny study's program
    for name, s in scenarios.items():
        got = hs.load_result(os.path.join(out, "results", f"{name}.json"))
        want = _alone(s, 7)
        assert got.timing is not None and len(got.timing["step_s"]) == s.num_steps
        assert len(got.steps) == len(want.steps) == s.num_steps
        for a, b in zip(want.steps, got.steps):
            assert [c.associations for c in a.components] == [c.associations for c in b.components]
            np.testing.assert_allclose([c.weight for c in a.components], [c.weight for c in b.components], rtol=1e-9)
            np.testing.assert_allclose(a.metrics["entropy"], b.metrics["entropy"], rtol=1e-9, atol=1e-12)
    calls = []
    study.run_file_study(spec, out, on_cell=lambda *a: calls.append(a))
    assert calls == []  # finished groups are not run again


@pytest.mark.slow  # two smoother compiles (batched and single): the extended suite, CI
def test_scenario_files_run_by_a_smoother_carry_its_trajectory(tmp_path):
    """A smoother's result files from `--scenarios` carry the smoothed `trajectory` and `objects` that `run` writes,
    cut to each file's own length (the shorter file ran padded). Run as the `independent` model: the batch
    runs it as an AlphaK (batch.shared_classifier), which smooths class realizations apart that
    `Independent` smooths once (step.py's ``by_class``): the same trajectories and weights."""
    files = tmp_path / "logs"
    files.mkdir()
    scenarios = {"short": hs.simulate(3, steps=3), "long": hs.simulate(4, steps=4)}
    for name, s in scenarios.items():
        hs.save_scenario(s, str(files / f"{name}.json"))
    hybrid = hs.Hybrid(weights=hs.Linearized(), capacity=4, max_detections=2, max_steps=4)
    spec = study.FileStudy(tuple(study.scenario_paths(str(files))), ("independent",), 0, hybrid)
    study.run_file_study(spec, str(tmp_path / "out"))
    alone = dataclasses.replace(hybrid, classifier="independent")
    for name, s in scenarios.items():
        got = hs.load_result(str(tmp_path / "out" / "results" / f"{name}.independent.json"))
        want = hs.run(alone, s).result
        assert "classifier=independent" in got.estimator
        assert got.trajectory is not None and got.trajectory.shape == (s.num_steps + 1, 3)
        np.testing.assert_allclose(got.trajectory, want.trajectory, atol=1e-9)
        assert got.objects is not None and got.objects.shape == (s.num_objects, 3)  # and the objects
        np.testing.assert_allclose(got.objects, want.objects, atol=1e-9)
        for a, b in zip(want.steps, got.steps, strict=True):
            assert [c.associations for c in a.components] == [c.associations for c in b.components]
            np.testing.assert_allclose([c.weight for c in a.components], [c.weight for c in b.components],
                                       rtol=1e-9, atol=1e-12)


def test_files_are_grouped_by_shape_and_model():
    a, b = hs.simulate(0, steps=3), hs.simulate(1, steps=4)
    spec = study.FileStudy(("a.json", "b.json", "c.json"), None)
    cells = study.file_groups(spec, {"a.json": a, "b.json": b, "c.json": a})
    # Files of different lengths share a cell (the shorter ones are padded with inactive steps).
    assert [(c["run_as"], c["scenarios"]) for c in cells] == [("mirror", ["a.json", "b.json", "c.json"])]
    two = study.file_groups(study.FileStudy(("a.json",), ("mirror", "none")), {"a.json": a})
    assert [c["run_as"] for c in two] == ["mirror", "none"]


def test_cli_plot_and_sweep_errors(tiny, tmp_path, capsys):
    folder, _, _ = tiny
    assert cli.main(["plot", folder]) == 0
    assert os.path.getsize(os.path.join(folder, "alpha_sweep.png")) > 10_000
    cases = [
        (["plot", str(tmp_path)], "no table.csv"),
        (["sweep", "--scenarios", str(tmp_path / "nothing*.json"), "-o", str(tmp_path / "o")], "no scenario files"),
        (["sweep", "--scenarios", str(tmp_path), "--alphas", "0.1", "-o", str(tmp_path / "o")], "--alphas: only for simulated"),
        (["sweep", "--models", "mirror,learned:" + str(tmp_path / "missing.eqx"), "-o", str(tmp_path / "o")], "missing.eqx"),
        (["sweep", "--models", "mirrror", "-o", str(tmp_path / "o")], "unknown model(s) mirrror"),
        (["sweep", "--alphas", "0.1,x", "-o", str(tmp_path / "o")], "--alphas: expected"),
        (["sweep", "--alphas", "0.1", "--tracks", "3", "--steps", "3", "--capacity", "8", "--weights",
          "linearized", "--smoother", "filter", "--models", "mirror", "-o", folder], "capacity: 4 there, 8 now"),
    ]
    for argv, message in cases:
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("hybridslam: error: ") and message in err, (argv, err)


def test_learned_model_names_resolve_to_the_model_file(tmp_path):
    model = hs.Learned(2, (4,), key=jax.random.PRNGKey(0))
    path = str(tmp_path / "m.eqx")
    hs.save_classifier(model, path)
    loaded = study.resolve_model("learned:" + path)
    assert isinstance(loaded, hs.Learned)
    vp = np.array([0.6, 0.8])
    np.testing.assert_array_equal(loaded.class_means(vp), model.class_means(vp))
    assert study.resolve_model("mirror") == "mirror"
    with pytest.raises(ValueError, match="nope.eqx"):
        study.resolve_model("learned:" + str(tmp_path / "nope.eqx"))
