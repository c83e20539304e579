"""The loop-closure pass (hybridslam.estimators.loops.closure): its Bayes factor against closed-form
Gaussian integrals, its search against brute force, and a small hallway whose loop it closes."""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest

from hybridslam.analysis import consistency
from hybridslam.estimators.loops import closure as lc
from hybridslam.estimators.loops import merge as loop_merge, search as loop_search, settings as loop_settings
from hybridslam.io.result import Result, load_result, save_result
from hybridslam.sim.hallway import HallwaySetup, hallway


def _log_gaussian_integral(h: np.ndarray, g: np.ndarray) -> float:
    """``log ∫ exp(−½ θᵀHθ + gᵀθ) dθ``."""
    d = h.shape[0]
    return 0.5 * d * math.log(2 * math.pi) - 0.5 * np.linalg.slogdet(h)[1] + 0.5 * g @ np.linalg.solve(h, g)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_bayes_factor_is_the_ratio_of_the_two_models_evidence(seed):
    # A linear-Gaussian likelihood over [x, o_0, o_1, o_2] (3 + 9 numbers) with flat priors: merging
    # o_2 into o_0 (their positions equal) changes the evidence by exactly log N(0; Aμ, AΣAᵀ).
    rng = np.random.default_rng(seed)
    j = rng.standard_normal((20, 12))
    h = j.T @ j + 0.1 * np.eye(12)
    g = rng.standard_normal(12)
    mean, cov = np.linalg.solve(h, g), np.linalg.inv(h)
    # the merged model: o_2's position replaced by o_0's, θ = T φ
    t = np.eye(12)[:, [c for c in range(12) if c not in (9, 10)]]
    t[9, 3], t[10, 4] = 1.0, 1.0
    expected = _log_gaussian_integral(t.T @ h @ t, t.T @ g) - _log_gaussian_integral(h, g)
    got = loop_search.log_bayes_factor(mean, cov, [(2, 0)], new_log_density=0.0, ranges=np.ones(3))
    assert got == pytest.approx(expected, abs=1e-9)
    # the new-object density and the creating range enter per merge
    shifted = loop_search.log_bayes_factor(mean, cov, [(2, 0)], new_log_density=-2.0, ranges=np.full(3, 3.0))
    assert shifted == pytest.approx(got + 2.0 + math.log(3.0), abs=1e-9)


def test_the_beam_search_with_room_for_everything_is_the_brute_force_maximum():
    rng = np.random.default_rng(3)
    n = 6
    j = rng.standard_normal((40, 3 + 3 * n))
    cov = np.linalg.inv(j.T @ j)
    mean = rng.standard_normal(3 + 3 * n)
    cands = {3: [0, 1], 4: [0, 2], 5: [1, 2]}
    ranked, dropped = loop_search.search(mean, cov, cands, -1.0, np.full(n, 2.0), beam=1000, log_odds=0.5)
    assert dropped == 0
    best = max(
        (sum(([(a, b)] if b is not None else [] for a, b in zip(cands, choice)), []) for choice in
         itertools.product(*[c + [None] for c in cands.values()])
         if len({b for b in choice if b is not None}) == sum(b is not None for b in choice)),
        key=lambda m: loop_search.log_bayes_factor(mean, cov, m, -1.0, np.full(n, 2.0)) + 0.5 * len(m))
    assert set(ranked[0][0]) == set(best)
    assert ranked[0][1] == pytest.approx(loop_search.log_bayes_factor(mean, cov, best, -1.0, np.full(n, 2.0)) + 0.5 * len(best))
    assert [lbf for _, lbf in ranked] == sorted((lbf for _, lbf in ranked), reverse=True)
    _, dropped = loop_search.search(mean, cov, cands, -1.0, np.full(n, 2.0), beam=2)
    assert dropped > 0


