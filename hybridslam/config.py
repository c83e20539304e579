"""The process-wide settings hybridslam needs, set only when asked (:func:`setup`); importing the
package changes nothing outside it.

* **float64** (``jax_enable_x64``): the paper's variances span 1e-4 to 1e2, and the estimators'
  Cholesky factors and log-weights lose the small ones in float32. Every estimator checks it when it
  is built (:func:`require_x64`) and refuses to run in float32.
* **XLA's CPU thread pool** (``PJRT_NPROC``): jaxlib 0.10.2's CPU LAPACK kernels (Cholesky,
  triangular solve, QR, ...) split a batched call over XLA's intra-op thread pool and block a pool
  thread until the pieces finish. Two such calls that XLA runs concurrently on a pool as small as the
  machine (2 threads on a 2-core CPU) can wait for each other forever: the multimodal estimator on
  the 12-step hallway file of ``tests/data/golden`` hung every time on a 2-core machine (jaxlib
  0.11 compiles that path out). The estimator's later batching no longer shows it: on 2026-11-27
  (commit d39eb23) that file ran to its end with XLA's default 2-thread pool, with XLA's default
  options and with the test suite's (158 s each, 2-core CPU). A larger pool rules the cycle out and
  changes no number (the golden result files of ``tests/data/golden``). XLA reads the size when its
  CPU backend starts: the first array or compile of the process.
* **OpenBLAS's threads** (``OPENBLAS_NUM_THREADS=1``): those kernels call scipy's OpenBLAS, whose
  worker threads busy-wait for work and, beside XLA's pool, oversubscribe the cores (on a 2-core
  CPU an ``ml`` hallway smoother step took 35-40 ms with one OpenBLAS thread and 40-58 ms with the
  default, 4.4 s instead of 37 ms while another process ran). Our matrices (a few hundred rows at
  most) gain nothing from threaded BLAS. Read when scipy's OpenBLAS loads (the first LAPACK call).

The ``hybridslam`` command sets all three in its ``main``; the test suite in ``tests/conftest.py``.
"""

from __future__ import annotations

import os
import warnings

import jax

X64_HELP = ("hybridslam computes in float64: call hybridslam.setup() (or jax.config.update('jax_enable_x64', "
            "True)) before creating arrays, or set JAX_ENABLE_X64=1")


def thread_pool_size() -> int:
    """The XLA CPU thread pool :func:`setup` asks for: ``max(32, 4 × cores)`` (module docstring)."""
    return max(32, 4 * (os.cpu_count() or 1))


def setup(*, threads: bool = True) -> None:
    """Turn on float64 (``jax_enable_x64``) and, with ``threads``, size XLA's CPU thread pool and
    OpenBLAS's threads for this process (module docstring). Call it once, before the first JAX array
    or compile of the process (after that, XLA's pool is fixed: a warning says so). A user's own
    ``PJRT_NPROC`` and ``OPENBLAS_NUM_THREADS`` win.

    Without it, an estimator refuses to run in float32 (:func:`require_x64`), and on a CPU with few
    cores and jaxlib 0.10.2, batched LAPACK calls can deadlock in XLA's thread pool (module
    docstring): in a Python program, call it first::

        import hybridslam as hs
        hs.setup()
    """
    if threads:
        if _backend_started() and "PJRT_NPROC" not in os.environ:
            warnings.warn("hybridslam.setup(): JAX's backend has started, so XLA's CPU thread pool keeps its size "
                          "(on a CPU with few cores, jaxlib 0.10.2's LAPACK kernels can then deadlock); call "
                          "setup() before the first array or compile", RuntimeWarning, stacklevel=2)
        os.environ.setdefault("PJRT_NPROC", str(thread_pool_size()))
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    jax.config.update("jax_enable_x64", True)


def x64_enabled() -> bool:
    return bool(jax.config.read("jax_enable_x64"))


def require_x64(what: str) -> None:
    """Raise :class:`RuntimeError` saying how to turn float64 on, unless it is on (``what``: who needs it)."""
    if not x64_enabled():
        raise RuntimeError(f"{what}: {X64_HELP}")


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # another jax: no way to tell
        return False
