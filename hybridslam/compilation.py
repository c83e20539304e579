"""Compiling the driver's programs: ahead-of-time compilation with this project's XLA options, one
executable kept per program, a quick compile for short runs that tiers up when its reuse pays, the
garbage collector paused while tracing, and the probe that puts the options into ``XLA_FLAGS``.

:func:`compiled` is what :func:`hybridslam.driver.run` and the sweeps (:mod:`hybridslam.studies.many`)
call; :func:`clear_compiled` forgets what it kept. The driver re-exports these names.
"""

from __future__ import annotations

import contextlib
import gc
import os
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax

_COMPILED: dict = {}  # one executable per (estimator settings, state structure, shapes): equal runs share it

# XLA's CPU fusion emitters (MLIR-based, the default in jaxlib 0.10) compile this project's programs
# 25-35% slower than XLA's elemental emitters, and the programs run no faster (2026-11-26, 2-core
# CPU, jaxlib 0.10.2: `hybridslam run` on a paper-setup file 12.5-13.6 -> 8.6-9.4 s, the hallway hybrid
# belief's program 11.2-11.7 -> 7.8-8.7 s, `multimodal`'s 15.9-16.7 -> 11.3-12.0 s, every step as
# fast or faster; a 16-track vmapped sweep's batched work ~7% slower, its end to end 4 s faster).
# LLVM's optimization level 1 instead of XLA's default 3 compiles 15-25% faster again and the steps
# run as fast (2026-11-26, alternating runs of scripts/bench_goals.py: paper4 hybrid 9.5, 10.6 -> 8.0,
# 9.1 s, hallway multimodal 14.6, 15.8 -> 12.0, 11.9 s, MRCLAM hybrid 14.1, 14.2 -> 15.6, 10.4 s; step
# times within the machine's noise; level 0 halves XLA's time but doubles the step time).
# A jaxlib that does not know an option compiles with its defaults.
CPU_COMPILER_OPTIONS: dict[str, str | bool | int] = {"xla_cpu_use_fusion_emitters": False,
                                                     "xla_backend_optimization_level": 1}
XLA_DEFAULTS_ENV = "HYBRIDSLAM_XLA_DEFAULTS"  # "1": compile with XLA's own default options


def xla_defaults_from_environment() -> bool:
    """Whether ``$HYBRIDSLAM_XLA_DEFAULTS`` is ``1``; a ``ValueError`` naming it unless unset, 0 or 1."""
    value = os.environ.get(XLA_DEFAULTS_ENV, "").strip()
    if value not in ("", "0", "1"):
        raise ValueError(f"{XLA_DEFAULTS_ENV}={value!r}: expected 0 or 1")
    return value == "1"


def compiler_options(quick: bool = False) -> dict[str, str | bool | int]:
    """The XLA options :func:`compiled` passes: :data:`CPU_COMPILER_OPTIONS` on the CPU backend,
    none on others or when ``$HYBRIDSLAM_XLA_DEFAULTS`` is ``1``. ``quick``: LLVM's optimization
    level 0 (:data:`QUICK_RUN_STEPS`)."""
    if xla_defaults_from_environment() or jax.default_backend() != "cpu":
        return {}
    return dict(CPU_COMPILER_OPTIONS) | ({"xla_backend_optimization_level": 0} if quick else {})


def _as_xla_flags(options: dict[str, str | bool | int]) -> str:
    """``{"xla_a": False, "xla_b": 2}`` as ``XLA_FLAGS`` text: ``--xla_a=false --xla_b=2``."""
    return " ".join(f"--{name}={str(value).lower() if isinstance(value, bool) else value}"
                    for name, value in options.items())


