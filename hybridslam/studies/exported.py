"""A study's batched program kept on disk as traced, lowered code, so that a second study of the same
shapes skips tracing.

JAX's persistent compilation cache (:mod:`hybridslam.cli.cache`) keeps the *executable*, keyed by
the lowered module: a process must still trace and lower the whole step (Python, seconds to tens of
seconds for the hybrid belief's batched scan) before it can look the executable up. This module
keeps the lowered module itself (``jax.export``: StableHLO bytecode and its signature, pickled) beside the cache, keyed by
what fixes the program: the function, the arguments' tree structure, shapes, dtypes and shardings,
their static (non-array) parts, the versions of jax, jaxlib and equinox and the source of this
package. A study that finds its key deserializes the module and compiles a thin wrapper around it
(``Exported.call``), whose executable the persistent cache holds from the first study: no trace.

The first study pays for one export (the same trace and lowering it paid before) and compiles the
same wrapper, so both studies ask the persistent cache for one and the same executable.

Anything unusual falls back to :func:`hybridslam.driver.compiled` (no cache folder, several
processes, a static part without a stable ``repr``, a program ``jax.export`` refuses, an unreadable
or stale file): the cache changes when a program is traced, never what it computes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import os
import pathlib
import pickle
import re
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax

from ..driver import _collector_paused, compile_lowered, compiled

FOLDER = "hybridslam-exported"  # under the persistent cache's folder
_ADDRESS = re.compile(r" at 0x[0-9a-f]+")  # a repr that names an object's address is not stable
_SOURCE: list[str] = []
_PROGRAMS: dict[str, Callable] = {}  # this process's programs by key: a study's later batches reuse them


def _source_digest() -> str:
    """A digest of this package's Python source: a changed step is a different program."""
    if not _SOURCE:
        digest = hashlib.sha256()
        root = pathlib.Path(__file__).resolve().parents[1]
        for path in sorted(root.rglob("*.py")):
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())
        _SOURCE.append(digest.hexdigest())
    return _SOURCE[0]


def _versions() -> str:
    return ",".join(f"{name}={importlib.metadata.version(name)}" for name in ("jax", "jaxlib", "equinox"))


def cache_key(fn: Callable, args: tuple) -> str | None:
    """The file name of ``fn`` applied to ``args`` (see the module docstring), or ``None`` when a part of
    the program has no stable description."""
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    parts = [f"{fn.__module__}.{fn.__qualname__}", str(treedef), repr(static),
             repr([(x.shape, str(x.dtype), str(getattr(x, "sharding", None))) for x in leaves]),
             _versions(), _source_digest()]
    if any(_ADDRESS.search(p) for p in parts):
        return None
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]


class ExportedProgram:
    """A compiled wrapper of a deserialized program, called like the function it was exported from."""

    def __init__(self, executable: Any, out_skeleton: Any):
        self.compiled = executable  # jax's Compiled: memory_analysis() (hybridslam.studies.batch.batch_bytes)
        self._out = jax.tree_util.tree_structure(out_skeleton)

    def __call__(self, *args):
        leaves = jax.tree_util.tree_leaves(eqx.filter(args, eqx.is_array))
        return jax.tree_util.tree_unflatten(self._out, self.compiled(*leaves))


def _serialize(exported: Any) -> dict:
    """The fields of a ``jax.export.Exported`` as picklable values: its own ``serialize()`` needs the
    ``flatbuffers`` package, which is no dependency of hybridslam. The VJP rule (a closure) is left
    out: a study never differentiates its batch."""
    return {f.name: getattr(exported, f.name) for f in dataclasses.fields(exported) if f.name != "_get_vjp"}


def _deserialize(fields: dict) -> Any:
    return jax.export.Exported(**fields, _get_vjp=None)  # type: ignore[arg-type]


def _compile(exported: Any, leaves: list, out_skeleton: Any, quick: bool) -> ExportedProgram:
    lowered = jax.jit(exported.call).lower(*leaves)
    return ExportedProgram(compile_lowered(lowered, quick), out_skeleton)


def compiled_exported(fn: Callable, *args, folder: str | None = None) -> tuple[Callable, float]:
    """:func:`hybridslam.driver.compiled` (fully optimized), tracing ``fn`` only when no earlier process
    exported the same program into ``folder`` (default: under JAX's persistent cache folder; none:
    no export). Returns the callable and the seconds spent getting it."""
    base = folder or jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]
    if not base or jax.process_count() > 1:
        return compiled(fn, *args)
    key = cache_key(fn, args)
    if key is None:
        return compiled(fn, *args)
    if key in _PROGRAMS:
        return _PROGRAMS[key], 0.0
    program, seconds = _load_or_export(fn, args, os.path.join(base, FOLDER, key))
    _PROGRAMS[key] = program
    return program, seconds


def clear() -> None:
    """Forget this process's programs (as :func:`hybridslam.driver.clear_compiled` does its own)."""
    _PROGRAMS.clear()


def _load_or_export(fn: Callable, args: tuple, path: str) -> tuple[Callable, float]:
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves = jax.tree_util.tree_leaves(dynamic)
    t0 = time.perf_counter()
    try:
        with open(path, "rb") as source:
            blob, out_skeleton = pickle.load(source)
        exported = _deserialize(blob)
    except (OSError, EOFError, pickle.UnpicklingError, ValueError, TypeError, AttributeError):
        exported = None  # no file yet, or one this version cannot read: export it again
    if exported is not None:
        try:
            return _compile(exported, leaves, out_skeleton, quick=False), time.perf_counter() - t0
        except Exception:  # noqa: BLE001 - a stale export must never stop a study: trace it instead
            exported = None
    treedef = jax.tree_util.tree_structure(dynamic)
    out_tree: list = []  # the output's structure, seen while tracing (no second trace for it)

    def flat(*xs):
        out = fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, list(xs)), static))
        out_tree.append(jax.tree_util.tree_structure(out))
        return jax.tree_util.tree_leaves(out)

    try:
        with _collector_paused():
            shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None)) for x in leaves]
            exported = jax.export.export(jax.jit(flat))(*shapes)
        out_skeleton = jax.tree_util.tree_unflatten(out_tree[-1], range(out_tree[-1].num_leaves))
        blob = _serialize(exported)
        exported = _deserialize(pickle.loads(pickle.dumps(blob)))  # what a later process compiles: the same executable
        program = _compile(exported, leaves, out_skeleton, quick=False)
    except Exception:  # noqa: BLE001 - jax.export refused the program (e.g. a host callback): no export
        return compiled(fn, *args)
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "wb") as sink:
            pickle.dump((blob, out_skeleton), sink)
        os.replace(tmp, path)  # atomic: a concurrent study reads a whole file or none
    except (OSError, pickle.PicklingError, TypeError, AttributeError):
        pass  # an unwritable cache or an unpicklable structure: the next study traces again
    return program, time.perf_counter() - t0
