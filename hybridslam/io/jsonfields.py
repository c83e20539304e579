"""Reading and checking JSON fields, for the file formats of :mod:`.scenario` and :mod:`.result`.

Every check raises :class:`ScenarioError` whose message is one line, ``<field path>: <what is
wrong>`` (e.g. ``steps[3].detections[1].scores: expected 2 numbers, got 3``). Pure numpy and the
standard library.
"""

from __future__ import annotations

import itertools
import json
import math
import numbers
import os
from collections.abc import Callable
from typing import Any, NoReturn

import numpy as np

SYM_TOL = 1e-9  # relative to the largest absolute entry
PROB_TOL = 1e-6


class ScenarioError(ValueError):
    """Malformed scenario/result file. str(e) is one line: '<field path>: <what is wrong>'."""

    def __init__(self, path: str, message: str):
        super().__init__(path, message)
        self.path = path
        self.message = message

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


def fail(path: str, message: str) -> NoReturn:
    raise ScenarioError(path, message)


def kind(obj: Any) -> str:
    """The JSON name of a value's type, for messages."""
    if obj is None:
        return "null"
    if isinstance(obj, (bool, np.bool_)):
        return "boolean"
    if isinstance(obj, numbers.Number):
        return "number"
    if isinstance(obj, str):
        return "string"
    if isinstance(obj, (list, tuple, np.ndarray)):
        return "list"
    return "object" if isinstance(obj, dict) else type(obj).__name__


def join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def get(obj: dict, key: str, path: str, parse: Callable[..., Any], *args: Any) -> Any:
    """Parse the required key `key` of the object at `path`."""
    if key not in obj:
        fail(join(path, key), "missing")
    return parse(obj[key], join(path, key), *args)


def maybe(obj: dict, key: str, path: str, parse: Callable[..., Any], *args: Any) -> Any:
    """Parse an optional key; absent or null gives None."""
    value = obj.get(key)
    return None if value is None else parse(value, join(path, key), *args)


def as_object(obj: Any, path: str) -> dict:
    if not isinstance(obj, dict):
        fail(path, f"expected an object, got {kind(obj)}")
    return obj


def as_list(obj: Any, path: str) -> list:
    if isinstance(obj, np.ndarray):
        obj = obj.tolist()
    if not isinstance(obj, (list, tuple)):
        fail(path, f"expected a list, got {kind(obj)}")
    return list(obj)


def string(obj: Any, path: str) -> str:
    if not isinstance(obj, str):
        fail(path, f"expected a string, got {kind(obj)}")
    return obj


def number(obj: Any, path: str) -> float:
    if type(obj) is float and math.isfinite(obj):
        return obj  # the common case, without the abstract base classes' checks
    if isinstance(obj, (bool, np.bool_)) or not isinstance(obj, numbers.Real):
        fail(path, f"expected a number, got {kind(obj)}")
    try:
        value = float(obj)
    except OverflowError:
        value = math.inf
    if not math.isfinite(value):
        fail(path, "not a finite number")
    return value


def positive(obj: Any, path: str) -> float:
    value = number(obj, path)
    if value <= 0:
        fail(path, f"expected a positive number, got {value!r}")
    return value


def integer(obj: Any, path: str, lo: int | None = None, hi: int | None = None) -> int:
    """An integer in [lo, hi) (either bound may be None). A whole float (``2.0``) counts: the format's
    numbers are plain JSON numbers, and a writer may print an integer with a decimal point."""
    if type(obj) is int and (lo is None or obj >= lo) and (hi is None or obj < hi):
        return obj  # the common case, without the abstract base classes' checks
    whole = isinstance(obj, float) and math.isfinite(obj) and obj.is_integer()
    if isinstance(obj, (bool, np.bool_)) or not (isinstance(obj, numbers.Integral) or whole):
        got = repr(obj) if isinstance(obj, float) else kind(obj)
        fail(path, f"expected an integer, got {got}")
    value = int(obj)
    if (lo is not None and value < lo) or (hi is not None and value >= hi):
        want = f">= {lo}" if hi is None else f"in [{lo}, {hi})"
        fail(path, f"expected an integer {want}, got {value}")
    return value


def integers(obj: Any, path: str, lo: int | None = None) -> list[int]:
    if type(obj) is list and all(type(x) is int for x in obj) and (lo is None or not obj or min(obj) >= lo):
        return list(obj)  # the common case, without a path string per entry
    return [integer(x, f"{path}[{i}]", lo) for i, x in enumerate(as_list(obj, path))]


def integer_lists(obj: Any, path: str, lo: int | None = None) -> list[list[int]]:
    """A list of lists of integers >= ``lo`` (a component's associations)."""
    items = as_list(obj, path)
    if all(type(a) is list for a in items):
        flat = list(itertools.chain.from_iterable(items))
        if set(map(type, flat)) <= {int} and (lo is None or not flat or min(flat) >= lo):
            return [list(a) for a in items]  # copies: the record must not share the caller's lists
    return [integers(a, f"{path}[{j}]", lo) for j, a in enumerate(items)]


