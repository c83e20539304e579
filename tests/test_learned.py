"""Learned classifier models (Eq. 2 fitted from data): recovery of the mirror model, files, wiring.

One fit, shared by the module: 4000 samples (2000 per class, uniform viewpoints) from
``Mirror(alpha=0.25, K=15)``, the default network (16, 16) and weight prior.
"""

from __future__ import annotations

import json
import os
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridslam as hs
from hybridslam.io.scenario import (
    Classifier,
    ScenarioError,
    load_scenario,
    parse_scenario,
    save_scenario,
    scenario_to_json,
)
from hybridslam.models.learned import mean_nll, sample_scores, viewpoint_features

TRUE = hs.Mirror(0.25, 15.0)
GRID = viewpoint_features(jnp.linspace(-jnp.pi, jnp.pi, 72, endpoint=False))  # every 5°


@pytest.fixture(scope="module")
def samples():
    return tuple(np.asarray(a) for a in sample_scores(TRUE, 4000, jax.random.PRNGKey(0)))


@pytest.fixture(scope="module")
def fitted(samples) -> hs.Learned:
    return hs.fit_classifier(*samples, seed=0)


@pytest.fixture(scope="module")
def model_file(fitted, tmp_path_factory) -> str:
    path = str(tmp_path_factory.mktemp("learned") / "mirror.eqx")
    hs.save_classifier(fitted, path)
    return path


