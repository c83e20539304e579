"""The installed version of hybridslam: pyproject.toml's, read through the package metadata (the one
version source; CITATION.cff agrees, tests/test_environment.py)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

try:
    __version__ = _version("hybridslam")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