def vector(obj: Any, path: str, n: int | None = None) -> np.ndarray:
    items = as_list(obj, path)
    if n is not None and len(items) != n:
        fail(path, f"expected {n} numbers, got {len(items)}")
    if set(map(type, items)) <= {float, int}:  # no bool, no string: the common case, checked at once
        try:
            out = np.array(items, dtype=np.float64)
        except OverflowError:  # an integer beyond float64: the loop below names it
            out = np.full(1, np.inf)
        if np.all(np.isfinite(out)):
            return out
    return np.array([number(x, f"{path}[{i}]") for i, x in enumerate(items)], dtype=np.float64)


def matrix(obj: Any, path: str, rows: int | None, cols: int) -> np.ndarray:
    """A list of rows; `rows=None` accepts any number of rows."""
    if (type(obj) is list and obj and (rows is None or len(obj) == rows)
            and all(type(r) is list and len(r) == cols for r in obj)
            and set(itertools.chain.from_iterable(map(map, [type] * len(obj), obj))) <= {float, int}):
        try:  # the common case (a result file's covariances), checked at once
            out = np.array(obj, dtype=np.float64)
        except OverflowError:  # an integer beyond float64: the rows below name it
            out = np.full(1, np.inf)
        if np.all(np.isfinite(out)):
            return out
    items = as_list(obj, path)
    lens = {len(as_list(r, f"{path}[{i}]")) for i, r in enumerate(items)}
    if rows is not None and len(lens) <= 1 and (len(items) != rows or lens - {cols}):
        fail(path, f"expected a {rows}x{cols} matrix, got {len(items)}x{min(lens, default=0)}")
    data = [vector(r, f"{path}[{i}]", cols) for i, r in enumerate(items)]
    return np.array(data, dtype=np.float64).reshape(len(items), cols)


def symmetric(obj: Any, path: str, n: int) -> np.ndarray:
    m = matrix(obj, path, n, n)
    if np.abs(m - m.T).max(initial=0.0) > SYM_TOL * np.abs(m).max(initial=0.0):
        fail(path, "not symmetric")
    return m


def spd(obj: Any, path: str, n: int) -> np.ndarray:
    m = symmetric(obj, path, n)
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        fail(path, "not positive definite")
    return m


def distributions(m: np.ndarray, path: str, axis: int) -> np.ndarray:
    """Check each row (axis=1) or column (axis=0) of m is a probability vector."""
    for i, j in np.argwhere(m < 0)[:1]:
        fail(f"{path}[{i}][{j}]", f"negative probability {float(m[i, j])!r}")
    for i, total in enumerate(m.sum(axis=axis)):
        if abs(total - 1.0) > PROB_TOL:
            if axis == 1:
                fail(f"{path}[{i}]", f"sums to {total:.9g}, expected 1")
            fail(path, f"column {i} sums to {total:.9g}, expected 1")
    return m


def floats(a: Any) -> Any:
    return np.asarray(a, dtype=np.float64).tolist()


def dumps(obj: Any, indent: int = 0, width: int = 100) -> str:
    """JSON text, readable and linear in its length: a value whose one-line text fits in ``width``
    (indent included) stays on one line; a longer object has one key per line (its values laid out
    by the same rule), a longer list of objects or lists one item per line, each item on one line
    (a scenario's steps, a matrix's rows, a result step's components)."""
    text = json.dumps(obj, allow_nan=False)
    if len(text) + indent <= width:
        return text
    inner = " " * (indent + 1)
    if isinstance(obj, dict) and obj:
        # a key that is not a string is written as json.dumps writes it: {1: 2} -> {"1": 2}
        items = [f"{json.dumps(k if isinstance(k, str) else json.dumps(k))}: {dumps(v, indent + 1, width)}"
                 for k, v in obj.items()]
    elif isinstance(obj, list) and any(isinstance(x, (dict, list)) for x in obj):
        items = [json.dumps(x, allow_nan=False) for x in obj]
    else:
        return text
    opening, closing = ("{", "}") if isinstance(obj, dict) else ("[", "]")
    return opening + "\n" + ",\n".join(inner + x for x in items) + "\n" + " " * indent + closing


def write_json(obj: Any, path: str | os.PathLike) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(dumps(obj) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except OSError as e:
        fail("<file>", f"cannot read {os.fspath(path)!r}: {e.strerror or e}")
    except json.JSONDecodeError as e:
        fail("<file>", f"{os.fspath(path)!r} is not valid JSON: {e}")
    except UnicodeDecodeError as e:
        fail("<file>", f"{os.fspath(path)!r} is not UTF-8 text: {e.reason}")


def check_format(obj: dict, expected: str) -> None:
    fmt = get(obj, "format", "", string)
    if fmt != expected:
        fail("format", f"expected {expected!r}, got {fmt!r}")