def test_candidates_are_the_gated_pairs_of_a_direct_loop():
    rng = np.random.default_rng(4)
    num, n = 10, 12
    history = np.full((50, 3), -1, dtype=np.int32)
    for o in range(num):
        for k in rng.choice(50, size=rng.integers(1, 4), replace=False):
            history[k, rng.integers(3)] = o
    j = rng.standard_normal((60, 3 + 3 * n))
    cov, mean = 5.0 * np.linalg.inv(j.T @ j), 2.0 * rng.standard_normal(3 + 3 * n)
    classes = rng.integers(-1, 2, size=n)
    settings = loop_settings.LoopClosureSettings(gap=5, gate=30.0)
    steps = [np.flatnonzero((history == o).any(axis=1)) for o in range(num)]
    expected = {}
    for a in range(num):
        near = []
        for b in range(num):
            if not (steps[b][0] < steps[a][0] and steps[a][0] - steps[b][-1] > settings.gap):
                continue
            if min(classes[a], classes[b]) >= 0 and classes[a] != classes[b]:
                continue
            pa, pb = slice(3 + 3 * a, 5 + 3 * a), slice(3 + 3 * b, 5 + 3 * b)
            d = mean[pa] - mean[pb]
            s = cov[pa, pa] + cov[pb, pb] - cov[pa, pb] - cov[pb, pa]
            if d @ np.linalg.solve(s, d) < settings.gate:
                near.append((d @ np.linalg.solve(s, d), b))
        if near:
            expected[a] = [b for _, b in sorted(near)][: settings.candidates]
    assert expected and loop_search.candidates(mean, cov, history, classes, num, settings) == expected


GAP = 10


@pytest.fixture(scope="module")
def small_loop():
    """A 24-step hallway loop (then 4 more steps) and a run that associated every detection right,
    except that landmarks re-detected after the loop became new objects (what the gated estimators do)."""
    scenario = hallway(0, 0.01, steps=28, setup=HallwaySetup(length=8.0, width=4.0))
    result, truth_of = consistency.gated_oracle_result(scenario, GAP)
    late = {s for s, o in truth_of.items() if any(t < s and truth_of[t] == o for t in truth_of)}
    return scenario, result, truth_of, late


@pytest.fixture(scope="module")
def closed_small_loop(small_loop):
    """The pass over ``small_loop`` (the closed result and its report): two tests read it."""
    scenario, result, _, _ = small_loop
    return lc.close_loops(scenario, result, loop_settings.LoopClosureSettings(gap=GAP))


def test_a_small_loop_is_closed_onto_the_right_landmarks(small_loop, closed_small_loop, tmp_path):
    scenario, result, truth_of, late = small_loop
    assert len(late) >= 2  # the scenario has a loop to close
    closed, report = closed_small_loop
    merges = [m for c in report.closures for m in c.merges]
    assert {a for a, _ in merges} == set(late)
    assert all(truth_of[a] == truth_of[b] for a, b in merges)
    assert not report.failed and report.rejected == 0
    truth = np.asarray(scenario.true_robot_poses)
    assert np.linalg.norm(closed.trajectory[-1, :2] - truth[-1, :2]) < 0.3
    top = closed.steps[-1].components[0]
    assert max(max(a, default=-1) for a in top.associations) + 1 == len(truth_of) - len(late)
    assert closed.steps[:-1] == result.steps[:-1]  # the online records are the run's own
    save_result(closed, tmp_path / "closed.json")
    assert load_result(tmp_path / "closed.json") == closed


def test_score_merges_gives_the_first_rounds_score_and_cost(small_loop, closed_small_loop):
    scenario, result, truth_of, _ = small_loop
    settings = loop_settings.LoopClosureSettings(gap=GAP)
    _, report = closed_small_loop
    first = report.closures[0]
    score = lc.score_merges(scenario, result, first.merges, settings)
    assert score.verified and score.log_odds == pytest.approx(first.log_bayes_factor, abs=1e-9)
    assert score.cost_rise == pytest.approx(first.cost_after - first.cost_before, abs=1e-9)
    # a merge of two different landmarks: the Bayes factor says no and the re-solved cost rejects it
    a, b = first.merges[0]
    other = next(o for o in range(a) if truth_of[o] != truth_of[a] and o != b)
    wrong = lc.score_merges(scenario, result, [(a, other)], settings)
    assert wrong.log_bayes_factor < 0 < score.log_odds and not wrong.verified
    with pytest.raises(ValueError, match="distinct objects"):
        lc.score_merges(scenario, result, [(a, b), (a, other)], settings)
    with pytest.raises(ValueError, match="distinct objects"):
        lc.score_merges(scenario, result, [(a, 10_000)], settings)


def test_bad_inputs_name_what_is_wrong(small_loop):
    scenario, result, _, _ = small_loop
    with pytest.raises(ValueError, match="known map"):
        lc.close_loops(scenario.replace(discovery=None), result)
    with pytest.raises(ValueError, match="steps"):
        lc.close_loops(scenario, Result("test", result.steps[:-1]))
    with pytest.raises(ValueError, match="LoopClosureSettings.gate"):
        loop_settings.LoopClosureSettings(gate=-1.0)