def use_elemental_emitters_everywhere(extra: dict[str, str | bool | int] | None = None) -> bool:
    """Put :data:`CPU_COMPILER_OPTIONS` into ``XLA_FLAGS`` as well: then every compile of this process
    (not only :func:`compiled`'s) and of the processes it starts uses them. Call it before JAX starts
    its backend (XLA reads the flags then); the test suite and ``scripts/make_golden.py`` do. Only if
    this jaxlib knows the options (XLA aborts on an unknown flag: a probe in a subprocess, about a
    second) and ``$HYBRIDSLAM_XLA_DEFAULTS`` is not ``1``. ``extra``: more XLA options for these
    flags only (the test suite's). Returns whether the flags are set."""
    flags, wanted = os.environ.get("XLA_FLAGS", ""), _as_xla_flags(CPU_COMPILER_OPTIONS | (extra or {}))
    if wanted in flags:
        return True
    if xla_defaults_from_environment():
        return False
    env = dict(os.environ, XLA_FLAGS=f"{flags} {wanted}".strip())
    probe = subprocess.run([sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"],
                           env=env, capture_output=True, timeout=300, check=False)
    if probe.returncode == 0:
        os.environ["XLA_FLAGS"] = env["XLA_FLAGS"]
    return probe.returncode == 0


def compile_lowered(lowered: Any, quick: bool = False) -> Any:
    """``lowered.compile()`` (a ``jax`` or ``equinox`` lowered program) with :func:`compiler_options`;
    if this jaxlib rejects an option, with XLA's defaults."""
    options = compiler_options(quick)
    if options:
        try:
            return lowered.compile(compiler_options=options)
        except TypeError:  # a jax whose compile() takes no options
            pass
        except RuntimeError as error:  # XLA's runtime error: only an unknown option falls back
            if "No such compile option" not in str(error):
                raise
    return lowered.compile()


@contextlib.contextmanager
def _collector_paused():
    """Python's cyclic garbage collector off for the block (then on again, if it was).

    Tracing a step allocates a few hundred thousand short-lived objects, and the collector's passes
    over the whole heap (JAX's modules included) cost a fifth of the tracing: the paper program's
    trace and lowering 1.75, 1.95 → 1.42, 1.56 s (2026-11-26; alternating
    processes, ``gc.freeze`` in between bought half of that). The garbage the block leaves is
    reference cycles of the tracer, collected at the collector's next pass after it.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


# A short run compiles with LLVM's optimization level 0: XLA's part of the compile takes about half
# as long and the steps twice as long, which a run of a few steps does not feel (a 10-step
# paper-setup file, `hybridslam run`, 2026-11-27, alternating: compile 4.63, 4.89 -> 3.61, 3.71 s;
# steps 4.1, 3.8 -> 7.2, 7.7 ms; results equal to 1e-14). A program that short runs reuse is compiled
# again at the default level once the step time they spent at level 0 passes TIER_UP times its
# compile (rent or buy: at most about twice the better choice made in advance).
QUICK_RUN_STEPS = 20
TIER_UP = 2.5
_QUICK: dict[int, list[float]] = {}  # id of a level-0 executable in _COMPILED -> [compile s, step s run]


def compiled(fn: Callable, *args, steps: int | None = None) -> tuple[Callable, float]:
    """``eqx.filter_jit(fn)`` compiled ahead of time for these arguments' structure and shapes, and
    the seconds spent compiling (0 when an equal program was compiled before in this process).

    ``steps``: how many times the caller will run it (:func:`run`: the scenario's steps). At most
    :data:`QUICK_RUN_STEPS` compiles it quickly (LLVM level 0, slower code), until the time spent
    running that code (:func:`spent`) says that compiling it fully pays.
    """
    quick = steps is not None and steps <= QUICK_RUN_STEPS
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    key: tuple | None = (fn, treedef, tuple((x.shape, x.dtype, getattr(x, "sharding", None)) for x in leaves),
                         static)
    try:
        hash(key)
    except TypeError:  # an unhashable static part: compile every time, correctly
        key = None
    if key is not None and key in _COMPILED:
        tally = _QUICK.get(id(_COMPILED[key]))
        if tally is None or (quick and tally[1] < TIER_UP * tally[0]):
            return _COMPILED[key], 0.0
        del _QUICK[id(_COMPILED[key])]
        quick = False  # level 0 has cost more than a full compile would: compile it fully
    t0 = time.perf_counter()
    with _collector_paused():
        executable = compile_lowered(eqx.filter_jit(fn).lower(*args), quick)  # type: ignore[attr-defined]
    seconds = time.perf_counter() - t0
    if key is not None:
        _COMPILED[key] = executable
        if quick:
            _QUICK[id(executable)] = [seconds, 0.0]
    return executable, seconds


def spent(executable: Callable, seconds: float) -> None:
    """Count ``seconds`` of running ``executable`` (from :func:`compiled`) toward compiling it fully."""
    tally = _QUICK.get(id(executable))
    if tally is not None:
        tally[1] += seconds


def clear_compiled() -> None:
    """Forget every executable :func:`compiled` kept, and JAX's own caches.

    Each executable holds its machine code in memory maps; a process that compiles many programs
    (a benchmark over every estimator, smoother and workload: about 40) reaches the kernel's map
    limit (``vm.max_map_count``, 65530 by default) and XLA then fails with "LLVM compilation error:
    Cannot allocate memory". Call this between programs that will not run again.
    """
    _COMPILED.clear()
    _QUICK.clear()
    jax.clear_caches()
