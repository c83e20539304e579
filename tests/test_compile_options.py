"""The XLA options of the driver's compiles (``compilation.compiler_options``, ``compilation.compile_lowered``)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hybridslam import compilation


def _f(x):
    return jnp.sin(x) * jnp.exp(-x) + jnp.cumsum(x)


def test_the_cpu_gets_the_elemental_emitters_unless_the_environment_asks_for_xla_defaults(monkeypatch):
    monkeypatch.delenv(compilation.XLA_DEFAULTS_ENV, raising=False)
    on_cpu = jax.default_backend() == "cpu"  # other backends get XLA's defaults
    wanted = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}
    assert compilation.compiler_options() == (wanted if on_cpu else {})
    monkeypatch.setenv(compilation.XLA_DEFAULTS_ENV, "1")
    assert compilation.compiler_options() == {}
    monkeypatch.setenv(compilation.XLA_DEFAULTS_ENV, "0")
    assert compilation.compiler_options() == (compilation.CPU_COMPILER_OPTIONS if on_cpu else {})
    monkeypatch.setenv(compilation.XLA_DEFAULTS_ENV, "yes")
    with pytest.raises(ValueError, match=compilation.XLA_DEFAULTS_ENV):
        compilation.compiler_options()


def test_compiled_programs_compute_the_same_with_and_without_the_options(monkeypatch):
    monkeypatch.delenv(compilation.XLA_DEFAULTS_ENV, raising=False)
    x = jnp.linspace(0.0, 3.0, 17)
    ours = compilation.compile_lowered(eqx.filter_jit(_f).lower(x))
    default = jax.jit(_f).lower(x).compile()
    np.testing.assert_allclose(np.asarray(ours(x)), np.asarray(default(x)), rtol=1e-14)


def test_an_option_this_jaxlib_does_not_know_falls_back_to_the_defaults(monkeypatch):
    monkeypatch.delenv(compilation.XLA_DEFAULTS_ENV, raising=False)
    monkeypatch.setattr(compilation, "CPU_COMPILER_OPTIONS", {"xla_cpu_no_such_option_anywhere": False})
    x = jnp.arange(5.0)
    out = compilation.compile_lowered(jax.jit(_f).lower(x))(x)
    np.testing.assert_allclose(np.asarray(out), np.asarray(_f(x)), rtol=1e-14)


def test_the_options_as_xla_flags():
    assert (compilation._as_xla_flags(compilation.CPU_COMPILER_OPTIONS)
            == "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=1")
    assert compilation._as_xla_flags({"xla_a": True, "xla_b": 2}) == "--xla_a=true --xla_b=2"


def test_the_garbage_collector_pauses_only_while_compiling(monkeypatch):
    """``compilation.compiled`` traces with the cyclic collector off and leaves it as it found it, also
    when tracing raises."""
    import gc

    seen = []

    def traced(x):
        seen.append(gc.isenabled())
        return _f(x)

    def broken(x):
        raise RuntimeError("no trace")

    was = gc.isenabled()
    try:
        for enabled in (True, False):
            gc.enable() if enabled else gc.disable()
            compilation.compiled(traced, jnp.arange(3.0 + enabled))  # a new shape each time: traced again
            with pytest.raises(RuntimeError, match="no trace"):
                compilation.compiled(broken, jnp.arange(2.0))
            assert gc.isenabled() == enabled
        assert seen == [False, False]
    finally:
        gc.enable() if was else gc.disable()


def _g(x):
    return jnp.cos(x) * jnp.cumsum(x)


def test_a_short_run_compiles_quickly_and_a_program_its_reuses_pay_for_is_compiled_fully(monkeypatch):
    """Level 0 for a run of at most QUICK_RUN_STEPS steps; the same program again at the default
    level once its level-0 steps cost TIER_UP times its compile, or for a longer run."""
    monkeypatch.delenv(compilation.XLA_DEFAULTS_ENV, raising=False)
    on_cpu = jax.default_backend() == "cpu"
    assert compilation.compiler_options(quick=True) == ({**compilation.CPU_COMPILER_OPTIONS,
                                                     "xla_backend_optimization_level": 0} if on_cpu else {})
    x = jnp.linspace(0.0, 1.0, 7)
    quick, seconds = compilation.compiled(_g, x, steps=compilation.QUICK_RUN_STEPS)
    assert seconds > 0 and compilation._QUICK[id(quick)] == [seconds, 0.0]
    np.testing.assert_allclose(np.asarray(quick(x)), np.asarray(_g(x)), rtol=1e-14)
    compilation.spent(quick, 0.4 * compilation.TIER_UP * seconds)
    assert compilation.compiled(_g, x, steps=3) == (quick, 0.0)  # not yet paid for
    compilation.spent(quick, 0.6 * compilation.TIER_UP * seconds)
    full, again = compilation.compiled(_g, x, steps=3)
    assert full is not quick and again > 0 and id(full) not in compilation._QUICK
    assert compilation.compiled(_g, x, steps=3) == (full, 0.0)
    y = jnp.linspace(0.0, 1.0, 9)  # another shape: another program, compiled fully for a long run
    long, _ = compilation.compiled(_g, y, steps=compilation.QUICK_RUN_STEPS + 1)
    assert id(long) not in compilation._QUICK
    compilation.spent(long, 1e9)  # counts only for level-0 programs
    assert compilation.compiled(_g, y) == (long, 0.0)
    z = jnp.linspace(0.0, 1.0, 11)
    short, _ = compilation.compiled(_g, z, steps=1)
    assert id(short) in compilation._QUICK and compilation.compiled(_g, z)[0] is not short  # steps unknown: fully