def test_the_command_line_closes_the_loop_and_reports_bad_files(small_loop, tmp_path, capsys):
    from hybridslam.cli import main
    from hybridslam.io.scenario import save_scenario

    scenario, result, truth_of, _ = small_loop
    save_scenario(scenario, tmp_path / "s.json")
    save_result(result, tmp_path / "r.json")
    assert main(["close-loops", str(tmp_path / "s.json"), str(tmp_path / "r.json"), "-o", str(tmp_path / "c.json"),
                 "--gap", str(GAP)]) == 0
    out = capsys.readouterr().out
    assert "6 objects merged" in out and "after: smoothed APE" in out
    # The map error of the closed map: every object against the landmark its detections are of.
    after = re.search(r"after: .*map error ([0-9.]+) m \((\d+) objects\)", out)
    assert after is not None, out
    assert float(after.group(1)) < 0.2 and int(after.group(2)) == len(set(truth_of.values()))
    assert load_result(tmp_path / "c.json").trajectory is not None
    save_scenario(hallway(0, 0.01, steps=28, known_map=True, setup=HallwaySetup(length=8.0, width=4.0)),
                  tmp_path / "known.json")
    assert main(["close-loops", str(tmp_path / "known.json"), str(tmp_path / "r.json"), "-o",
                 str(tmp_path / "x.json")]) == 2
    assert "known map" in capsys.readouterr().err
    assert main(["close-loops", str(tmp_path / "s.json"), str(tmp_path / "r.json"), "-o", str(tmp_path / "x.json"),
                 "--beam", "0"]) == 2
    assert "LoopClosureSettings.beam" in capsys.readouterr().err


def test_the_runs_own_closures_are_reopened_at_each_pause_longer_than_the_gap():
    history = np.full((40, 2), -1, dtype=np.int32)
    history[0:3, 0] = 0  # object 0: steps 0-2, then again 30-32 (a closure of the run's own)
    history[30:33, 0] = 0
    history[5:35, 1] = 1  # object 1: never pauses
    h, cls, origin, added = loop_merge.reopen(history, np.array([1, 0, -1, -1]), gap=20)
    assert added == 1
    assert (h[0:3, 0] == 0).all() and (h[30:33, 0] == 2).all() and (h[5:35, 1] == 1).all()
    assert cls.tolist() == [1, 0, 1, -1] and origin.tolist()[:3] == [0, 1, 0]
    same, _, _, none = loop_merge.reopen(history, np.array([1, 0]), gap=20)  # no free slot: left as it is
    assert none == 0 and (same == history).all()
    assert loop_merge.pauses(history, gap=20) == 1 and loop_merge.pauses(history, gap=30) == 0  # what was left closed



def test_a_run_whose_object_slots_are_full_still_has_its_closures_reopened_and_merged_back(small_loop):
    """The run closed its loop itself and used every slot: the pass re-opens the closures into new
    slots (after the run it is not bound by the run's shapes) and merges them back."""
    import dataclasses

    scenario, result, truth_of, late = small_loop
    top = result.steps[-1].components[0]
    history = np.full((len(top.associations), max(map(len, top.associations))), -1)
    for j, a in enumerate(top.associations):
        history[j, : len(a)] = a
    old_of = {a: min(t for t in truth_of if truth_of[t] == truth_of[a]) for a in late}
    h, cls, used = loop_merge.compact(history, np.asarray(top.classes), old_of)  # the run's own closures
    full = dataclasses.replace(top, associations=[r[: len(a)].tolist() for r, a in zip(h, top.associations)],
                               classes=list(cls[: len(used)]))  # no free slot
    run = dataclasses.replace(result, steps=[*result.steps[:-1],
                                             dataclasses.replace(result.steps[-1], components=[full])])
    assert loop_merge.reopen(h, cls[: len(used)], GAP)[3] == 0 < loop_merge.pauses(h, GAP)  # the run's slots cannot hold them
    closed, report = lc.close_loops(scenario, run, loop_settings.LoopClosureSettings(gap=GAP))
    assert report.reopened == loop_merge.pauses(h, GAP) and not report.failed
    merges = [m for c in report.closures for m in c.merges]
    assert merges and all(a == b for a, b in merges)  # each stretch back onto its own object
    final = closed.steps[-1].components[0]
    assert len(final.classes) == len(used)
    assert max(max(a, default=-1) for a in final.associations) + 1 == len(used)
