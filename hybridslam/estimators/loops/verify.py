"""How the loop-closure pass (:mod:`.closure`) verifies a merge set: the run's whole graph
(geometric only: prior, odometry and range-bearing factors of every associated detection) re-solved
with the merges applied (:class:`Solver`, Levenberg-Marquardt, warm-started), its cost allowed to
rise by at most the chi-square ``verify_probability`` quantile of the merged constraints
(:func:`judge`), and the set re-scored with negative information (:func:`misses`, the
log-likelihood of the (step, object) pairs in view yet undetected, :mod:`.misses`): the
merged graph's against the reference's.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ...inference import smoother as sm
from ...models.scenario import Scenario
from ...models.model import model_from_scenario
from ..smoothers import factors as smoother_factors
from ...inference.gating import chi2_gate
from .misses import in_view_probability, miss_log_likelihood, point_in_view, uses_marginal
from .settings import LoopClosureSettings, MergeScore


@eqx.filter_jit
def solve_graph(log: smoother_factors.DataLog, model, history, poses, objects, num_created, max_steps: int,
                max_range, fov, marginal: bool):
    """Solve the whole graph of ``history``: the solution, the marginal of ``[x_T, objects]`` and,
    where ``marginal``, each (pose, object) pair's :func:`~.misses.in_view_probability`, else
    ``None`` (one compile per shape)."""
    t = log.mask.shape[0]
    g = smoother_factors.graph(log, smoother_factors.history_factors(history), jnp.asarray(t), num_created, model.sensor,
                              model.motion_cov, semantic=False)
    sol = sm.solve(g, poses, objects, max_steps=max_steps)
    mean, cov = sm.marginal(sol, t)
    in_view = in_view_probability(sol, max_range, fov) if marginal else None
    return sol.poses, sol.objects, sol.cost, mean, cov, sol.result == optx.RESULTS.successful, in_view


class Solver:
    """:func:`solve_graph` for one run of ``scenario`` (its data ``log``; the history is an argument:
    merges do not recompile). A call returns ``poses, objects, cost, mean, cov, converged, in_view``
    (``in_view`` ``None`` unless ``marginal``: :func:`~.misses.uses_marginal`)."""

    def __init__(self, scenario: Scenario, log: smoother_factors.DataLog, max_steps: int, marginal: bool):
        self._model = model_from_scenario(scenario.replace(discovery=None))
        self._log, self._max_steps, self._marginal = log, max_steps, marginal
        self._footprint = (jnp.asarray(scenario.max_range, float), jnp.asarray(scenario.fov, float))

    def __call__(self, history, poses, objects, num_created):
        out = jax.device_get(solve_graph(self._log, self._model, jnp.asarray(history), jnp.asarray(poses),
                                         jnp.asarray(objects), jnp.asarray(num_created), self._max_steps,
                                         *self._footprint, self._marginal))
        in_view = None if out[6] is None else np.asarray(out[6])
        return tuple(np.asarray(x) for x in out[:5]) + (bool(out[5]), in_view)


def judge(log_bayes_factor: float, cost_rise: float, converged: bool, negative_information: float, merged: int,
          settings: LoopClosureSettings) -> MergeScore:
    """A merge set's :class:`MergeScore` from its parts: verified when its re-solve converged and
    ``2 · cost_rise`` lies within the chi-square ``verify_probability`` quantile of its ``2 · merged``
    constraints (2 at least); ``negative_information``: :func:`misses` of the merged graph less the
    reference's."""
    verified = converged and 2.0 * cost_rise <= chi2_quantile(max(2 * merged, 2), settings.verify_probability)
    return MergeScore(log_bayes_factor, float(negative_information), cost_rise, bool(verified))


def chi2_quantile(dof: int, probability: float) -> float:
    """The chi-square ``probability`` quantile with ``dof`` degrees of freedom (Wilson-Hilferty; exact for 2)."""
    if dof == 2:
        return chi2_gate(probability)
    z = NormalDist().inv_cdf(probability)
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3


def misses(scenario: Scenario, poses: np.ndarray, objects: np.ndarray, in_view: np.ndarray | None,
           history: np.ndarray, num: int, settings: LoopClosureSettings) -> float:
    """The log-likelihood of the (step, object) pairs of a solved graph that were in view yet
    undetected (:func:`~.misses.miss_log_likelihood`), ``P(in view)`` as ``settings.misses``
    says: ``in_view`` (the solve's :func:`~.misses.in_view_probability`; ``None`` where
    :func:`~.misses.uses_marginal` is false) for ``"marginal"``,
    the solved ``poses (≥ T+1, 3)`` and ``objects (N, 3)`` with ``fov_margin`` for ``"point"`` (and
    for the pairs whose marginal probability is not finite)."""
    settings = settings.for_scenario(scenario)  # the file's detection probability where none is set
    if not settings.detection_probability:
        return 0.0
    t = history.shape[0]
    marginal = None
    if uses_marginal(settings):
        if in_view is None:
            raise ValueError("misses: the marginal test needs the solve's in_view probabilities")
        marginal = np.asarray(in_view, float)[: t + 1, :num]
        if np.all(np.isfinite(marginal)):
            return miss_log_likelihood(marginal, history, num, settings)
    # the point test, or where the solved covariance was not finite (a singular H) for those pairs
    point = point_in_view(scenario, poses[: t + 1], objects[:num], settings.fov_margin)
    if marginal is not None:
        point = np.where(np.isfinite(marginal), marginal, point)
    return miss_log_likelihood(point, history, num, settings)
