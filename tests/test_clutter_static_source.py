"""A known map with a clutter density and a spurious source that stands still (another robot seen
again and again at one place): gpda must not follow it where clutter explains it better. A
detection more likely clutter than not adds no factor, and the clutter mass of the others shrinks
their pull (PDA, :func:`hybridslam.estimators.gpda.clutter_weights`)."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridslam as hs
from hybridslam.driver import run
from hybridslam.estimators.gpda import clutter_weights
from hybridslam.io.scenario import Step

OFFSET = 0.15  # rad: the spurious detection's bearing beyond object 0's (2 bearing sds of S, inside the gate)


def _stationary(clutter_log_density: float, steps: int = 8, offset: float = OFFSET) -> hs.Scenario:
    """A robot standing at the origin (heading sd 0.1 rad) that sees, at every step, one detection
    of no object at object 0's range (5 m) but ``offset`` rad beside it: a static spurious source
    (another robot standing still). Its true pose never changes; objects are known to 1 mm."""
    base = hs.simulate(2, steps=1, setup=hs.PaperSetup(max_detections=2, max_range=12.0))
    x, y = base.object_prior_means[0, :2]
    spurious = dataclasses.replace(base.steps[0].detections[0], range=float(math.hypot(x, y)),
                                   bearing=float(math.atan2(y, x)) + offset, true_object=None)
    n = base.num_objects
    return base.replace(
        steps=tuple(Step(odometry=np.zeros(3), detections=(spurious,)) for _ in range(steps)),
        robot_prior_cov=np.diag([1e-4, 1e-4, 0.01]), geometric_cov=np.diag([0.01, 0.0004]),
        object_prior_covs=np.tile(np.eye(3) * 1e-6, (n, 1, 1)), clutter_log_density=clutter_log_density,
        true_robot_poses=np.zeros((steps + 1, 3)))


def _headings(clutter_log_density: float) -> tuple[np.ndarray, list[int]]:
    out = run(hs.make_estimator("gpda"), _stationary(clutter_log_density))
    return (np.array([float(s.components[0].pose_mean[2]) for s in out.result.steps]),
            [int(i.rejected) for i in out.infos])


def test_a_static_source_more_likely_clutter_never_pulls_the_pose():
    """Clutter is the likeliest option at every step (log density 1 over [range, bearing]): the
    detection is rejected each time and the heading stays put (a factor of its 8% association
    pulled it 0.138 rad, 92% of the way, at the first step, and the later ones followed)."""
    heading, rejected = _headings(1.0)
    assert rejected == [1] * len(rejected)
    assert np.max(np.abs(heading)) < 0.01 * OFFSET


def test_the_clutter_mass_shrinks_the_pull():
    """Clutter less likely than the object (log density 0.6): the first step moves the heading part
    of the way (PDA: by about the association probability; Eq. 3.7's factor alone moved it 93%),
    and a source seen again and again is still followed, as an object would be."""
    heading, rejected = _headings(0.6)
    assert rejected == [0] * len(rejected)
    assert -0.8 * OFFSET < heading[0] < -0.2 * OFFSET
    assert heading[-1] < -0.9 * OFFSET


@settings(max_examples=50, deadline=None)
@given(p=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3), b0=st.floats(0.0, 0.99),
       spread=st.lists(st.floats(1.0, 1e4), min_size=3, max_size=3))
def test_clutter_weights_never_exceed_the_association_probability(p, b0, spread):
    """``w_g ≤ p_g``, with equality (Eq. 3.7) without clutter mass."""
    p_ = np.array([p]) * (1.0 - b0) / max(sum(p), 1e-12)
    w = np.asarray(clutter_weights(jnp.asarray(p_), jnp.array([b0]), jnp.array([spread])))
    assert np.all(w <= p_ * (1 + 1e-12)) and np.all(w >= 0.0)
    np.testing.assert_allclose(np.asarray(clutter_weights(jnp.asarray(p_), jnp.zeros(1), jnp.array([spread]))), p_,
                               rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("b0", [0.3, 0.8])
def test_one_candidate_gets_the_pda_gain(b0):
    """One candidate, a linear scalar model: the weighted factor's gain is ``(1 − β₀)`` times the
    full one (the PDA filter's mean), where ``S = λ Γ`` exactly."""
    prior, gamma = 4.0, 0.01
    lam = (prior + gamma) / gamma
    w = float(np.asarray(clutter_weights(jnp.array([[1.0 - b0]]), jnp.array([b0]), jnp.array([[lam]])))[0, 0])
    gain = prior / (prior + gamma / w)
    assert gain == pytest.approx((1.0 - b0) * prior / (prior + gamma), rel=1e-9)

