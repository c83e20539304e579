"""Importing hybridslam changes no process-wide setting; :func:`hybridslam.setup` sets them
(``hybridslam/config.py``, ``docs/installation.md``): float64, and thread defaults that a user's own
values override. An estimator refuses to run in float32. One version source."""

from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys
import tomllib

import pytest

import hybridslam as hs

ROOT = pathlib.Path(__file__).resolve().parent.parent
SETTINGS = ("PJRT_NPROC", "OPENBLAS_NUM_THREADS", "JAX_ENABLE_X64")
SHOW = ("import os, jax, hybridslam as hs; {call}"
        "print(os.environ.get('PJRT_NPROC'), os.environ.get('OPENBLAS_NUM_THREADS'), jax.config.jax_enable_x64)")


def _python(code: str, **env) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k not in SETTINGS}
    return subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True,
                          timeout=120, check=False)


def test_import_sets_nothing_and_an_estimator_refuses_float32_and_says_how_to_turn_float64_on():
    """One process (each start imports the package again): the settings after the import, then an
    estimator built without float64."""
    out = _python(SHOW.format(call="") + "; hs.make_estimator('ml')")
    assert out.stdout.split() == ["None", "None", "False"], out.stderr
    assert out.returncode != 0
    assert "ML(): hybridslam computes in float64" in out.stderr and "hybridslam.setup()" in out.stderr, out.stderr


@pytest.mark.parametrize("env, want", [
    ({}, [str(max(32, 4 * (os.cpu_count() or 1))), "1", "True"]),  # one OpenBLAS thread; a pool that cannot deadlock
    ({"PJRT_NPROC": "7", "OPENBLAS_NUM_THREADS": "3"}, ["7", "3", "True"]),  # the user's own win
])
def test_setup_sets_float64_and_thread_defaults_and_keeps_the_users(env, want):
    out = _python(SHOW.format(call="hs.setup(); "), **env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == want


def test_jaxs_own_float64_switch_is_enough_to_build_an_estimator():
    """No thread settings needed to build one."""
    ok = _python("import hybridslam as hs; hs.make_estimator('max-mixture'); print('built')", JAX_ENABLE_X64="1")
    assert ok.stdout.strip() == "built", ok.stderr


def test_the_command_line_runs_in_float64_without_any_setting(tmp_path):
    """The ``hybridslam`` command's ``main`` calls :func:`hybridslam.setup` itself."""
    out = _python("import sys; from hybridslam.cli import main; "
                  f"sys.exit(main(['simulate', '--steps', '2', '-o', {str(tmp_path / 's.json')!r}]))")
    assert out.returncode == 0, out.stderr


def test_one_version_source():
    """``hybridslam.__version__`` is the installed metadata's (pyproject.toml's); CITATION.cff agrees."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    cited = re.search(r"^version:\s*(\S+)\s*$", (ROOT / "CITATION.cff").read_text(encoding="utf-8"), re.M)
    assert cited is not None
    assert hs.__version__ == project == cited.group(1).strip("'\"")
