"""Tests of the ``hybridslam`` command (in-process through ``hybridslam.cli.main``) and its plot helpers.

JAX compiles dominate: every ``run`` here uses one program (3 steps, 2 detection slots, capacity 8,
50 samples, the filter: the smoother is not these tests' subject, and the filter's program is a
fraction of the full smoother's), which compiles once. It is the demo's program for the mirror
model (the same estimator settings: the classifier and the detection slots named as the demo names
them, on the demo's first track), so the demo adds two (the other classifier models).
"""

from __future__ import annotations

import csv
import json
import pathlib

import equinox as eqx
import numpy as np
import pytest

import hybridslam as hs
from hybridslam import cli
from hybridslam.analysis import plot

# The demo's settings for its mirror-model runs (test_demo_smoke), so that both use one program.
SMALL = ["--samples", "50", "--capacity", "8", "--smoother", "filter",
         "--classifier", "mirror", "--max-detections", "2"]


@pytest.fixture(scope="module")
def scenario_path(tmp_path_factory) -> str:
    """A 3-step simulated scenario written by ``hybridslam simulate`` (seed 0 has a 2-detection step;
    the demo's first track)."""
    path = tmp_path_factory.mktemp("cli") / "scenario.json"
    assert cli.main(["simulate", "--seed", "0", "--steps", "3", "--alpha", "0.25", "-o", str(path)]) == 0
    return str(path)


def error_line(capsys) -> str:
    """stderr must be exactly one line ``hybridslam: error: ...``; return it."""
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("hybridslam: error: ")
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("name, value", [("HYBRIDSLAM_BUCKETS", "four"), ("HYBRIDSLAM_XLA_DEFAULTS", "yes")])
def test_a_bad_environment_variable_is_a_one_line_error_naming_it(scenario_path, tmp_path, capsys, monkeypatch,
                                                                  name, value):
    monkeypatch.setenv(name, value)
    assert cli.main(["run", scenario_path, "-o", str(tmp_path / "r.json")]) == 2
    line = error_line(capsys)
    assert name in line and repr(value) in line
    assert not (tmp_path / "r.json").exists()


def test_simulate_writes_loadable_scenario(scenario_path):
    s = hs.load_scenario(scenario_path)
    assert s.num_steps == 3 and s.num_objects == 6
    assert s.true_robot_poses is not None and s.true_robot_poses.shape == (4, 3)
    assert s.classifier.model == "mirror" and s.classifier.alpha == 0.25 and s.classifier.K == 15.0
    assert s == hs.simulate(0, steps=3, alpha=0.25, K=15.0)


@pytest.mark.slow  # half a minute of compile; the README test runs the same command
def test_run_prints_table_and_writes_result(scenario_path, tmp_path, capsys):
    out = tmp_path / "result.json"
    assert cli.main(["run", scenario_path, "-o", str(out), *SMALL]) == 0
    stdout = capsys.readouterr().out
    result = hs.load_result(out)
    assert [r.k for r in result.steps] == [1, 2, 3]
    assert "samples=50" in result.estimator and "capacity=8" in result.estimator
    assert len(result.timing["step_s"]) == 3
    lines = stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.split()[:3] == ["k", "det", "alive"])
    rows = [line.split() for line in lines[header + 1 : header + 4]]
    assert [int(r[0]) for r in rows] == [1, 2, 3]
    assert [len(r) for r in rows] == [8, 8, 8]  # k, det, alive, entropy, det_cov, err_wmax, err_wavg, ms
    assert "compile time" in stdout


def test_same_seed_same_result(scenario_path, tmp_path):
    """Same seed, same file; and the file the command writes as the run goes (its records in memory
    linked to the previous step's) holds the whole records the API returns."""
    paths = [tmp_path / "a.json", tmp_path / "b.json"]
    for path in paths:
        assert cli.main(["run", scenario_path, "-o", str(path), *SMALL, "--seed", "7"]) == 0
    a, b = (json.loads(p.read_text()) for p in paths)
    assert "timing" in a and "timing" in b
    del a["timing"], b["timing"]
    assert a == b
    estimator = hs.make_estimator("hybrid", samples=50, capacity=8, smoother="filter", classifier="mirror",
                                  max_detections=2)
    api = hs.run(estimator, hs.load_scenario(scenario_path), seed=7).result
    assert hs.load_result(paths[0]).steps == api.steps
    assert a["format"] == "hybridslam-result/2" and "step_associations" in json.dumps(a["steps"][1])
    old = tmp_path / "format1.json"  # for readers of format 1 only
    assert cli.main(["run", scenario_path, "-o", str(old), *SMALL, "--seed", "7", "--result-format", "1"]) == 0
    assert json.loads(old.read_text())["format"] == "hybridslam-result/1"
    assert hs.load_result(old).steps == api.steps
    slim = hs.run(estimator, hs.load_scenario(scenario_path), seed=7, keep_associations=False).result
    assert slim.steps == api.steps  # the same histories, held as links to the previous step's
    assert any(isinstance(c.associations, hs.io.result.History) for step in slim.steps[1:] for c in step.components)
    assert [c.pose_mean.tolist() for step in slim.steps for c in step.components] == \
        [c.pose_mean.tolist() for step in api.steps for c in step.components]


