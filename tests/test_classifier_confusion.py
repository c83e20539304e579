"""The confusion-matrix classifier (thesis Eq. 2.14-2.15): likelihood, sampling, a hybrid run."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam.io.scenario import Classifier
from hybridslam.models.classifier import Confusion
from hybridslam.models.registry import make_classifier

MATRIX = np.array([[0.7, 0.1, 0.2], [0.2, 0.6, 0.3], [0.1, 0.3, 0.5]])  # matrix[label, class]
VIEW = jnp.array([0.6, 0.8])


def test_log_likelihood_is_the_log_matrix_entry_of_the_argmax_label():
    clf = Confusion(MATRIX)
    for scores in ([0.1, 0.8, 0.1], [0.0, 0.0, 1.0], [2.0, -1.0, 0.5]):
        label = int(np.argmax(scores))
        for c in range(3):
            got = clf.log_likelihood(jnp.asarray(scores), c, VIEW)
            assert float(got) == pytest.approx(np.log(MATRIX[label, c]), abs=1e-14)
    r, _ = clf.residuals(jnp.array([0.2, 0.3, 0.5]), VIEW)
    np.testing.assert_array_equal(r, 0.0)  # no Gaussian semantic factor for Gauss-Newton


def test_sampling_frequencies_match_the_column():
    clf = Confusion(MATRIX)
    keys = jax.random.split(jax.random.PRNGKey(0), 20000)
    for c in range(3):
        z = jax.vmap(lambda k: clf.sample(k, c, VIEW))(keys)
        assert np.all(np.sum(z, axis=1) == 1.0)  # one-hot
        np.testing.assert_allclose(np.mean(z, axis=0), MATRIX[:, c], atol=0.015)  # ~4 sigma at n = 20000


def test_make_classifier_and_model_from_scenario_build_it():
    assert isinstance(make_classifier("confusion", 3, matrix=MATRIX), Confusion)
    with pytest.raises(ValueError, match="classifier.matrix: a 3-class matrix, expected 2"):
        make_classifier("confusion", 2, matrix=MATRIX)
    with pytest.raises(ValueError, match="needs its confusion matrix"):
        make_classifier("confusion", 2)
    scenario = hs.simulate(0, steps=1)
    model = hs.model_from_scenario(scenario.replace(classifier=Classifier("confusion", matrix=np.eye(2))))
    np.testing.assert_array_equal(model.sensor.classifier.matrix, np.eye(2))
    with pytest.raises(ValueError, match="'confusion' needs a matrix"):
        hs.model_from_scenario(scenario, "confusion")


@pytest.mark.slow  # a whole run's compile; the suite's time
def test_hybrid_run_realizes_the_detected_label():
    """Every detection says class 1 (a one-hot score vector); with a 90%-accurate matrix and a uniform
    prior the best component realizes class 1 for every detected object."""
    scenario = hs.simulate(0, steps=3)
    steps = tuple(
        dataclasses.replace(s, detections=tuple(dataclasses.replace(d, scores=np.array([0.0, 1.0]))
                                                for d in s.detections))
        for s in scenario.steps
    )
    matrix = np.array([[0.9, 0.1], [0.1, 0.9]])
    scenario = scenario.replace(steps=steps, classifier=Classifier("confusion", matrix=matrix))
    run = hs.run_estimator(scenario, capacity=4, weights="linearized")
    last = run.result.steps[-1]
    assert sum(c.weight for c in last.components) == pytest.approx(1.0)
    best = last.components[0]
    seen = {o for assoc in best.associations for o in assoc}
    assert seen and all(best.classes[o] == 1 for o in seen)
    assert all(c == -1 for n, c in enumerate(best.classes) if n not in seen)
    # The class-0 twin of the best association is 9x less likely per realized object.
    twins = [c for c in last.components if c.associations == best.associations and c is not best]
    for twin in twins:
        assert twin.weight < best.weight
