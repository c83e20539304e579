"""How a rerun golden result file is compared with its committed one (``tests/test_golden.py``,
``scripts/make_golden.py --check``).

Non-float fields (associations, classes, counts) must be equal; floats equal to ``RTOL`` relative
(``ATOL`` absolute near zero). XLA's machine code for exp, log and the reductions differs between
CPUs (AVX2 against AVX-512, Intel against AMD), which moves the last bits of every number: on
2026-11-26 the same commit rerun on an AMD EPYC with AVX-512 differed from the files by up to
5e-14 absolute, 1e-11 relative. A step's components are matched as a set, not by position: two
components of exactly equal weight (a symmetric tie) may come out in either order.
"""

from __future__ import annotations

from typing import Any

RTOL, ATOL = 1e-9, 1e-12


def differences(got: Any, want: Any, path: str = "") -> list[str]:
    """Where ``got`` and ``want`` (JSON values) differ beyond the tolerances; ``[]``: the same."""
    if isinstance(want, dict) and isinstance(got, dict):
        if set(got) != set(want):
            return [f"{path}: keys {sorted(got)} != {sorted(want)}"]
        if "components" in want and isinstance(want["components"], list):
            out = _component_differences(got["components"], want["components"], f"{path}.components")
            rest = {k: v for k, v in want.items() if k != "components"}
            return out + [d for k, v in rest.items() for d in differences(got[k], v, f"{path}.{k}")]
        return [d for k, v in want.items() for d in differences(got[k], v, f"{path}.{k}")]
    if isinstance(want, list) and isinstance(got, list):
        if len(got) != len(want):
            return [f"{path}: length {len(got)} != {len(want)}"]
        return [d for i, (a, b) in enumerate(zip(got, want)) for d in differences(a, b, f"{path}[{i}]")]
    if isinstance(want, float) or isinstance(got, float):
        numbers = isinstance(got, (int, float)) and isinstance(want, (int, float))
        if numbers and abs(got - want) <= ATOL + RTOL * abs(want):
            return []
        return [f"{path}: {got!r} != {want!r}"]
    return [] if got == want else [f"{path}: {got!r} != {want!r}"]


def _component_differences(got: list, want: list, path: str) -> list[str]:
    """Each wanted component matched with an equal one among ``got`` (any order)."""
    if len(got) != len(want):
        return [f"{path}: {len(got)} components != {len(want)}"]
    free = list(range(len(got)))
    for i, component in enumerate(want):
        match = next((j for j in free if not differences(got[j], component)), None)
        if match is None:
            same_place = differences(got[i], component, f"{path}[{i}]")
            return same_place or [f"{path}[{i}]: matched twice"]
        free.remove(match)
    return []