@eqx.filter_jit
def _on_grid(model: hs.ClassifierModel) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Means ``(72, M, M)``, ``R_c`` and covariances ``Σ_c = (R_cᵀ R_c)⁻¹`` ``(72, M, M, M)`` on GRID."""
    r = jax.vmap(model.class_sqrt_informations)(GRID)
    return jax.vmap(model.class_means)(GRID), r, jnp.linalg.inv(jnp.swapaxes(r, -1, -2) @ r)


def test_recovers_the_mirror_model(fitted, samples):
    """h_c and Σ_c of the fit match Eq. 18 at 72 viewpoints (every 5°), both classes.

    Tolerances: mean |Δh| < 0.008 and max |Δh| < 0.02 (the mirror mean swings by alpha = 0.25
    around the circle; the score noise sd is about 0.07); covariance relative error
    ‖Σ̂ − Σ‖_F / ‖Σ‖_F below 0.10 on average and 0.20 at worst. This fit achieves 0.0024 / 0.0072
    and 0.047 / 0.092; fits of other sample seeds (1-3) stay within 0.0041 / 0.015 and 0.050 / 0.14.
    The viewpoint-independent model (Sec. V), by contrast, is off by up to alpha/2 = 0.125 in the mean.
    """
    (h_fit, _, s_fit), (h_true, _, s_true) = _on_grid(fitted), _on_grid(TRUE)
    h_err = np.abs(h_fit - h_true)
    assert h_err.mean() < 0.008 and h_err.max() < 0.02
    rel = np.linalg.norm(s_fit - s_true, axis=(-2, -1)) / np.linalg.norm(s_true, axis=(-2, -1))
    assert rel.mean() < 0.10 and rel.max() < 0.20
    # The fit's likelihood is the truth's, to within what 4000 samples can tell apart.
    assert abs(float(mean_nll(fitted, *samples)) - float(mean_nll(TRUE, *samples))) < 0.01


def test_classifier_interface(fitted):
    """R_c is upper-triangular with a positive diagonal, and log_likelihood is the Gaussian of Eq. 2."""
    means, r, covs = _on_grid(fitted)
    assert r.shape == (72, 2, 2, 2) and means.shape == (72, 2, 2)
    np.testing.assert_array_equal(np.tril(np.asarray(r), -1), 0.0)
    assert bool(jnp.all(jnp.diagonal(r, axis1=-2, axis2=-1) > 0))
    z, i = jnp.array([0.6, 0.3]), 9
    log_lik = eqx.filter_jit(lambda m, c: m.log_likelihood(z, c, GRID[i]))
    for c in range(2):
        want = jax.scipy.stats.multivariate_normal.logpdf(z, means[i, c], covs[i, c])
        np.testing.assert_allclose(log_lik(fitted, jnp.array(c)), want, rtol=1e-10)
    # The weights are traced leaves: a gradient reaches every layer.
    grads = eqx.filter_jit(eqx.filter_grad(lambda m: m.log_likelihood(z, jnp.array(0), GRID[i])))(fitted)
    assert all(bool(jnp.any(layer.weight != 0)) for layer in grads.layers)


def test_fit_is_deterministic(samples):
    """Two fits of the same data and seed give the same weights. On 400 of the samples (200 per
    class): a fit of all 4000 runs BFGS for seconds; the determinism is the fit's, not the data size's."""
    subset = tuple(a[:400] for a in samples)  # the classes take turns (sample_scores): 200 each
    first, again = (hs.fit_classifier(*subset, seed=0) for _ in range(2))
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(again)):
        np.testing.assert_array_equal(a, b)


def test_save_load_round_trip(fitted, model_file):
    loaded = hs.load_classifier(model_file)
    assert isinstance(loaded, hs.Learned) and loaded.hidden == fitted.hidden == (16, 16)
    for a, b in zip(_on_grid(loaded), _on_grid(fitted)):
        np.testing.assert_array_equal(a, b)
    assert isinstance(hs.make_classifier("learned", 2, path=model_file), hs.Learned)


def test_bad_files_are_named(model_file, tmp_path):
    data = pathlib.Path(model_file).read_bytes()
    cases = {
        "missing.eqx": None,
        "empty.eqx": b"",
        "truncated.eqx": data[:-64],
        "other_shape.eqx": data.replace(b'"hidden": [16, 16]', b'"hidden": [16, 8]'),
        "wrong_format.eqx": data.replace(b"classifier/1", b"classifier/9"),
    }
    messages = {
        "missing.eqx": "cannot read: No such file",
        "empty.eqx": r"not a hybridslam-learned-classifier/1 file \(no JSON header line\)",
        "truncated.eqx": "weights are truncated or do not match the header",
        "other_shape.eqx": r"weights are truncated or do not match the header \(num_classes=2, hidden=\[16, 8\]\)",
        "wrong_format.eqx": "expected format 'hybridslam-learned-classifier/1'",
    }
    for name, content in cases.items():
        path = tmp_path / name
        if content is not None:
            path.write_bytes(content)
        with pytest.raises(ValueError, match=rf"^learned classifier '{path}': {messages[name]}"):
            hs.load_classifier(path)
    with pytest.raises(ValueError, match=r"^classifier\.path: the 'learned' model needs"):
        hs.make_classifier("learned", 2)
    with pytest.raises(ValueError, match=r"^classifier\.path: .* is a model of 2 classes, expected 3"):
        hs.make_classifier("learned", 3, path=model_file)


def test_bad_samples_are_refused(unchecked_types):
    z = np.zeros((4, 2))
    with pytest.raises(ValueError, match=r"^viewpoints: expected shape \(4,\)"):
        hs.fit_classifier(np.array([0, 0, 1, 1]), np.zeros(3), z)
    with pytest.raises(ValueError, match=r"^classes\[2\]: expected an integer in \[0, 2\), got 2"):
        hs.fit_classifier(np.array([0, 1, 2, 1]), np.zeros(4), z)
    with pytest.raises(ValueError, match=r"^classes: class 1 has 1 samples"):
        hs.fit_classifier(np.array([0, 0, 0, 1]), np.zeros(4), z)
    z[0, 0] = np.nan
    with pytest.raises(ValueError, match=r"^scores: not all finite"):
        hs.fit_classifier(np.array([0, 0, 1, 1]), np.zeros(4), z)


# --------------------------------------------------------------------------- #
# Wiring: the estimator and scenario files
# --------------------------------------------------------------------------- #


@pytest.fixture(scope="module")
def two_steps() -> hs.Scenario:
    return hs.simulate(0, steps=2)


# The paper's sampled weights (Eq. 16) compile in about half the time of laplace-is; the steps of
# both tests below run one compiled program (the same settings, shapes and classifier file format).
# The filter: the classifier inside the step is the subject, not the smoother (the filter's program
# is a fraction of the full smoother's).
SETTINGS = {"capacity": 4, "samples": 32, "max_detections": 2, "weights": "sampled", "smoother": "filter"}


@pytest.mark.slow  # a step's compile with the MLP inside; the suite's time
def test_step_with_learned_model(fitted, model_file, two_steps):
    """The fitted network inside the estimator's steps (read from its file, as a scenario names it)."""
    run = hs.run_estimator(two_steps.replace(classifier=Classifier("learned", path=model_file)), **SETTINGS)
    assert isinstance(run.state.model.sensor.classifier, hs.Learned)
    for a, b in zip(jax.tree_util.tree_leaves(run.state.model.sensor.classifier), jax.tree_util.tree_leaves(fitted)):
        np.testing.assert_array_equal(a, b)
    w = run.belief.weights[run.belief.alive]
    assert w.size >= 1 and bool(jnp.all(jnp.isfinite(w)))
    np.testing.assert_allclose(float(w.sum()), 1.0, rtol=1e-12)


