"""The smoother's data log (``estimators.smoothers.factors.DataLog``): one measurement factor per detection.

The full smoother's graph lists the detections received, not the padded ``(steps, slots)`` grid:
the same graph with fewer rows. Checked here against the padded layout at the level that matters,
the normal equations (``H``, ``g``, cost) of the two graphs at random states; the runs' trajectories
against an independent batch solve are in tests/test_smoother_batch.py. A log sized for fewer
detections than it is given keeps the first ones and counts the rest, which the step's warnings
name.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam.driver import inputs_from_scenario
from hybridslam.estimators.base import StepInfo, _totals, messages
from hybridslam.estimators.smoothers.factors import (Factors, WindowPrior, data_log, factor_budget, graph,
                                                   history_factors, new_overflow, scenario_log, window_factor_budget,
                                                   window_graph)
from hybridslam.inference import smoother as sm

STEPS = 6


@pytest.fixture(scope="module")
def scenario():
    return hs.simulate(3, steps=STEPS)


def _recorded(log, scenario, slots):
    inputs = inputs_from_scenario(scenario, slots)
    logs = [log]
    for k in range(scenario.num_steps):
        det = hs.Detections(inputs.detections.geo[k], inputs.detections.scores[k], inputs.detections.mask[k])
        logs.append(logs[-1].record(jnp.asarray(k), inputs.odometry[k], det))
    return logs


def test_the_budget_is_the_scenario_s_detections_unless_the_shapes_are_shared(scenario):
    total = sum(len(s.detections) for s in scenario.steps)
    assert 0 < total < STEPS * scenario.max_detections  # else the test shows nothing
    assert factor_budget(scenario, None, scenario.max_detections) == total
    assert factor_budget(scenario, STEPS + 4, 3) == (STEPS + 4) * 3
    with pytest.raises(ValueError, match="max_factors"):
        data_log(scenario, STEPS, 2, scenario.num_objects, max_factors=0)


def _grid_factors(history, classes) -> Factors:
    """The reference factors of an association history: every (step, slot) of the grid written out."""
    obj = jnp.maximum(history, 0)
    return Factors(obj[..., None], jnp.where(history >= 0, 0.0, -jnp.inf)[..., None],
                   jnp.full(history.shape, -jnp.inf), jnp.maximum(classes[obj], 0)[..., None])


def test_history_factors_list_the_rows_of_the_grid(scenario):
    rng = np.random.default_rng(2)
    n, slots = scenario.num_objects, scenario.max_detections
    history = jnp.asarray(rng.integers(-1, n, size=(STEPS, slots)))
    classes = jnp.asarray(rng.integers(-1, scenario.num_classes, size=n))  # -1: not realized yet
    cells = jnp.asarray(rng.integers(0, STEPS * slots, size=40))
    lazy, grid = history_factors(history, classes).rows(cells), _grid_factors(history, classes).rows(cells)
    for a, b in zip(lazy, grid):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.any(np.asarray(grid.log_weight) == 0.0) and np.any(np.isinf(np.asarray(grid.log_weight)))


def _grid_graph(log, factors, k, sensor, motion_cov) -> sm.FactorGraph:
    """The reference: one factor per (step, slot) of the padded grid, written out independently."""
    t, dmax = log.mask.shape
    reached = (jnp.arange(t) < k)[:, None] & log.mask
    flat = lambda a: a.reshape((t * dmax,) + a.shape[2:])  # noqa: E731
    w = jnp.linalg.cholesky(jnp.linalg.inv(motion_cov)).T
    return sm.FactorGraph(
        prior_mean=log.prior_mean, prior_sqrt_info=log.prior_sqrt_info, odometry=log.odometry,
        odometry_active=jnp.arange(t) < k, motion_sqrt_info=w,
        meas_pose=jnp.repeat(jnp.arange(1, t + 1), dmax), meas_objects=flat(factors.objects),
        meas_log_weight=jnp.where(flat(reached)[:, None], flat(factors.log_weight), -jnp.inf),
        meas_null_log_weight=jnp.full(t * dmax, -jnp.inf),
        meas_data=sm.DetectionData(flat(log.geo), flat(log.scores), flat(factors.classes)),
        pose_active=jnp.arange(t + 1) <= k, object_active=jnp.ones((log.prior_mean.shape[0] - 3) // 3, bool),
        residual_fn=sm.SensorResidual(sensor), independent_objects=True,
    )


def test_the_compact_graph_has_the_normal_equations_of_the_padded_grid(scenario):
    slots, n = scenario.max_detections, scenario.num_objects
    sensor = hs.model_from_scenario(scenario).sensor
    logs = _recorded(data_log(scenario, STEPS, slots, n, factor_budget(scenario, None, slots)), scenario, slots)
    rng = np.random.default_rng(0)
    history = jnp.asarray(rng.integers(-1, n, size=(STEPS, slots)))
    classes = jnp.asarray(rng.integers(0, scenario.num_classes, size=n))
    factors, grid = history_factors(history, classes), _grid_factors(history, classes)
    poses = jnp.asarray(rng.normal(size=(STEPS + 1, 3)))
    objects = jnp.asarray(rng.normal(size=(n, 3)) * 3.0)

    @eqx.filter_jit  # one compile per layout, not an eager dispatch per operation (20 s of this test)
    def normal_equations(g):
        lin = sm.linearize(g, poses, objects)
        return (*lin.dense(), lin.cost)

    for k in (1, 3, STEPS):
        graphs = [graph(logs[-1], factors, jnp.asarray(k), n, sensor, jnp.eye(3) * 0.01, True),
                  _grid_graph(logs[-1], grid, k, sensor, jnp.eye(3) * 0.01)]
        assert graphs[0].meas_pose.shape[0] < graphs[1].meas_pose.shape[0]
        live = [int(jnp.sum(g.meas_log_weight > -jnp.inf)) for g in graphs]
        assert live[0] == live[1] > 0
        (h0, g0, c0), (h1, g1, c1) = (normal_equations(g) for g in graphs)
        np.testing.assert_allclose(np.asarray(h0), np.asarray(h1), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(g0), np.asarray(g1), rtol=1e-12, atol=1e-12)
        assert float(c0) == pytest.approx(float(c1), rel=1e-12)


def test_a_whole_run_log_lists_every_detection_in_order(scenario):
    log = scenario_log(scenario, scenario.num_objects)
    slots = log.mask.shape[1]
    expected = [k * slots + d for k, s in enumerate(scenario.steps) for d in range(len(s.detections))]
    assert np.asarray(log.rows).tolist() == expected and int(log.count()) == len(expected)


def test_detections_beyond_the_budget_are_counted_and_named(scenario):
    slots, n = scenario.max_detections, scenario.num_objects
    logs = _recorded(data_log(scenario, STEPS, slots, n, max_factors=2), scenario, slots)
    per_step = [int(new_overflow(a, b)) for a, b in zip(logs[:-1], logs[1:])]
    total = sum(len(s.detections) for s in scenario.steps)
    assert sum(per_step) == int(logs[-1].overflow()) == total - 2
    first = [k * slots + d for k, s in enumerate(scenario.steps) for d in range(len(s.detections))][:2]
    assert np.asarray(logs[-1].rows).tolist() == first  # the first two kept, nothing overwritten
    info = StepInfo(k=jnp.asarray(STEPS), num_components=jnp.asarray(1), log_overflow=jnp.asarray(sum(per_step)))
    assert any("factor budget" in line for line in messages(_totals(info), per_step=True))
    assert int(new_overflow(None, logs[-1])) == 0


def test_a_window_lists_its_own_detections_with_the_normal_equations_of_its_padded_slots(scenario):
    """A fixed-lag window's graph takes its detections from the log's rows, as many slots as the
    busiest window of the scenario holds (``window_factor_budget``): the normal equations of the
    padded layout (every slot of the window's steps), also where the window starts before the log
    (``start`` 0) and where it has slid past the first steps."""
    slots, n, length = scenario.max_detections, scenario.num_objects, 2
    sensor = hs.model_from_scenario(scenario).sensor
    counts = [len(s.detections) for s in scenario.steps]
    budget = window_factor_budget(scenario, None, slots, length)
    assert budget == max(sum(counts[i:i + length + 1]) for i in range(STEPS)) < (length + 1) * slots
    assert window_factor_budget(scenario, STEPS + 4, slots, length) == (length + 1) * slots  # shared shapes
    logs = {w: _recorded(data_log(scenario, STEPS, slots, n, factor_budget(scenario, None, slots), w,
                                  length + 1 if w else 0), scenario, slots)[-1] for w in (budget, 0)}
    assert int(logs[budget].overflow()) == int(logs[0].overflow()) == 0  # the scenario's windows fit
    rng = np.random.default_rng(1)
    history = jnp.asarray(rng.integers(-1, n, size=(STEPS, slots)))
    classes = jnp.asarray(rng.integers(0, scenario.num_classes, size=n))
    factors, grid = history_factors(history, classes), _grid_factors(history, classes)
    poses = jnp.asarray(rng.normal(size=(length + 1, 3)))
    objects = jnp.asarray(rng.normal(size=(n, 3)) * 3.0)
    prior = WindowPrior(logs[0].prior_mean, logs[0].prior_info)

    @eqx.filter_jit
    def normal_equations(g):
        lin = sm.linearize(g, poses, objects)
        return (*lin.dense(), lin.cost)

    for k, start in ((2, 0), (4, 2), (STEPS, STEPS - length)):
        graphs = [window_graph(logs[w], factors, jnp.asarray(k), jnp.asarray(start), length, n, sensor,
                               jnp.eye(3) * 0.01, True, "sum", prior) for w in (budget, 0)]
        graphs.append(_window_grid_graph(graphs[1], logs[0], grid, k, start, length))
        assert graphs[0].meas_pose.shape[0] == budget < graphs[1].meas_pose.shape[0]
        live = [int(jnp.sum(g.meas_log_weight > -jnp.inf)) for g in graphs]
        assert live[0] == live[1] == live[2] > 0
        (h0, g0, c0), *rest = (normal_equations(g) for g in graphs)
        for h1, g1, c1 in rest:
            np.testing.assert_allclose(np.asarray(h0), np.asarray(h1), rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(np.asarray(g0), np.asarray(g1), rtol=1e-12, atol=1e-12)
            assert float(c0) == pytest.approx(float(c1), rel=1e-12)


def _window_grid_graph(like, log, factors, k, start, length) -> sm.FactorGraph:
    """The reference window: one factor per (step, slot) of the window's steps, written out
    independently; the rest of the graph as ``like``'s."""
    t, dmax = log.mask.shape
    rows = start - 1 + jnp.arange(length + 1)
    take = lambda a: jnp.take(a, jnp.clip(rows, 0, t - 1), axis=0)  # noqa: E731
    reached = ((rows >= 0) & (rows < k))[:, None] & take(log.mask)
    flat = lambda a: a.reshape(((length + 1) * dmax,) + a.shape[2:])  # noqa: E731
    return eqx.tree_at(
        lambda g: (g.meas_pose, g.meas_objects, g.meas_log_weight, g.meas_null_log_weight, g.meas_data), like,
        (jnp.repeat(jnp.arange(length + 1), dmax), flat(take(factors.objects)),
         jnp.where(flat(reached)[:, None], flat(take(factors.log_weight)), -jnp.inf),
         jnp.full((length + 1) * dmax, -jnp.inf),
         sm.DetectionData(flat(take(log.geo)), flat(take(log.scores)), flat(take(factors.classes)))))


def test_a_window_s_detections_beyond_its_slots_are_counted(scenario):
    """A window sized for fewer detections than the data bring (a state stepped on other data) counts
    each detection that arrives beyond the slots of the window ending at its step."""
    slots, n, length = scenario.max_detections, scenario.num_objects, 2
    logs = _recorded(data_log(scenario, STEPS, slots, n, None, 1, length + 1), scenario, slots)
    counts = [len(s.detections) for s in scenario.steps]
    expected = 0
    for k in range(STEPS):
        held = sum(counts[max(k - length, 0):k + 1])
        expected += min(counts[k], max(held - 1, 0))
    assert int(logs[-1].overflow()) == expected > 0
    assert sum(int(new_overflow(a, b)) for a, b in zip(logs[:-1], logs[1:])) == expected
