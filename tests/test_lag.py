"""Fixed-lag smoothing (``smoother=Lag(L)``, ``--smoother lag:L``).

A window of ``L`` steps is re-solved at every step; its oldest pose is marginalized when it slides
(``inference.smoother.marginalize_first``, exact for linear factors: tests/test_smoother.py). The
window's behaviour with ``ml`` (as long as the run: the full smoother; short: frozen past poses,
close to the full smoother) is tested in tests/test_smoother_batch.py, next to the full smoother's
compiled step. Here: the mixtures run with a window; bad values are one-line errors.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam import cli
from hybridslam.estimators.smoothers import parse_smoother
from hybridslam.estimators.smoothers.kinds import FINAL_ATOL, Full, Lag, step_tolerance
from hybridslam.estimators.smoothers.factors import data_log

STEPS = 6


@pytest.fixture(scope="module")
def scenario():
    return hs.simulate(0, steps=STEPS)


# The window is the subject, not the weights: the hybrid belief's deterministic linearized weights
# compile in less time than laplace-is.
@pytest.mark.slow  # a mixture's smoother compile each: the extended suite, CI
@pytest.mark.parametrize("name, options", [("hybrid", {"capacity": 4, "weights": "linearized"}),
                                           ("multimodal", {"capacity": 4})])
def test_the_mixtures_run_with_a_window(name, options, scenario):
    run = hs.run_estimator(scenario, name, smoother=Lag(2), **options)
    assert "smoother=lag:2" in run.result.estimator
    assert np.all(np.isfinite(run.result.trajectory))
    assert all(int(i.solver_failures) == 0 for i in run.infos)
    truth = scenario.true_robot_poses
    assert np.max(np.linalg.norm(run.result.trajectory[:, :2] - truth[:, :2], axis=1)) < 1.0
    # The window prior carries only its information Λ (handed on by the marginalization): symmetric
    # and positive semidefinite in every live component.
    info = np.asarray(run.state.smoothing.window.info)[np.isfinite(np.asarray(run.state.log_weights))]
    np.testing.assert_allclose(info, np.swapaxes(info, -1, -2), atol=1e-9 * np.abs(info).max())
    assert np.min(np.linalg.eigvalsh(info)) > -1e-9 * np.abs(info).max()


def test_parse_smoother():
    assert parse_smoother("lag:3") == Lag(3) and parse_smoother("full") == Full()
    assert Lag(3).name == "lag:3"
    for bad in ("lag:0", "lag:", "lag:x", "lag3", "lag:-1"):
        with pytest.raises(ValueError, match="lag:L"):
            parse_smoother(bad)
    with pytest.raises(ValueError, match="Lag.length"):
        Lag(0)
    for bad in (-1e-4, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="step_atol"):
            Full(step_atol=bad)
        with pytest.raises(ValueError, match="step_atol"):
            Lag(3, step_atol=bad)


def test_every_step_but_the_last_is_solved_to_the_step_tolerance(scenario):
    """``Full.step_atol`` before the scenario's last step; the last (and any after it) to ``FINAL_ATOL``,
    also in a log padded to more rows than the scenario's steps."""
    log = data_log(scenario, STEPS + 4, 2, scenario.num_objects)
    for settings in (Full(), Lag(3), Full(step_atol=1e-6)):
        got = [float(step_tolerance(settings, log, jnp.asarray(k))) for k in range(1, STEPS + 3)]
        assert got == [settings.step_atol] * (STEPS - 1) + [FINAL_ATOL] * 3
    assert FINAL_ATOL < Full().step_atol


def test_a_bad_window_is_a_one_line_cli_error(tmp_path, capsys):
    assert cli.main(["run", str(tmp_path / "s.json"), "-o", str(tmp_path / "r.json"), "--smoother", "lag:0"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    assert "--smoother" in err and "lag:L" in err and "Traceback" not in err


@pytest.mark.parametrize("smoother", [Lag(50), parse_smoother("incremental:50")])
def test_a_window_longer_than_the_run_smooths_as_the_full_smoother(smoother, scenario):
    # lag:50 on a 6-step file: the window holds every pose (it once asked for 51 of the 7 rows).
    assert Lag(50).span(STEPS) == STEPS and Lag(2).span(STEPS) == 2
    window = hs.run_estimator(scenario, "ml", smoother=smoother).result.trajectory
    full = hs.run_estimator(scenario, "ml", smoother=Full()).result.trajectory
    np.testing.assert_allclose(window, full, atol=1e-6)