def test_a_run_that_fails_half_way_leaves_no_file_behind(scenario_path, tmp_path, monkeypatch):
    """The records written so far go with the failure: no result file, no temporary file."""
    real = cli.run.run

    def run_then_fail(estimator, scenario, *, on_step, **kwargs):
        def failing(record, info, seconds):
            on_step(record, info, seconds)
            if record.k == 2:
                raise KeyboardInterrupt  # a user's Ctrl-C between steps

        return real(estimator, scenario, on_step=failing, **kwargs)

    monkeypatch.setattr(cli.run, "run", run_then_fail)
    assert cli.main(["run", scenario_path, "-o", str(tmp_path / "r.json"), *SMALL]) == 130
    assert list(tmp_path.iterdir()) == []


def test_run_warns_on_capacity_and_visibility(scenario_path, tmp_path, capsys, monkeypatch):
    """The warnings come from StepInfo; fake the counters on a real run (same compiled step)."""
    real = cli.run.run

    def run_with_bad_news(estimator, scenario, *, on_step, **kwargs):
        def patched(record, info, seconds):
            if record.k == 2:
                info = eqx.tree_at(lambda i: (i.dropped_capacity, i.visibility_ignored), info,
                                   (np.int64(5), np.bool_(True)))
            on_step(record, info, seconds)

        return real(estimator, scenario, on_step=patched, **kwargs)

    monkeypatch.setattr(cli.run, "run", run_with_bad_news)
    assert cli.main(["run", scenario_path, "-o", str(tmp_path / "r.json"), *SMALL]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("WARNING")]
    assert len(warnings) == 2, warnings
    assert "step 2" in warnings[0] and "5 hypotheses" in warnings[0] and "--capacity" in warnings[0]
    assert "step 2" in warnings[1] and "visibility" in warnings[1]


def test_malformed_scenario_is_one_line_error(scenario_path, tmp_path, capsys):
    obj = json.loads(pathlib.Path(scenario_path).read_text())
    del obj["geometric_cov"]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(obj))
    assert cli.main(["run", str(bad), "-o", str(tmp_path / "r.json")]) == 2
    assert error_line(capsys).startswith("hybridslam: error: geometric_cov")
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--classifier", "bogus"], "--classifier"),
        (["--prune-ratio", "0.5"], "prune_ratio"),
        (["--capacity", "0"], "capacity"),
        (["--samples", "x"], "--samples"),
    ],
)
def test_bad_settings_exit_2(scenario_path, tmp_path, capsys, args, message):
    assert cli.main(["run", scenario_path, "-o", str(tmp_path / "r.json"), *args]) == 2
    assert message in error_line(capsys)


def test_missing_input_and_unwritable_output_exit_2(scenario_path, tmp_path, capsys):
    assert cli.main(["run", str(tmp_path / "missing.json"), "-o", str(tmp_path / "r.json")]) == 2
    assert "missing.json" in error_line(capsys)
    assert cli.main(["run", scenario_path, "-o", str(tmp_path / "no" / "dir" / "r.json")]) == 2
    assert "cannot write" in error_line(capsys)
    assert cli.main(["simulate", "-o", str(tmp_path)]) == 2  # a directory
    assert "cannot write" in error_line(capsys)
    assert cli.main([]) == 2
    error_line(capsys)