@pytest.mark.slow  # a minute-scale compile of its own; the suite's time
def test_scenario_key_and_relative_path(model_file, two_steps, tmp_path, monkeypatch):
    """``{"model": "learned", "path": ...}``: relative to the scenario file, round trip, a run."""
    folder = tmp_path / "scenarios"
    (folder / "models").mkdir(parents=True)
    os.link(model_file, folder / "models" / "mirror.eqx")
    scenario = two_steps.replace(classifier=Classifier("learned", path="models/mirror.eqx"))
    assert parse_scenario(scenario_to_json(scenario)) == scenario
    save_scenario(scenario, folder / "track.json")
    assert json.loads((folder / "track.json").read_text())["classifier"] == {"model": "learned", "path": "models/mirror.eqx"}
    monkeypatch.chdir(tmp_path)  # not the scenario's folder: the path must not be read from here
    loaded = load_scenario("scenarios/track.json")
    assert loaded.classifier.path == str(folder / "models" / "mirror.eqx")
    save_scenario(loaded, tmp_path / "copy.json")  # the absolute path is written back
    assert load_scenario(tmp_path / "copy.json") == loaded
    run = hs.run_estimator(loaded, **SETTINGS)
    assert len(run.result.steps) == 2 and "classifier=learned" in run.result.estimator
    weights = run.belief.weights[run.belief.alive]
    assert bool(jnp.all(jnp.isfinite(weights))) and abs(float(weights.sum()) - 1.0) < 1e-12


def test_scenario_path_errors(two_steps, tmp_path):
    obj = scenario_to_json(two_steps)
    for value, message in ((None, "missing"), (3, "expected a string, got number"), ("  ", "empty path")):
        obj["classifier"] = {"model": "learned"} if value is None else {"model": "learned", "path": value}
        with pytest.raises(ScenarioError, match=rf"^classifier\.path: {message}$"):
            parse_scenario(obj)
    obj["classifier"] = {"model": "learned", "path": "nowhere.eqx"}
    (tmp_path / "track.json").write_text(json.dumps(obj))
    scenario = load_scenario(tmp_path / "track.json")
    with pytest.raises(ValueError, match=r"^classifier\.path: learned classifier '.*nowhere\.eqx': cannot read"):
        hs.model_from_scenario(scenario)
    with pytest.raises(ValueError, match=r"classifier 'learned' needs a model file, but the scenario's model is 'mirror'"):
        hs.model_from_scenario(two_steps, "learned")


