"""The domain types and the generative model.

* :mod:`.scenario`: what every layer reads, a scenario (prior map and robot, noise, classifier
  model, the steps' odometry and detections, optional ground truth) and its steps stacked into
  fixed-shape arrays; the file format that holds it is :mod:`hybridslam.io.scenario`;
* the model: SE(2) poses, odometry, range-bearing geometry, the classifier models (Eq. 2, Eq. 18,
  the thesis's confusion matrix, a learned one) and the measurement factor (Eq. 10).

Nothing here knows about scenario or result files, beliefs or estimators; the model is pure
functions of poses and parameters, written for one pose or one detection (batch with ``jax.vmap``).
"""
