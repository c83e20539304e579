"""What importing hybridslam sets in the environment before JAX starts (``hybridslam/__init__.py``,
``docs/installation.md``): defaults that a user's own values override."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SHOW = "import hybridslam, os; print(os.environ['PJRT_NPROC'], os.environ['OPENBLAS_NUM_THREADS'])"


def _imported_with(**env) -> list[str]:
    base = {k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "OPENBLAS_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", SHOW], env={**base, **env}, capture_output=True, text=True, check=True)
    return out.stdout.split()


@pytest.mark.parametrize("env, want", [
    ({}, [str(max(32, 4 * (os.cpu_count() or 1))), "1"]),  # one OpenBLAS thread; a pool that cannot deadlock
    ({"PJRT_NPROC": "7", "OPENBLAS_NUM_THREADS": "3"}, ["7", "3"]),  # the user's own win
])
def test_import_sets_thread_defaults_and_keeps_the_users(env, want):
    assert _imported_with(**env) == want