@pytest.mark.parametrize("num_classes", [1, 3, 4])
def test_learned_residuals_match_the_base_formula(num_classes):
    """Learned.residuals (one network pass, no matrix) holds ClassifierModel's R_c (z - h_c) in its
    first M entries, and its log-density -½‖r‖² + log_norm equals the base formula's, with the same
    derivative in the viewpoint: the extra entry carries log|R_c(θ)| (the step differentiates it)."""
    from hybridslam.models.classifier import ClassifierModel

    model = hs.Learned(num_classes, (5,), key=jax.random.PRNGKey(num_classes))
    # Larger output weights than the initialization's, so the upper entries and scales matter.
    model = eqx.tree_at(lambda m: m.layers[-1].weight, model, 3.0 * model.layers[-1].weight)
    rng = np.random.default_rng(num_classes)

    def density(residuals, z, v):
        r, log_norm = residuals(model, z, v)
        return log_norm - 0.5 * jnp.sum(r**2, axis=-1)

    @eqx.filter_jit  # one compiled program for the three points (op by op: about a hundred tiny compiles)
    def both(model, z, v):
        jac = jax.jacfwd(lambda vv: model.residuals(z, vv)[0][:, :num_classes])(v)
        jac_base = jax.jacfwd(lambda vv: ClassifierModel.residuals(model, z, vv)[0])(v)
        dens = [jax.jacfwd(density, argnums=2)(f, z, v) for f in (type(model).residuals, ClassifierModel.residuals)]
        return (model.residuals(z, v), ClassifierModel.residuals(model, z, v), jac, jac_base,
                density(type(model).residuals, z, v), density(ClassifierModel.residuals, z, v), dens)

    for _ in range(3):
        z = jnp.asarray(rng.uniform(-1, 2, num_classes))
        v = jnp.asarray([np.cos(a := rng.uniform(-np.pi, np.pi)), np.sin(a)])
        got, want, jac, jac_base, dens, dens_base, grads = both(model, z, v)
        assert got[0].shape == (num_classes, num_classes + 1) and model.residual_dim == num_classes + 1
        np.testing.assert_allclose(got[0][:, :num_classes], want[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(dens, dens_base, rtol=1e-12, atol=1e-10)
        np.testing.assert_allclose(grads[0], grads[1], rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(jac, jac_base, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(jax.vmap(lambda c: model.log_likelihood(z, c, v))(jnp.arange(num_classes)),
                                   dens_base, rtol=1e-12, atol=1e-10)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), scale=st.floats(0.1, 10.0), hidden=st.sampled_from([(), (4,), (3, 5)]),
       angle=st.floats(-np.pi, np.pi))
def test_log_det_bound_holds_for_every_viewpoint(seed, scale, hidden, angle):
    """The bound that keeps the normalizer's entry real, √(2 (b_c + 1 − log|R_c(θ)|)) ≥ √2, holds
    for any weights and viewpoint, with or without hidden layers."""
    model = hs.Learned(3, hidden, key=jax.random.PRNGKey(seed))
    model = eqx.tree_at(lambda m: (m.layers[-1].weight, m.layers[-1].bias), model,
                        (scale * model.layers[-1].weight, scale * model.layers[-1].bias))
    v = jnp.asarray([np.cos(angle), np.sin(angle)])
    diag = jnp.diagonal(model.class_sqrt_informations(v), axis1=-2, axis2=-1)
    log_det = jnp.sum(jnp.log(diag), axis=-1)
    assert np.all(np.asarray(model.log_det_bound()) >= np.asarray(log_det) - 1e-12)
    r, _ = model.residuals(jnp.zeros(3), v)
    assert np.all(np.isfinite(r)) and np.all(np.asarray(r[:, -1]) >= np.sqrt(2.0) - 1e-12)
