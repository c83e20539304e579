"""JAX's persistent compilation cache for the ``hybridslam`` command, on by default.

A run compiles its step once (seconds to tens of seconds on a CPU); the second run of a scenario of
the same shapes and settings reads the executable from disk instead. The cache lives in
``$HYBRIDSLAM_CACHE_DIR`` (default ``~/.cache/hybridslam/jax``, or under ``$XDG_CACHE_HOME``);
``HYBRIDSLAM_NO_CACHE=1`` turns it off. A cache JAX was already given (``JAX_COMPILATION_CACHE_DIR``
or ``jax.config``) is left as it is.
"""

from __future__ import annotations

import os

import jax
from jax.experimental.compilation_cache import compilation_cache


def enable() -> str | None:
    """Turn the persistent cache on (see the module docstring); the folder, or ``None`` when off."""
    if os.environ.get("HYBRIDSLAM_NO_CACHE", "").strip() not in ("", "0"):
        return None
    given = os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]
    if given:
        return given
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    path = os.environ.get("HYBRIDSLAM_CACHE_DIR") or os.path.join(base, "hybridslam", "jax")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None  # an unwritable home: compile every time rather than fail
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    compilation_cache.reset_cache()  # a compile before this point may have settled on "no cache"
    return path
