"""How the loop-closure pass (:mod:`.loop_closure`) verifies a merge set: the run's whole graph
(geometric only: prior, odometry and range-bearing factors of every associated detection) re-solved
with the merges applied (:class:`Solver`, Levenberg-Marquardt, warm-started), its cost allowed to
rise by at most the chi-square ``verify_probability`` quantile of the merged constraints
(:func:`judge`), and the set re-scored with negative information (:func:`misses`,
:func:`negative_information`): each (step, object) pair whose solved object lies inside the
footprint of the solved pose (by ``fov_margin``) with no detection associated to it, more or fewer
than before the merge, adds ``log(1 − detection_probability)`` or takes it away (the sensor model's
detection of every object in the footprint).
"""

from __future__ import annotations

import math
from statistics import NormalDist

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..inference import smoother as sm
from ..io.scenario import Scenario
from ..models.model import model_from_scenario
from . import smoothing_graph
from .gaussian import chi2_gate
from .loop_settings import DEFAULT_DETECTION_PROBABILITY, LoopClosureSettings, MergeScore


@eqx.filter_jit
def solve_graph(log: smoothing_graph.DataLog, model, history, poses, objects, num_created, max_steps: int):
    """Solve the whole graph of ``history`` and take the marginal of ``[x_T, objects]`` (one compile per shape)."""
    t = log.mask.shape[0]
    g = smoothing_graph.graph(log, smoothing_graph.history_factors(history), jnp.asarray(t), num_created, model.sensor,
                              model.motion_cov, semantic=False)
    sol = sm.solve(g, poses, objects, max_steps=max_steps)
    mean, cov = sm.marginal(sol, t)
    return sol.poses, sol.objects, sol.cost, mean, cov, sol.result == optx.RESULTS.successful


class Solver:
    """:func:`solve_graph` for one run of ``scenario`` (its data ``log``; the history is an argument:
    merges do not recompile)."""

    def __init__(self, scenario: Scenario, log: smoothing_graph.DataLog, max_steps: int):
        self._model = model_from_scenario(scenario.replace(discovery=None))
        self._log, self._max_steps = log, max_steps

    def __call__(self, history, poses, objects, num_created):
        out = jax.device_get(solve_graph(self._log, self._model, jnp.asarray(history), jnp.asarray(poses),
                                         jnp.asarray(objects), jnp.asarray(num_created), self._max_steps))
        return tuple(np.asarray(x) for x in out[:5]) + (bool(out[5]),)


def negative_information(extra_misses: int, settings: LoopClosureSettings) -> float:
    """The log-likelihood of ``extra_misses`` more (step, object) pairs in view yet undetected
    (fewer: negative), ``log(max(1 − detection_probability, min_miss_probability))`` each (module
    docstring; ``detection_probability`` ``None`` counts as :data:`DEFAULT_DETECTION_PROBABILITY`)."""
    p = DEFAULT_DETECTION_PROBABILITY if settings.detection_probability is None else settings.detection_probability
    if not p:
        return 0.0
    return extra_misses * math.log(max(1.0 - p, settings.min_miss_probability))


def judge(log_bayes_factor: float, cost_rise: float, converged: bool, extra_misses: int, merged: int,
          settings: LoopClosureSettings) -> MergeScore:
    """A merge set's :class:`MergeScore` from its parts: verified when its re-solve converged and
    ``2 · cost_rise`` lies within the chi-square ``verify_probability`` quantile of its ``2 · merged``
    constraints (2 at least), and :func:`negative_information` of its extra misses."""
    verified = converged and 2.0 * cost_rise <= chi2_quantile(max(2 * merged, 2), settings.verify_probability)
    return MergeScore(log_bayes_factor, negative_information(extra_misses, settings), cost_rise, bool(verified))


def chi2_quantile(dof: int, probability: float) -> float:
    """The chi-square ``probability`` quantile with ``dof`` degrees of freedom (Wilson-Hilferty; exact for 2)."""
    if dof == 2:
        return chi2_gate(probability)
    z = NormalDist().inv_cdf(probability)
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3


def misses(scenario: Scenario, poses: np.ndarray, objects: np.ndarray, history: np.ndarray, num: int,
            settings: LoopClosureSettings) -> int:
    """Negative information: (step, object) pairs where the solved object lies inside the sensor's
    footprint from the solved pose, by ``fov_margin`` (m, rad) at least, yet no detection of that step
    was associated with it."""
    t = history.shape[0]
    d = objects[None, :num, :2] - poses[1: t + 1, None, :2]  # (T, N, 2)
    rng = np.hypot(d[..., 0], d[..., 1])
    bearing = np.angle(np.exp(1j * (np.arctan2(d[..., 1], d[..., 0]) - poses[1: t + 1, None, 2])))
    inside = (rng < scenario.max_range - settings.fov_margin[0]) & (np.abs(bearing) < scenario.fov / 2 - settings.fov_margin[1])
    seen = np.zeros((t, num), bool)
    rows, cols = np.nonzero(history >= 0)
    seen[rows, history[rows, cols]] = True
    return int(np.sum(inside & ~seen))
