"""The object heading's curvature in the smoother's linearization (``inference.smoother.linearize``).

Range and bearing do not observe an object's heading; a viewpoint-dependent classifier's semantic
factor does, through a residual far from linear in it, and there Gauss-Newton's ``JᵀJ`` alone can
be far below the cost's curvature (KITTI 0006 with a learned model: 0.75 against 50.6 nats/rad²).
The linearization adds the second-order term ``Σ r_i ∂²r_i/∂θ_o²`` where it is positive, so the
heading's diagonal entry is ``max(cost curvature, JᵀJ)``: checked here against finite differences
of the cost, on one detection factor, for a learned model and the paper's closed-form one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridslam as hs
from hybridslam.inference import smoother as sm
from hybridslam.models import geometry
from hybridslam.models.classifier import Mirror
from hybridslam.models.learned import Learned

H = 1e-4  # rad: the finite-difference step of the cost's curvature (float64: error ~1e-8 relative)


def _graph(classifier, rng, semantic=True) -> sm.FactorGraph:
    """Two poses, one object, one detection factor of ``classifier``'s class 0 from the second pose."""
    m = classifier.num_classes
    sensor = hs.SensorModel(jnp.diag(jnp.array([0.05, 0.002])), classifier, jnp.asarray(30.0), jnp.asarray(1.6))
    geo = jnp.asarray([[rng.uniform(3.0, 15.0), rng.uniform(-0.6, 0.6)]])
    scores = jnp.asarray(rng.dirichlet(np.ones(m), size=1))
    n0 = 6
    prior = np.diag([1e2, 1e2, 1e2, 1.0, 1.0, 1e-2])  # the object's heading nearly free, as a new one's
    if semantic:
        residual, data = sm.SensorResidual(sensor), sm.DetectionData(geo, scores, jnp.zeros((1, 1), int))
    else:
        w, _ = sensor.geometric_sqrt_information()
        residual, data = sm.RangeBearingResidual(w), geo
    return sm.FactorGraph(
        prior_mean=jnp.zeros(n0), prior_sqrt_info=jnp.asarray(np.sqrt(prior)),
        odometry=jnp.asarray([[1.0, 0.0, 0.1]]), odometry_active=jnp.ones(1, bool),
        motion_sqrt_info=jnp.eye(3) * 10.0,
        meas_pose=jnp.asarray([1]), meas_objects=jnp.zeros((1, 1), int), meas_log_weight=jnp.zeros((1, 1)),
        meas_null_log_weight=jnp.full(1, -jnp.inf), meas_data=data,
        pose_active=jnp.ones(2, bool), object_active=jnp.ones(1, bool), residual_fn=residual, mode="sum",
    )


@jax.jit
def _heading_entries(graph, poses, objects):
    """The linearization's heading entry of ``H``, the same with ``JᵀJ`` alone, and the cost at
    ``θ_o ± H`` and ``θ_o``."""
    lin = sm.linearize(graph, poses, objects)
    data = jax.tree.map(lambda a: a[0], graph.meas_data)
    r_of = lambda t: graph.residual_fn(poses[1], objects[0].at[2].set(t), data, jnp.asarray(0))[0]  # noqa: E731
    j_theta = jax.jacfwd(r_of)(objects[0, 2])
    gauss_newton = jnp.sum(j_theta**2) + 1e-2  # the factor's JᵀJ and the prior's heading information
    cost = lambda t: sm.linearize(graph, poses, objects.at[0, 2].set(t)).cost  # noqa: E731
    t = objects[0, 2]
    return lin.object[2, 2], gauss_newton, cost(t - H), cost(t), cost(t + H)


def _start(rng, graph):
    """Poses at the odometry's chain, the object where the detection puts it, any heading."""
    poses = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1]])
    geo = graph.meas_data.geo if isinstance(graph.meas_data, sm.DetectionData) else graph.meas_data
    r, b = (float(v) for v in geo[0])
    p = np.array([1.0, 0.0]) + r * np.array([np.cos(0.1 + b), np.sin(0.1 + b)])
    return poses, jnp.asarray([[p[0], p[1], rng.uniform(-np.pi, np.pi)]])


