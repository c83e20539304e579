"""Loop closure during the run (hybridslam.estimators.loops.online): the slot renumbering against a
hand-worked case, a small hallway loop that the hybrid belief misses on its own and closes with
the merge hypotheses added between steps, and the same search for ``multimodal``
(hybridslam.estimators.multimodal.loops): a loop it misses on its own, closed; merged class posteriors."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam import compilation
from hybridslam.analysis.trajectory import error_summary
from hybridslam.estimators.loops import settings as loop_settings
from hybridslam.analysis.recall import closure_recall
from hybridslam.estimators.loops.online import OnlineLoopClosure, _renumbered
from hybridslam.estimators.multimodal.loops import merged_class_posteriors
from hybridslam.sim.hallway import HallwaySetup, hallway


@pytest.fixture(scope="module", autouse=True)
def quick_compiles():
    """The 28-step runs compile as short runs do (LLVM level 0, ``hybridslam.compilation``): XLA's part
    of each compile about halves and the steps, which these runs are few of, take longer. For the
    whole module, so that every run (the CLI's too) finds the same executable."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(compilation, "QUICK_RUN_STEPS", 28)
        yield


def test_merged_slots_are_renumbered_in_creation_order():
    # objects 0..3 in use of 5 slots; 3 is a late copy of 1, and 2 was first detected after 3
    history = np.array([[0, 1], [3, -1], [2, 3], [-1, -1]], dtype=np.int32)
    classes = np.array([0, -1, 1, 1, -1])
    objects = np.arange(15, dtype=float).reshape(5, 3)
    h, c, o, n = _renumbered(history, classes, objects, 4, {3: 1})
    assert n == 3
    np.testing.assert_array_equal(h, [[0, 1], [1, -1], [2, 1], [-1, -1]])
    np.testing.assert_array_equal(c, [0, 1, 1, -1, -1])  # 1 takes the late copy's class; freed slots open
    np.testing.assert_array_equal(o[:3], objects[[0, 1, 2]])
    assert not o[3:].any()
    # without merges, a stretch re-opened into a high slot moves to where its first detection puts it
    h, _, o, n = _renumbered(np.array([[0, 1], [3, -1], [2, 3]], dtype=np.int32), classes, objects, 4, {})
    assert n == 4
    np.testing.assert_array_equal(h, [[0, 1], [2, -1], [3, 2]])
    np.testing.assert_array_equal(o[:4], objects[[0, 1, 3, 2]])


@pytest.fixture(scope="module")
def drifted_loop():
    """A 28-step hallway loop with odometry noise tr 0.06: the hybrid belief alone ends 2 m off."""
    scenario = hallway(2, 0.06, steps=28, setup=HallwaySetup(length=8.0, width=4.0))
    estimator = hs.make_estimator("hybrid", capacity=8, gate=3, weights="linearized")
    return scenario, estimator, hs.run(estimator, scenario).result


def test_merge_hypotheses_close_a_loop_the_belief_misses(drifted_loop):
    scenario, estimator, plain = drifted_loop
    hook = OnlineLoopClosure(estimator, scenario, loop_settings.LoopClosureSettings(gap=10))
    run = hs.run(estimator, scenario, between_steps=hook)
    before, after = error_summary(plain, scenario), error_summary(run.result, scenario)
    assert before["final_smoothed"] > 1.5 and after["final_smoothed"] < 0.5
    assert hook.closures and all(c.log_odds > 0 and c.step > 10 for c in hook.closures)
    for c in hook.closures:  # each names what it changes: no object merged into itself
        assert (c.merges or c.splits) and all(a != b for a, b in c.merges)
        assert str(c).startswith(f"step {c.step}: ") and str(c).endswith(f"(log odds {c.log_odds:.2f})")
    state = run.state
    alive = np.asarray(state.log_weights) > -np.inf
    assert np.isclose(np.logaddexp.reduce(np.asarray(state.log_weights)[alive]), 0.0)
    for i in np.flatnonzero(alive):  # every component names only objects it has, and they have classes
        named = np.asarray(state.history[i])
        assert named.max() < int(state.num_created[i])
        assert np.all(np.asarray(state.classes[i])[int(state.num_created[i]):] == -1)


def test_a_negative_threshold_adds_less_likely_closures_the_belief_would_keep(drifted_loop):
    """``threshold=-log(prune_ratio)``: a closure less likely than the component it came from is added
    as a hypothesis of its own (the loop still closes); with a threshold that lets every verified set
    through, a full belief of equal weights takes none that is no likelier than its weakest component:
    each is declined and counted."""
    scenario, estimator, _ = drifted_loop
    hook = OnlineLoopClosure(estimator, scenario, loop_settings.LoopClosureSettings(gap=10, threshold=-5.01))
    run = hs.run(estimator, scenario, between_steps=hook)
    assert any(c.log_odds < 0 for c in hook.closures) and all(c.log_odds > -5.01 for c in hook.closures)
    assert error_summary(run.result, scenario)["final_smoothed"] < 0.5

    def equal_weights(belief):
        log_w = np.asarray(belief.log_weights)
        alive = log_w > -np.inf
        return eqx.tree_at(lambda b: b.log_weights, belief,
                           jnp.asarray(np.where(alive, -np.log(alive.sum()), -np.inf)))

    full = {}  # step: whether the belief was full when searched
    anything = OnlineLoopClosure(estimator, scenario, loop_settings.LoopClosureSettings(gap=10, threshold=-1e9))

    def between(k, belief):
        belief = equal_weights(belief)
        full[k] = bool(np.all(np.asarray(belief.log_weights) > -np.inf))
        return anything(k, belief)

    hs.run(estimator, scenario, between_steps=between)
    assert sum(full.values()) > len(full) // 2 and anything.declined > 0
    # into a full belief only a closure likelier than its parent, so than the weakest (an empty slot takes any)
    assert all(c.log_odds > 0 for c in anything.closures if full[c.step])


def test_online_loop_closure_refuses_what_it_cannot_do(drifted_loop):
    scenario, estimator, _ = drifted_loop
    with pytest.raises(ValueError, match="full smoother"):
        OnlineLoopClosure(hs.make_estimator("hybrid", smoother="filter"), scenario)
    with pytest.raises(ValueError, match="full smoother"):
        OnlineLoopClosure(hs.make_estimator("multimodal", smoother="filter"), scenario)
    with pytest.raises(ValueError, match="got ml"):
        OnlineLoopClosure(hs.make_estimator("ml"), scenario)
    with pytest.raises(ValueError, match="known map"):
        OnlineLoopClosure(estimator, scenario.replace(discovery=None))
    with pytest.raises(ValueError, match="every"):
        OnlineLoopClosure(estimator, scenario, every=0)


def test_the_command_line_closes_loops_during_the_run(drifted_loop, tmp_path, capsys):
    from hybridslam.cli import main

    scenario, _, _ = drifted_loop
    hs.save_scenario(scenario, tmp_path / "s.json")
    argv = ["run", str(tmp_path / "s.json"), "-o", str(tmp_path / "r.json"), "--capacity", "8", "--gate", "3",
            "--weights", "linearized", "--close-loops", "10"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "loop closure during the run:" in out and "hypotheses added: step" in out
    result = hs.load_result(tmp_path / "r.json")
    assert error_summary(result, scenario)["final_smoothed"] < 0.5
    assert result.estimator.endswith("hypotheses added)")
    assert main(argv[:-2] + ["--smoother", "filter", "--close-loops"]) == 2
    assert "--close-loops" in capsys.readouterr().err


def test_between_steps_runs_between_steps_only_and_an_identity_hook_changes_nothing(drifted_loop):
    scenario, estimator, plain = drifted_loop
    seen: list[int] = []

    def identity(k, state):
        seen.append(k)
        return state

    result = hs.run(estimator, scenario, between_steps=identity).result
    assert seen == list(range(1, scenario.num_steps))  # after steps 1..T-1, never after the last
    assert [s.components[0].pose_mean.tolist() for s in result.steps] == \
        [s.components[0].pose_mean.tolist() for s in plain.steps]
    np.testing.assert_array_equal(result.trajectory, plain.trajectory)


@pytest.fixture(scope="module")
def multimodal_loop():
    """A 28-step hallway loop (seed 0, odometry noise tr 0.06) that ``multimodal`` alone does not
    close: none of its 15 re-detections of a landmark seen more than 10 steps before is associated
    with that landmark's first object, and it ends 2.5 m off (under load, about 1 min with compiles)."""
    scenario = hallway(0, 0.06, steps=28, setup=HallwaySetup(length=8.0, width=4.0))
    estimator = hs.make_estimator("multimodal", capacity=4, samples=64)
    return scenario, estimator, hs.run(estimator, scenario).result


def test_multimodal_merges_a_revisited_landmark_during_the_run(multimodal_loop):
    scenario, estimator, plain = multimodal_loop
    hook = OnlineLoopClosure(estimator, scenario, loop_settings.LoopClosureSettings(gap=10))
    run = hs.run(estimator, scenario, between_steps=hook)
    before, after = closure_recall(scenario, plain), closure_recall(scenario, run.result)
    # Ground truth for the evaluation only: the estimator and the search never read it.
    assert before.redetections > 0 and before.top_closed == 0
    assert after.top_closed == after.redetections  # every re-detection on its landmark's first object
    assert error_summary(plain, scenario)["final"] > 1.5 and error_summary(run.result, scenario)["final"] < 0.5
    assert hook.closures and any(c.merges for c in hook.closures)
    assert all(c.log_odds > 0 and c.step > 10 and all(a != b for a, b in c.merges) for c in hook.closures)
    # The belief is never emptied: weights normalized, each component names only objects it has,
    # and its class posteriors are distributions where it has objects.
    state = run.state
    log_w = np.asarray(state.log_weights)
    alive = log_w > -np.inf
    assert alive.sum() >= 1 and np.isclose(np.logaddexp.reduce(log_w[alive]), 0.0)
    for i in np.flatnonzero(alive):
        n = int(state.num_created[i])
        assert np.asarray(state.history[i]).max() < n
        assert not np.asarray(state.observed[i])[n:].any()
        np.testing.assert_allclose(np.exp(np.asarray(state.class_log_probs[i])).sum(-1), 1.0, atol=1e-9)


def test_merged_class_posteriors_multiply_their_parts():
    # 3 slots of 2 classes, uniform prior: object 0 and 2 merged (0.8·0.6 against 0.2·0.4), 1 kept
    lp = np.log(np.array([[0.8, 0.2], [0.3, 0.7], [0.6, 0.4]]))
    observed = np.array([True, False, True])
    prior = np.full((3, 2), 0.5)
    out, seen = merged_class_posteriors(lp, observed, prior, ((0, 2), (1,)))
    np.testing.assert_allclose(np.exp(out[0]), [0.48 / 0.56, 0.08 / 0.56], rtol=1e-12)
    np.testing.assert_allclose(out[1], lp[1], rtol=1e-12)
    np.testing.assert_allclose(np.exp(out[2]), [0.5, 0.5], rtol=1e-12)  # a freed slot starts uniform
    np.testing.assert_array_equal(seen, [True, False, False])
    # parts that rule each other's classes out: the first part's posterior, never NaN
    with np.errstate(divide="ignore"):
        lp2 = np.log(np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]]))
        out2, _ = merged_class_posteriors(lp2, observed, prior, ((0, 1),))
    np.testing.assert_array_equal(out2[0], lp2[0])


def test_the_command_line_closes_multimodal_loops_during_the_run(multimodal_loop, tmp_path, capsys):
    from hybridslam.cli import main

    scenario, _, _ = multimodal_loop
    hs.save_scenario(scenario, tmp_path / "s.json")
    argv = ["run", str(tmp_path / "s.json"), "-o", str(tmp_path / "r.json"), "--estimator", "multimodal",
            "--capacity", "4", "--samples", "64", "--close-loops", "10"]
    assert main(argv) == 0
    assert "hypotheses added: step" in capsys.readouterr().out
    result = hs.load_result(tmp_path / "r.json")
    assert error_summary(result, scenario)["final"] < 0.5
