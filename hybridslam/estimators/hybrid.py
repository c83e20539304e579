"""The hybrid belief (Tchuiev et al. 2019, Algorithm 1) under the estimator registry.

Its step, state and runner live in :mod:`hybridslam.step`, :mod:`hybridslam.belief` and
:func:`hybridslam.run.run_scenario`; :func:`hybridslam.estimators.run_estimator` delegates there.
"""

NAME = "hybrid"
