import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridslam.models import se2

angle = st.floats(-3.1, 3.1)
coord = st.floats(-20, 20)
pose = st.tuples(coord, coord, angle).map(lambda p: jnp.array(p))
settings.register_profile("hybridslam", deadline=None, max_examples=30, database=None)
settings.load_profile("hybridslam")


@given(st.floats(-50, 50))
def test_wrap_range_and_equivalence(a):
    w = float(se2.wrap(jnp.asarray(a)))
    assert -np.pi < w <= np.pi
    assert np.isclose(np.cos(w), np.cos(a)) and np.isclose(np.sin(w), np.sin(a))


def test_wrap_pi_is_pi():
    assert float(se2.wrap(jnp.asarray(-np.pi))) == np.pi


@given(pose, pose)
def test_between_inverts_compose(a, b):
    expected = jnp.concatenate([b[:2], se2.wrap(b[2:])])
    np.testing.assert_allclose(se2.between(a, se2.compose(a, b)), expected, atol=1e-9)


@given(pose)
def test_exp_log_round_trip(p):
    np.testing.assert_allclose(se2.exp(se2.log(p)), p, atol=1e-9)


@given(pose)
def test_compose_inverse_is_identity(p):
    np.testing.assert_allclose(se2.compose(p, se2.inverse(p)), jnp.zeros(3), atol=1e-9)


def test_log_gradient_finite_at_zero():
    g = jax.jacfwd(se2.log)(jnp.zeros(3))
    np.testing.assert_allclose(g, jnp.eye(3), atol=1e-12)
