"""Shared fixtures. hybridslam runs in float64 (enabled on import); tests share a few small shapes
so that each compiled step is reused across tests (JAX compiles dominate the suite's time)."""

from __future__ import annotations

import jax
import pytest

import hybridslam as hs

jax.config.update("jax_numpy_rank_promotion", "raise")

# One small shape for most step-level tests: capacity 8, 2 detection slots, 200 samples.
CAPACITY, SAMPLES, SLOTS = 8, 200, 2


@pytest.fixture(scope="session")
def scenario() -> hs.Scenario:
    """A 6-step paper-setup track (seed chosen to include 2-detection and empty steps)."""
    return hs.simulate(0, steps=6)


@pytest.fixture
def key() -> jax.Array:
    return jax.random.PRNGKey(0)
