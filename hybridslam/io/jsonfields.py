"""Reading and checking JSON fields, for the file formats of :mod:`.scenario` and :mod:`.result`.

Every check raises :class:`ScenarioError` whose message is one line, ``<field path>: <what is
wrong>`` (e.g. ``steps[3].detections[1].scores: expected 2 numbers, got 3``). Pure numpy and the
standard library.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import numbers
import os
import shutil
import tempfile
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


def equal(a: Any, b: Any) -> bool:
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(
            equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.shape(a) == np.shape(b) and bool(np.array_equal(a, b))
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(map(equal, a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)
    return bool(a == b)


def dataclass_eq(self: Any, other: Any) -> bool:
    return equal(self, other) if type(other) is type(self) else NotImplemented


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
    """JSON text; objects and lists of lists/objects are spread over lines when long (one item per
    line, one more space of indent per level), everything else on one line.

    Linear in the text: each value is encoded once (a result file of a 1700-step log holds about
    25 million association lists, and encoding every subtree again at each level took minutes).
    """
    if isinstance(obj, dict):
        return _object_text([(_key(k), dumps(v, indent + 1, width)) for k, v in obj.items()], indent, width)
    if not (isinstance(obj, list) and any(isinstance(x, (dict, list)) for x in obj)):
        return json.dumps(obj, allow_nan=False)
    if all(type(x) is list for x in obj):
        text = json.dumps(obj, allow_nan=False)
        if len(text) + indent <= width:
            return text
        if '"' not in text and "{" not in text and text.count("[") == len(obj) + 1:
            # A list of flat lists of numbers (associations, matrices): one item per line, cut
            # from the one-line text, whose "], [" then only separates items.
            inner = " " * (indent + 1)
            cut = text[2:-2].replace("], [", "],\n" + inner + "[")
            return "[\n" + inner + "[" + cut + "]\n" + " " * indent + "]"
    return _list_text([dumps(x, indent + 1, width) for x in obj], indent, width)


def _object_text(parts: list[tuple[str, str]], indent: int, width: int) -> str:
    """An object's text from its keys' and values' texts (values already at ``indent + 1``)."""
    if not parts:
        return "{}"
    if not any("\n" in v for _, v in parts):
        text = "{" + ", ".join(f"{k}: {v}" for k, v in parts) + "}"
        if len(text) + indent <= width:
            return text
    inner = " " * (indent + 1)
    return "{\n" + ",\n".join(f"{inner}{k}: {v}" for k, v in parts) + "\n" + " " * indent + "}"


def _list_text(items: list[str], indent: int, width: int) -> str:
    """A list's text from its items' texts (at ``indent + 1``): one line if short, else one item per line."""
    if not any("\n" in x for x in items):
        text = "[" + ", ".join(items) + "]"
        if len(text) + indent <= width:
            return text
    return "[\n" + ",\n".join(" " * (indent + 1) + x for x in items) + "\n" + " " * indent + "]"


def _key(k: Any) -> str:
    """An object key as JSON text: a string, or the JSON text of any other key as a string (as
    ``json.dumps`` writes ``{1: 2}``)."""
    return json.dumps(k if isinstance(k, str) else json.dumps(k))


def write_json(obj: Any, path: str | os.PathLike) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(dumps(obj) + "\n")


class StreamedList:
    """Writes a JSON file whose top-level ``key`` is a long list of objects, one item at a time.

    :meth:`append` encodes an item and writes it to a temporary file beside ``path``, so that the
    items need not all be held in memory (a result file of a whole log holds millions of lists);
    :meth:`close` then writes ``head`` with that list in place of ``head[key]``, byte for byte the
    text :func:`write_json` gives the whole object, and moves it to ``path`` (a reader never sees
    half a file). :meth:`discard` (or leaving a ``with`` block on an exception) removes the
    temporary file and writes nothing.
    """

    def __init__(self, path: str | os.PathLike, key: str, width: int = 100):
        self.path, self.key, self.width = os.fspath(path), key, width
        if os.path.isdir(self.path):
            raise IsADirectoryError(f"{self.path!r} is a folder")
        folder, name = os.path.split(os.path.abspath(self.path))
        self._file = tempfile.NamedTemporaryFile("w", encoding="utf-8", dir=folder, prefix=f".{name}.",
                                                 suffix=".partial", delete=False)
        self._count = 0
        self._short: list[str] | None = []  # the items' texts while they could still fit on one line

    def __enter__(self) -> StreamedList:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is not None:
            self.discard()

    def __len__(self) -> int:
        return self._count

    def append(self, item: Any) -> None:
        text = dumps(item, 2, self.width)  # the list is a value of the top-level object: indent 1
        self._file.write(("," if self._count else "") + "\n  " + text)
        self._count += 1
        if self._short is not None:
            self._short.append(text)
            if "\n" in text or sum(map(len, self._short)) + 2 * len(self._short) > self.width:
                self._short = None

    def close(self, head: dict) -> None:
        """Write ``head`` (with ``head[key]`` replaced by the appended items) to ``path``."""
        if self.key not in head:
            self.discard()
            raise ValueError(f"StreamedList.close: head has no key {self.key!r} for the streamed list")
        self._file.close()
        marker = "\n\x00"  # a value with a line break keeps the object on many lines, as the list does
        items = self._short if self._count == 0 or self._short is not None else None
        listed = _list_text(items, 1, self.width) if items else "[]"
        parts = [(_key(k), marker if k == self.key else dumps(v, 1, self.width)) for k, v in head.items()]
        if items is not None and "\n" not in listed:
            parts = [(k, listed if v == marker else v) for k, v in parts]
        text = _object_text(parts, 0, self.width) + "\n"
        before, _, after = text.partition(marker)
        try:
            with open(self._file.name + ".json", "w", encoding="utf-8") as out:
                out.write(before)
                if marker in text:
                    out.write("[")
                    with open(self._file.name, encoding="utf-8") as streamed:
                        shutil.copyfileobj(streamed, out)
                    out.write("\n ]")
                out.write(after)
            os.replace(self._file.name + ".json", self.path)
        finally:
            for leftover in (self._file.name, self._file.name + ".json"):
                if os.path.exists(leftover):
                    os.remove(leftover)

    def discard(self) -> None:
        self._file.close()
        if os.path.exists(self._file.name):
            os.remove(self._file.name)


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

