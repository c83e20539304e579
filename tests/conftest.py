"""Shared fixtures. hybridslam runs in float64 (``hs.setup()`` below, which also sizes XLA's CPU
thread pool: ``hybridslam.config``); tests share a few small shapes
so that each compiled step is reused across tests (JAX compiles dominate the suite's time).

Several settings make the compiles cheaper, for this process and for the CLI subprocesses it starts
(through the environment):

* XLA's optimizations are off (``jax_disable_most_optimizations``): the programs under test are
  tiny, so compiling them costs far more than running them; the suite's CPU time drops by ~20%.
* XLA's elemental emitters and LLVM level 1 on the CPU (``compilation.CPU_COMPILER_OPTIONS`` in ``XLA_FLAGS``):
  the library passes the same option to its own compiles (``hybridslam.driver.compile_lowered``);
  in the flags it also reaches the tests' own ``jax.jit`` compiles and the CLI subprocesses, and
  the quick suite takes about half the time (``driver.use_elemental_emitters_everywhere``: only
  if this jaxlib knows the flag, and not with ``HYBRIDSLAM_XLA_DEFAULTS=1``).
* The driver's own compiles at XLA's optimization level 0 as well (``HYBRIDSLAM_XLA_DEFAULTS=1``, set
  after the flags above: the driver then passes no options of its own, and its compiles take the
  flags and ``jax_disable_most_optimizations`` like every other). The driver compiles a study's
  batch and a run of more than ``QUICK_RUN_STEPS`` steps at level 1 for users, whose runs are long;
  the tests' runs are tiny (the sweep, batching and export tests 174 -> 144 CPU s, 2026-11-28).
  ``tests/test_compile_options.py`` unsets it to check the options the driver passes.
* LLVM's code generation in one piece per program (``TEST_XLA_OPTIONS``): split for the cores, as
  XLA does by default, it costs 6-12% more CPU (hybrid, multimodal and ml programs, 2026-11-28), and
  the suite's two workers already keep both cores busy.
* One persistent compilation cache per test run, shared by the xdist workers and the
  subprocesses: a program that several of them compile (the CLI's step, the sweep's batched scan)
  is compiled once. It lives under the run's base temporary folder, so every run starts cold and
  CI times stay honest.
"""

from __future__ import annotations

import os

import jax
import jaxtyping
import pytest
from jax.experimental.compilation_cache import compilation_cache

import hybridslam as hs
from hybridslam.driver import XLA_DEFAULTS_ENV, use_elemental_emitters_everywhere

# XLA's code generation in one thread per program, not split over the cores (the module docstring).
TEST_XLA_OPTIONS = {"xla_cpu_parallel_codegen_split_count": 1}

hs.setup()  # float64 and the thread settings, before any JAX backend starts (hybridslam.config)
os.environ["JAX_ENABLE_X64"] = "1"  # and float64 in the Python subprocesses the tests start
use_elemental_emitters_everywhere(TEST_XLA_OPTIONS)  # before any JAX backend starts (module docstring)
os.environ[XLA_DEFAULTS_ENV] = "1"  # after the line above: the driver's compiles too at level 0 (module docstring)
jax.config.update("jax_numpy_rank_promotion", "raise")
os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
jax.config.update("jax_disable_most_optimizations", True)


@pytest.fixture(scope="session", autouse=True)
def shared_compilation_cache(tmp_path_factory) -> str:
    """The run's persistent compilation cache folder (see the module docstring)."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # shared by all workers of this run
    path = str(root / "jax-cache")
    os.makedirs(path, exist_ok=True)
    settings = {"jax_compilation_cache_dir": path, "jax_persistent_cache_min_compile_time_secs": 0}
    for name, value in settings.items():
        jax.config.update(name, value)
        os.environ[name.upper()] = str(value)
    compilation_cache.reset_cache()  # a compile at collection time may have settled on "no cache"
    return path

@pytest.fixture
def unchecked_types():
    """The runtime type checker off for one test (it is on for the whole suite: pyproject's
    ``--jaxtyping-packages``). For tests of the package's own input validation: users run without
    the checker and see the package's error naming the field, which the checker would pre-empt."""
    jaxtyping.config.update("jaxtyping_disable", True)
    yield
    jaxtyping.config.update("jaxtyping_disable", False)


# One small shape for most step-level tests: capacity 8, 2 detection slots, 200 samples.
CAPACITY, SAMPLES, SLOTS = 8, 200, 2


@pytest.fixture(scope="session")
def scenario() -> hs.Scenario:
    """A 6-step paper-setup track (seed chosen to include 2-detection and empty steps)."""
    return hs.simulate(0, steps=6)


@pytest.fixture
def key() -> jax.Array:
    return jax.random.PRNGKey(0)


# The test files that take longest, longest first (their CPU seconds in one run, 2026-11-28): test_gradients
# about 210 s, the readme files 150 and 90 s (with their subprocesses), test_planning (with its docs page)
# and test_sweep about 120 s, the others 100 s and less. The two workers take whole files in collection
# order (pyproject's `--dist loadfile --no-loadscope-reorder`): starting the long ones first lets the
# short ones fill the gaps, so both workers finish together (longest-processing-time-first
# scheduling). A file not listed runs after these, in name order; the order changes nothing but the
# run's length.
LONGEST_FIRST: tuple[str, ...] = (
    "test_gradients.py", "test_readme_run.py", "test_planning.py", "test_sweep.py", "test_readme_python.py",
    "test_step.py", "test_multimodal.py", "test_novelty.py", "test_discovery.py", "test_golden.py",
    "test_hard_inputs.py", "test_smoother.py", "test_online_loop_closure.py", "test_smoother_batch.py",
    "test_batch_strategies.py", "test_cli.py", "test_learned.py", "test_clutter_default.py", "test_lag.py",
    "test_mrclam.py", "test_laplace.py", "test_profiles.py", "test_environment.py", "test_consistency.py",
    "test_loop_closure.py", "test_weights.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file's tests keep their order
