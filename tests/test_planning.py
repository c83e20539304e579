"""Planning: predicted observations come from the belief; moving on towards the objects is informative.

The page runs here (``test_the_page_runs``, marked ``readme``: ``tests/docblocks.py``'s ``run_here``),
in this file's process, and the tests plan on its belief with its settings (horizon 3, capacity 4,
linearized predicted updates, 2 Gauss-Newton iterations; 32 candidates and 4 draws to score, 2 draws
and up to 20 BFGS steps to refine): the same programs, which JAX traces and compiles once for the
page and the tests. The refinement's program never reaches the persistent compilation cache (its
derivatives of the Gauss-Newton update carry lineax's error check, a host callback): only one
process can share it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam import planning

from .docblocks import run_here

HORIZON = 3
SETTINGS = dict(capacity=4, weights="linearized", gn_max_steps=2)  # docs/planning.md's


@pytest.mark.readme
def test_the_page_runs(request):
    """docs/planning.md's example, as a user runs it: finite scores, a refined plan of the page's form."""
    page = run_here(request, "planning.md")
    assert page["scores"].shape == (32,) and np.all(np.isfinite(np.asarray(page["scores"])))
    actions = np.asarray(page["refined"].actions)
    assert actions.shape == (HORIZON, 3) and np.all(np.abs(actions[:, 2]) < 0.6)  # |turn| < max_turn
    np.testing.assert_array_equal(actions[:, :2], [[1.0, 0.0]] * HORIZON)


@pytest.fixture(scope="module")
def ambiguous():
    """docs/planning.md's belief: geometry only, 2 steps, several association hypotheses alive."""
    scenario = hs.simulate(seed=0, steps=2)
    belief = hs.run_estimator(scenario, "hybrid", classifier="none", capacity=8, max_detections=2,
                              smoother="filter").state
    assert int(belief.alive.sum()) >= 2 and float(hs.association_entropy(belief)) > 0.3
    return scenario, belief, planning.prepare(belief, HORIZON, **SETTINGS)


def test_prepare_keeps_the_best_components_normalized(ambiguous):
    _, _, plan = ambiguous
    w = np.exp(np.asarray(plan.belief.log_weights))
    assert plan.belief.capacity == 4 and plan.estimator.batch_axis == planning.PLAN_AXIS
    np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-12)
    assert np.all(np.diff(w) <= 0)  # still sorted by weight
    assert plan.belief.max_steps >= int(plan.belief.k) + HORIZON and plan.room == HORIZON


def test_predicted_observations_follow_the_drawn_world(ambiguous):
    _, _, plan = ambiguous
    key = jax.random.PRNGKey(3)
    world = planning.sample_world(plan.belief, jax.random.split(jax.random.split(key, 3)[0], 1)[0])
    assert world.objects.shape == (6, 3) and world.classes.shape == (6,)
    actions = jnp.array([[1.0, 0.0, 0.0]] * HORIZON)
    odometry, det = planning.predict_observations(plan.belief, actions, key)
    np.testing.assert_array_equal(odometry, actions)
    assert det.geo.shape == (HORIZON, 2, 2) and det.mask.dtype == bool
    ranges = np.asarray(det.geo[..., 0])[np.asarray(det.mask)]
    assert np.all(ranges <= float(plan.belief.model.sensor.max_range) + 2.0)  # detections are of visible objects


def test_looking_at_the_objects_lowers_the_expected_entropy(ambiguous):
    _, _, plan = ambiguous
    forward = jnp.array([[1.0, 0.0, 0.0]] * HORIZON)  # on towards the objects
    still = jnp.zeros((HORIZON, 3))  # stand still: the same view again
    candidates = jnp.stack([forward, still] * 16)  # the page's 32 candidates
    scores = np.asarray(planning.score_candidates(plan, candidates, jax.random.PRNGKey(0), num_draws=4))
    assert np.all(np.isfinite(scores))
    assert np.all(scores[0::2] == scores[0]) and np.all(scores[1::2] == scores[1])  # common random numbers
    entropy_now = float(hs.association_entropy(plan.belief))
    assert float(scores[0]) < entropy_now - 0.05


def test_unprepared_beliefs_are_refused(ambiguous, unchecked_types):
    scenario, _, _ = ambiguous
    raw = hs.Hybrid(capacity=4).init(scenario)
    with pytest.raises(ValueError, match="prepare"):
        planning.score_candidates(raw, jnp.zeros((2, HORIZON, 3)), jax.random.PRNGKey(0))


def test_arc_candidates_shapes():
    c = planning.arc_candidates(8, 5, step_length=0.5, max_turn=0.4, key=jax.random.PRNGKey(0))
    assert c.shape == (8, 5, 3)
    np.testing.assert_allclose(c[..., 0], 0.5)
    assert float(jnp.max(jnp.abs(c[..., 2]))) <= 0.4
    np.testing.assert_allclose(c[0, :, 2], -0.4)  # the arcs come first, evenly spaced


@pytest.mark.slow  # a minute of compiling (gradients through a rollout; the page's): the extended suite, CI
def test_refinement_lowers_the_smooth_objective_within_bounds(ambiguous):
    _, belief, plan = ambiguous
    smooth = planning.prepare(belief, HORIZON, **SETTINGS, visibility_temperature=0.5)  # the page's
    with pytest.raises(ValueError, match="visibility_temperature"):
        planning.refine_actions(plan, jnp.zeros(HORIZON), jax.random.PRNGKey(0))
    start = jnp.array([0.5, -0.5, 0.0])
    r = planning.refine_actions(smooth, start, jax.random.PRNGKey(0), max_turn=0.6, num_draws=2)
    assert float(r.final) < float(r.initial)  # the gradient steps found descent
    assert np.all(np.abs(np.asarray(r.actions[:, 2])) < 0.6)  # max_turn
    np.testing.assert_array_equal(np.asarray(r.actions[:, :2]), [[1.0, 0.0]] * HORIZON)
    # The reported value is the returned plan's: restarted from it (the same compiled program, on
    # the same draws), the objective at the start is `final`, and it never gets worse.
    again = planning.refine_actions(smooth, r.actions[:, 2], jax.random.PRNGKey(0), max_turn=0.6, num_draws=2)
    np.testing.assert_allclose(float(again.initial), float(r.final), rtol=1e-9)
    assert float(again.final) <= float(again.initial)