CLASSIFIERS = {"learned": lambda: Learned(3, hidden=(8,), key=jax.random.PRNGKey(7)), "mirror": lambda: Mirror(0.6, 15.0)}


@pytest.mark.parametrize("name", sorted(CLASSIFIERS))
@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_the_heading_entry_is_the_cost_curvature_where_that_exceeds_gauss_newton(name, seed):
    rng = np.random.default_rng(seed)
    graph = _graph(CLASSIFIERS[name](), rng)
    poses, objects = _start(rng, graph)
    entry, gauss_newton, c_minus, c0, c_plus = (float(v) for v in _heading_entries(graph, poses, objects))
    curvature = (c_plus + c_minus - 2.0 * c0) / H**2
    expected = max(curvature, gauss_newton)
    assert entry == pytest.approx(expected, rel=1e-4, abs=1e-4 * max(1.0, abs(curvature)))


def test_geometry_alone_is_gauss_newton_unchanged():
    # Range and bearing do not see the heading: its entry is the prior's information alone.
    rng = np.random.default_rng(0)
    graph = _graph(CLASSIFIERS["learned"](), rng, semantic=False)
    assert not graph.residual_fn.heading_curvature and graph.residual_fn.__class__.heading_curvature is False
    poses, objects = _start(rng, graph)
    lin = sm.linearize(graph, poses, objects)
    assert float(lin.object[2, 2]) == pytest.approx(1e-2, rel=1e-12)


def test_a_viewpoint_free_classifier_adds_no_term():
    sensor = hs.SensorModel(jnp.eye(2), hs.make_classifier("independent", 2, 0.5, 10.0), jnp.asarray(9.0),
                            jnp.asarray(1.0))
    assert not sm.SensorResidual(sensor).heading_curvature
    assert sm.SensorResidual(hs.SensorModel(jnp.eye(2), Mirror(0.5, 10.0), jnp.asarray(9.0),
                                            jnp.asarray(1.0))).heading_curvature


@jax.jit
def _cost_and_exact(graph, poses, objects, t):
    """The smoother's cost and gradient in the object's heading ``t``, and the model's own negative
    log-density of the same factors (Eq. 2 via ``log_likelihood``, the heading prior's ½ 10⁻² t²;
    the geometric factor and the poses' priors do not depend on ``t``)."""
    objs = objects.at[0, 2].set(t)
    lin = sm.linearize(graph, poses, objs)
    classifier = graph.residual_fn.sensor.classifier
    scores = graph.meas_data.scores[0]
    exact = lambda tt: (0.5 * 1e-2 * tt**2  # noqa: E731
                        - classifier.log_likelihood(scores, 0, geometry.viewpoint(poses[1], objs[0].at[2].set(tt))))
    return lin.cost, lin.grad_object[2], exact(t), jax.grad(exact)(t)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), t1=st.floats(-3.1, 3.1), t2=st.floats(-3.1, 3.1))  # the prior wraps at ±π
def test_the_smoothers_cost_is_the_learned_models_whole_negative_log_likelihood(seed, t1, t2):
    """A learned model's covariance depends on the viewpoint, so its normalizer ``log|R_c(θ)|`` does
    too: the smoother's cost (and its gradient in the object's heading) must change with the heading
    as the model's negative log-density does, normalizer included (Eq. 2), not as ``½‖r‖²`` alone."""
    rng = np.random.default_rng(seed)
    graph = _graph(CLASSIFIERS["learned"](), rng)
    poses, objects = _start(rng, graph)
    c1, g1, e1, d1 = (float(v) for v in _cost_and_exact(graph, poses, objects, t1))
    c2, g2, e2, d2 = (float(v) for v in _cost_and_exact(graph, poses, objects, t2))
    assert c1 - c2 == pytest.approx(e1 - e2, rel=1e-9, abs=1e-9)
    # the linearization's gradient is Jᵀr, the cost's: d cost / d θ_o
    assert g1 == pytest.approx(d1, rel=1e-8, abs=1e-9) and g2 == pytest.approx(d2, rel=1e-8, abs=1e-9)
