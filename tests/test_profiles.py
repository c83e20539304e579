"""Settings chosen by the file (``hybridslam.estimators.profiles``) and ``hybridslam run --profile``."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridslam as hs
from hybridslam import cli
from hybridslam.estimators import profiles
from hybridslam.estimators.loops.online import OnlineLoopClosure
from hybridslam.datasets.mrclam import import_mrclam
from hybridslam.io.scenario import Classifier, Detection, Discovery, Step
from hybridslam.sim.hallway import hallway

MRCLAM = os.path.join(os.path.dirname(__file__), "data", "mrclam")
LARGE_HYBRID = {"capacity": 16, "gate": 3, "weights": "linearized"}


def _twelve_objects(steps: int = 3) -> hs.Scenario:
    """The paper's layout with 12 objects instead of 6: small and quick, but past the exact limit."""
    poses = tuple((4.0 + 2.5 * (i // 2), 3.0 * (-1) ** i, 0.3 * i) for i in range(12))
    return hs.simulate(seed=0, steps=steps, setup=hs.PaperSetup(object_poses=poses))


def test_the_paper_files_keep_the_estimators_own_defaults():
    four = hs.PaperSetup(max_detections=4)  # the benchmark's paper layout
    for scenario in (hs.simulate(seed=0, steps=10), hs.simulate(seed=1, steps=40, setup=four)):
        for name in hs.ESTIMATORS:
            p = hs.recommended(scenario, name)
            assert (p.kind, p.options, p.close_loops, p.flags()) == ("paper", {}, None, "")
            assert hs.make_estimator(name, scenario=scenario) == hs.make_estimator(name)


def test_a_hallway_file_gets_the_readme_hallway_settings():
    scenario = hallway(0, 0.021, steps=75)
    p = hs.recommended(scenario)
    assert p.kind == "large" and p.options == LARGE_HYBRID and p.close_loops == 20
    assert p.flags() == "--capacity 16 --gate 3 --weights linearized --close-loops"
    assert hs.recommended(scenario, "multimodal").options == {"capacity": 16}
    for name in ("ml", "gpda", "max-mixture"):  # they gate to 3 candidates already
        assert hs.recommended(scenario, name).options == {} and hs.recommended(scenario, name).close_loops is None
    estimator = hs.make_estimator("hybrid", scenario=scenario)
    assert estimator == hs.make_estimator("hybrid", **LARGE_HYBRID)
    assert isinstance(p.between_steps(estimator, scenario), OnlineLoopClosure)
    # The paper profile is the defaults, whatever the file.
    paper = hs.recommended(scenario, profile="paper")
    assert paper.options == {} and paper.close_loops is None
    assert hs.make_estimator("hybrid", scenario=scenario, profile="paper") == hs.Hybrid()


def test_a_long_file_gets_the_incremental_smoother_and_no_loop_closure():
    scenario = hallway(0, 0.021, steps=profiles.LONG_RUN_STEPS + 1)
    p = hs.recommended(scenario)
    assert p.kind == "large+long" and p.options == {**LARGE_HYBRID, "smoother": "incremental:50"} and p.close_loops is None
    # The single-Gaussian estimators' step is mostly the window's solve: a shorter window.
    assert hs.recommended(scenario, "ml").options == {"smoother": "incremental:20"}
    assert hs.make_estimator("ml", scenario=scenario).smoother == hs.Incremental(20)
    assert hs.make_estimator("hybrid", scenario=scenario).smoother == hs.Incremental(50)
    assert hs.recommended(scenario.replace(steps=scenario.steps[:profiles.LONG_RUN_STEPS])).options == LARGE_HYBRID


def test_real_data_without_classes_gets_no_loop_closure():
    known, unknown = import_mrclam(MRCLAM, 1), import_mrclam(MRCLAM, 1, unknown_map=True)
    assert known.num_classes == 1 and unknown.discovery is not None
    for scenario in (known, unknown):
        p = hs.recommended(scenario)
        assert p.kind == "large" and p.options == LARGE_HYBRID and p.close_loops is None
    assert "without classes" in hs.recommended(unknown).reason
    # The same file with class scores would close loops: the rule is the file's properties, no name.
    with_classes = unknown.replace(num_classes=2, classifier=Classifier("mirror", alpha=0.5, K=15.0))
    assert hs.recommended(with_classes).close_loops == 20


BASE = hs.simulate(seed=0, steps=1)


def _stub(slots: int, detections: int, steps: int, unknown: bool, classes: int, model: str) -> hs.Scenario:
    """A scenario with these properties (not a consistent one: :func:`recommended` reads only them)."""
    seen = Step(np.zeros(3), tuple(Detection(1.0, 0.0, np.full(classes, 1.0 / classes)) for _ in range(detections)))
    objects = 0 if unknown else slots
    return BASE.replace(
        object_prior_means=np.zeros((objects, 3)), object_prior_covs=np.broadcast_to(np.eye(3), (objects, 3, 3)),
        class_prior=np.full((objects, classes), 1.0 / classes),
        discovery=Discovery(slots, -3.0, 1.0) if unknown else None,
        steps=(seen,) + (Step(np.zeros(3), ()),) * (steps - 1), num_classes=classes, classifier=Classifier(model))


@settings(max_examples=200, deadline=None)
@given(slots=st.integers(0, 200), detections=st.integers(0, 20), steps=st.integers(1, 2000), unknown=st.booleans(),
       classes=st.integers(1, 4), model=st.sampled_from(["none", "mirror", "confusion"]),
       name=st.sampled_from(list(hs.ESTIMATORS)))
def test_the_rule(slots, detections, steps, unknown, classes, model, name):
    scenario = _stub(slots, detections, steps, unknown, classes, model)
    p = profiles.recommended(scenario, name)
    small = slots <= profiles.EXACT_MAX_OBJECTS and detections <= profiles.EXACT_MAX_DETECTIONS
    long = steps > profiles.LONG_RUN_STEPS
    assert p.kind.startswith("paper" if small else "large") and p.kind.endswith("long") == long
    lag = 50 if name in ("hybrid", "multimodal") else 20
    assert (p.options.get("smoother") == f"incremental:{lag}") == long
    assert (p.options.get("capacity") == 16) == (not small and name in ("hybrid", "multimodal"))
    assert (p.close_loops is not None) == (name == "hybrid" and not small and not long and unknown
                                           and classes >= 2 and model != "none")
    # Explicit options always win, and the paper profile adds nothing.
    explicit = {"capacity": 5, "smoother": "filter", "gate": None}
    merged = p.merged(**explicit)
    assert merged["capacity"] == 5 and merged["smoother"] == "filter" and merged.get("gate") == p.options.get("gate")
    assert p.loops(smoother="filter") is None and p.loops(smoother="full") == p.close_loops
    # the parsed smoothers too (what --smoother gives): only a whole-trajectory one keeps the search
    assert p.loops(smoother=hs.Incremental(50)) is None and p.loops(smoother=hs.Full()) == p.close_loops
    assert profiles.recommended(scenario, name, "paper").options == {}


def test_draws_drop_the_chosen_deterministic_weights():
    p = hs.recommended(hallway(0, 0.021, steps=75))
    assert p.merged(samples=32) == {"capacity": 16, "gate": 3, "samples": 32}
    assert p.merged(samples=32, weights="sampled")["weights"] == "sampled"
    assert hs.make_estimator("hybrid", scenario=hallway(0, 0.021, steps=75), samples=32).weights == hs.LaplaceIS(32)
    with pytest.raises(ValueError, match="profile"):
        hs.recommended(hs.simulate(seed=0, steps=2), profile="fast")


def test_run_with_no_flags_on_a_paper_file_is_the_paper_profile(tmp_path, capsys, monkeypatch):
    """No flags on a paper file and ``--profile paper`` hand the run the same estimator and options (the
    estimator's own defaults); the run stops there (a whole run of the defaults, capacity 64 and the
    full smoother, is the README's ``hybridslam run scenario.json``: tests/test_readme_run.py)."""
    path = tmp_path / "s.json"
    hs.save_scenario(hs.simulate(seed=0, steps=3), path)
    received: list = []

    def stop(estimator, scenario, **kwargs):
        received.append((estimator, scenario, kwargs.pop("on_step") is not None, kwargs))
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.run, "run", stop)
    assert cli.main(["run", str(path), "-o", str(tmp_path / "auto.json")]) == 130
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("settings for a 3-step file with 6 objects (known map)")
    assert "the hybrid estimator's own defaults" in out and "capacity=64" in out and "weights=laplace-is" in out
    assert cli.main(["run", str(path), "-o", str(tmp_path / "paper.json"), "--profile", "paper"]) == 130
    assert capsys.readouterr().out.splitlines()[0] == "settings: --profile paper: the estimator's own defaults"
    assert received[0] == received[1]
    assert received[0][0] == hs.Hybrid() and received[0][3] == {"seed": 0, "between_steps": None,
                                                                "keep_associations": False}


def test_run_prints_what_it_chose_and_flags_override(tmp_path, capsys, monkeypatch):
    path = tmp_path / "s.json"
    hs.save_scenario(_twelve_objects(), path)
    assert cli.main(["run", str(path), "-o", str(tmp_path / "r.json"), "--smoother", "filter"]) == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert first.startswith("settings for a 3-step file with 12 objects (known map)")
    assert "--capacity 16 --gate 3 --weights linearized" in first and "explicit flags override" in first
    assert "capacity=16" in out and "gate_candidates=3" in out and "weights=linearized" in out
    assert len(hs.load_result(tmp_path / "r.json").steps) == 3
    # The overrides change the settings line and the estimator handed to the run: that is checked,
    # and the run stops there (the whole run is the one above's; each estimator would compile its own).
    received: list = []

    def stop(estimator, scenario, **kwargs):
        received.append(estimator)
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.run, "run", stop)
    assert cli.main(["run", str(path), "-o", str(tmp_path / "r.json"), "--smoother", "filter", "--capacity", "8",
                     "--samples", "16"]) == 130
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert first.split(": ", 1)[1].startswith("--gate 3 (") and "overridden: --capacity, --weights" in first
    assert "capacity=8" in out and "gate_candidates=3" in out and "weights=laplace-is, samples=16" in out
    assert "capacity=8" in received[-1].describe() and "weights=laplace-is, samples=16" in received[-1].describe()
    assert cli.main(["run", str(path), "-o", str(tmp_path / "r.json"), "--profile", "paper", "--smoother",
                     "filter"]) == 130
    assert "capacity=64" in capsys.readouterr().out and "capacity=64" in received[-1].describe()
    assert cli.main(["run", str(path), "-o", str(tmp_path / "r.json"), "--profile", "fast"]) == 2
    assert cli.main(["run", str(path), "-o", str(tmp_path / "r.json"), "--close-loops", "--no-close-loops"]) == 2
    assert "--no-close-loops" in capsys.readouterr().err


def test_run_chooses_loop_closure_on_an_unknown_map_with_classes(tmp_path, capsys, monkeypatch):
    """No run: the settings line and the hook ``run`` builds, before it compiles anything."""
    scenario = hallway(0, 0.021, steps=30)
    path = tmp_path / "s.json"
    hs.save_scenario(scenario, path)
    hooks: list = []

    def stop(estimator, scenario, *, between_steps=None, **kwargs):
        hooks.append((estimator, between_steps))
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.run, "run", stop)
    for extra, expected in (([], True), (["--no-close-loops"], False), (["--smoother", "lag:10"], False),
                            (["--estimator", "ml"], False)):
        hooks.clear()
        assert cli.main(["run", str(path), "-o", str(tmp_path / "r.json"), *extra]) == 130
        first = capsys.readouterr().out.splitlines()[0]
        assert ("--close-loops" in first.split(": ", 1)[1].split(" (")[0]) == expected, (extra, first)
        assert isinstance(hooks[0][1], OnlineLoopClosure) == expected
    assert hooks[0][0] == hs.make_estimator("ml")  # the thesis's estimators keep their own defaults