@pytest.mark.slow  # the demo's compiles, half a minute: the extended suite, CI
def test_demo_smoke(tmp_path, capsys):
    out = tmp_path / "demo"
    # Three classifier models mean three programs; the mirror model's is the ``run`` tests' (SMALL).
    argv = ["demo", "-o", str(out), "--tracks", "1", "--steps", "3", "--capacity", "8", "--samples", "50",
            "--smoother", "filter"]
    assert cli.main(argv) == 0
    with open(out / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == list(cli.demo.CSV_COLUMNS)
    assert len(rows) == 3 * 1 * 3  # models x tracks x steps
    assert {r["model"] for r in rows} == {"mirror", "independent", "none"}
    assert all(r["err_wmax"] != "" and float(r["step_ms"]) > 0 for r in rows)
    for name in ("metrics.png", "posterior.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert hs.load_scenario(out / "scenarios" / "track00.json").num_steps == 3
    assert len(hs.load_result(out / "results" / "none_track00.json").steps) == 3
    stdout = capsys.readouterr().out
    assert all(model in stdout for model in ("mirror", "independent", "none"))


PNG = b"\x89PNG\r\n\x1a\n"


def test_run_draws_the_run_and_plot_draws_a_result_file(scenario_path, tmp_path, capsys):
    out, png = tmp_path / "r.json", tmp_path / "r.png"
    assert cli.main(["run", scenario_path, "-o", str(out), *SMALL, "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == PNG and f"wrote {png}" in capsys.readouterr().out
    assert cli.main(["plot", str(out), "--scenario", scenario_path]) == 0  # beside the result by default
    assert (tmp_path / "r.png").read_bytes()[:8] == PNG and f"wrote {png}" in capsys.readouterr().out
    assert cli.main(["plot", str(out)]) == 2
    assert "--scenario" in error_line(capsys)
    other = tmp_path / "other.json"
    assert cli.main(["simulate", "--seed", "1", "--steps", "4", "-o", str(other)]) == 0
    capsys.readouterr()
    assert cli.main(["plot", str(out), "--scenario", str(other), "-o", str(tmp_path / "x.png")]) == 2
    assert "not a run of this scenario" in error_line(capsys) and not (tmp_path / "x.png").exists()
    assert cli.main(["plot", str(tmp_path), "--scenario", scenario_path]) == 2  # a folder is a study
    assert "result file" in error_line(capsys)
    assert cli.main(["run", scenario_path, "-o", str(out), "--plot", str(tmp_path / "no" / "p.png")]) == 2
    assert "does not exist" in error_line(capsys)


def test_plot_run_draws_a_filter_result_and_a_scenario_without_ground_truth(tmp_path):
    from hybridslam.analysis import consistency
    from hybridslam.sim.hallway import HallwaySetup, hallway

    scenario = hallway(0, 0.01, steps=8, setup=HallwaySetup(length=8.0, width=4.0))
    result, _ = consistency.gated_oracle_result(scenario, 20)  # no trajectory, no objects: as a filter's
    plot.plot_run(scenario, result, tmp_path / "a.png", title="a filter's result")
    plot.plot_run(scenario.replace(true_robot_poses=None), result, tmp_path / "b.png")
    assert all((tmp_path / n).read_bytes()[:8] == PNG for n in ("a.png", "b.png"))
    with pytest.raises(ValueError, match="not a run of this scenario"):
        longer = hallway(0, 0.01, steps=9, setup=HallwaySetup(length=8.0, width=4.0))
        plot.plot_run(longer, result, tmp_path / "c.png")


def test_covariance_ellipse_and_band():
    pts = plot.covariance_ellipse([1.0, 2.0], np.diag([4.0, 1.0]), nsig=2)
    assert np.allclose(pts[0], pts[-1])
    assert np.isclose(np.max(pts[:, 0]), 1.0 + 4.0, atol=0.01) and np.isclose(np.max(pts[:, 1]), 2.0 + 2.0, atol=0.01)
    # every point is on the 2-sigma contour: (p - m)^T S^-1 (p - m) = 4
    d = pts - [1.0, 2.0]
    assert np.allclose(np.einsum("ni,ij,nj->n", d, np.diag([0.25, 1.0]), d), 4.0)
    mean, half = plot.mean_band(np.array([[1.0, 2.0], [3.0, np.nan]]))
    assert np.allclose(mean, [2.0, 2.0])
    assert np.isclose(half[0], 1.96 * np.sqrt(2.0) / np.sqrt(2.0)) and np.isnan(half[1])


def test_a_warning_repeated_at_many_steps_is_printed_three_times_then_counted(capsys):
    """``hybridslam run`` prints each kind of per-step warning (its text, numbers aside) three times,
    the third saying so, and at the end how many more steps had it; other kinds are unaffected."""
    from hybridslam.cli.run import REPEATS, WarningThrottle

    throttle = WarningThrottle()
    for k in range(1, 8):
        throttle(f"step {k}: {k + 4} hypotheses above the pruning threshold dropped for lack of capacity")
    throttle("step 8: the update did not converge for 1 of 4 component(s)")
    throttle.finish()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("WARNING")]
    capacity = [line for line in lines if "lack of capacity" in line]
    assert len(capacity) == REPEATS + 1 == 4
    assert "step 1:" in capacity[0] and "step 3:" in capacity[2] and "not repeated" in capacity[2]
    assert capacity[3].startswith("WARNING: and at 4 more step(s): 5 hypotheses")
    assert sum("did not converge" in line for line in lines) == 1


def test_the_command_line_starts_without_matplotlib():
    """Only the commands that draw import matplotlib (0.3-0.5 s of every start-up otherwise)."""
    import subprocess
    import sys

    code = "import sys, hybridslam.cli; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "False"


def test_a_long_file_under_the_full_smoother_gets_a_note_naming_the_bounded_option():
    import dataclasses

    from hybridslam.cli.run import LONG_RUN_STEPS, long_run_note
    from hybridslam.estimators.smoothers import Filter, Incremental, Lag

    one = hs.simulate(0, steps=1)  # the note reads the step count only
    long, short = (dataclasses.replace(one, steps=one.steps * n) for n in (LONG_RUN_STEPS + 1, LONG_RUN_STEPS))
    note = long_run_note(hs.make_estimator("ml"), long)
    assert note is not None and f"{LONG_RUN_STEPS + 1} steps" in note and "--smoother incremental:" in note
    assert long_run_note(hs.make_estimator("hybrid"), long) is not None
    assert long_run_note(hs.make_estimator("ml"), short) is None
    for smoother in (Lag(50), Incremental(50), Filter()):
        assert long_run_note(hs.make_estimator("ml", smoother=smoother), long) is None
