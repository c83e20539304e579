"""The generative model: SE(2) poses, odometry, range-bearing geometry, the classifier models
(Eq. 2, Eq. 18, the thesis's confusion matrix, a learned one) and the measurement factor (Eq. 10).

Nothing here knows about beliefs or estimators; everything is a pure function of poses and
parameters, written for one pose or one detection (batch with ``jax.vmap``).
"""
