"""The record file of a study (``cells.jsonl``) and the table written from it: nothing finished is
lost, nothing half-written is trusted.

``cells.jsonl`` is a header line (the settings that fix the numbers), then one JSON line per
finished cell, appended and fsynced as each cell finishes. A study started again on the same
folder reads it back and skips the cells it holds. The faults it survives:

- **A kill mid-write** leaves a last line without its newline: it is dropped (the file is
  truncated back to the last complete line) and its cell runs again.
- **A garbled last line** (ends with a newline, but is not JSON or lacks a record's fields: a
  partly flushed buffer, garbage after a crash) is dropped the same way. Either drop is said once
  on stderr. A bad line *before* the last is a :class:`StudyError` naming the line: records after
  it were written later, so it is no interrupted write, and finished work is never dropped silently.
- **A full disk** (or any ``OSError``) during an append: the line goes out in one ``os.write`` on
  an ``O_APPEND`` descriptor; if that fails, is short, or the fsync fails, the file is truncated
  back to its previous length and :class:`RecordWriteError` says what happened in one line. A
  failed rewrite of ``table.csv`` leaves the old table and no temporary file.
- **Two studies on one folder**: the writer holds an exclusive, non-blocking ``flock`` on
  ``cells.jsonl.lock`` for the life of its :class:`Records` (a context manager); a second one
  fails at once with :class:`StudyBusyError`, naming the holder's pid and start time (written into
  the lock file). The kernel releases the lock when the holder closes it or dies, even by SIGKILL.

When a study runs on several hosts (``jax.distributed``) only process 0 writes (:func:`is_writer`)
and takes the lock; the others only read.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import fcntl
import json
import math
import os
import sys
import time
from collections.abc import Iterable, Sequence
from typing import Any

import jax

RECORDS = "cells.jsonl"
LOCK = RECORDS + ".lock"
RECORD_FORMAT = "hybridslam-sweep/1"


class StudyError(ValueError):
    """A study that cannot run as asked (bad grid, records made with other settings)."""


class RecordWriteError(StudyError):
    """A record or the table could not be written (disk full, I/O error); what was recorded is intact."""


class StudyBusyError(StudyError):
    """Another study holds the folder's lock."""


def is_writer() -> bool:
    """Only process 0 writes files when a study runs on several hosts (``jax.distributed``)."""
    return jax.process_index() == 0


def cell_key(cell: dict) -> str:
    return json.dumps(cell, sort_keys=True)


def _cell_label(cell: dict, limit: int = 120) -> str:
    text = json.dumps(cell)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _reason(e: OSError) -> tuple[str, str]:
    """(what happened, what to do) for a failed write, in words."""
    text = e.strerror or (os.strerror(e.errno) if e.errno else str(e)) or type(e).__name__
    fix = "free space" if e.errno in (errno.ENOSPC, errno.EDQUOT) else "fix the cause"
    return text[:1].lower() + text[1:], fix


# --------------------------------------------------------------------------- #
# The lock
# --------------------------------------------------------------------------- #


def _lock(folder: str) -> int | None:
    """An exclusive ``flock`` on ``folder/cells.jsonl.lock`` (its descriptor), or StudyBusyError at once."""
    path = os.path.join(folder, LOCK)
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as e:
        what, fix = _reason(e)
        raise RecordWriteError(f"{what} while creating {path}; {fix} and run the same command again") from e
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise StudyBusyError(f"another study ({holder}) is writing to {folder}; wait for it or use another "
                             "-o folder") from None
    except OSError as e:  # a file system without locks (ENOLCK, EOPNOTSUPP): go on, unguarded
        os.close(fd)
        print(f"WARNING: cannot lock {path} ({e.strerror}); make sure no other study writes to {folder}",
              file=sys.stderr, flush=True)
        return None
    with contextlib.suppress(OSError):  # who holds it, for the message above; the lock works without
        started = time.strftime("%Y-%m-%d %H:%M:%S %Z", time.localtime())
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps({"pid": os.getpid(), "started": started}) + "\n").encode(), 0)
    return fd


def _holder(fd: int) -> str:
    """``pid N, started at T`` from a held lock file (it may still be empty if its holder just took it)."""
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode("utf-8"))
        return f"pid {int(info['pid'])}, started at {info['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "pid unknown"


# --------------------------------------------------------------------------- #
# The append-only record file
# --------------------------------------------------------------------------- #


def _parse(line: bytes) -> Any:
    try:
        return json.loads(line.decode("utf-8"))
    except (ValueError, RecursionError):  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        return None


class Records:
    """``cells.jsonl``: a header line, then one line per finished cell. Append-only; see the module docstring.

    ``done`` maps each recorded cell's key to its record. A record must be a JSON object with a
    ``cell`` object and every key in ``fields``. Opening it takes the folder's lock (process 0
    only): use it as a context manager, or call :meth:`close`, to let another study write there.
    """

    def __init__(self, folder: str, header: dict, *, fields: Sequence[str] = ("cell",)):
        self.folder = folder
        self.path = os.path.join(folder, RECORDS)
        self.done: dict[str, dict] = {}
        self._fields = tuple(dict.fromkeys(("cell", *fields)))
        self._writes = is_writer()
        self._lock: int | None = None
        self._closed = False
        self._broken: str | None = None  # why appends are refused (a failed write could not be undone)
        if self._writes:
            self._lock = _lock(folder)
        try:
            self._load({"format": RECORD_FORMAT, **header})
        except BaseException:
            self.close()
            raise

    def _load(self, head: dict) -> None:
        try:
            with open(self.path, "rb") as f:
                data = f.read()
        except FileNotFoundError:
            data = b""
        *lines, tail = data.split(b"\n")  # tail: what follows the last newline, cut short by a kill
        keep = len(lines)
        if lines:
            old = _parse(lines[0])
            if not (isinstance(old, dict) and "format" in old):
                if len(lines) > 1:
                    raise StudyError(f"{self.path}: line 1 is not a sweep header; remove the file to start "
                                     "afresh")
                keep = 0  # a garbled header and nothing else: nothing finished to lose
            elif old != head:
                diff = [f"{k}: {old.get(k)!r} there, {head.get(k)!r} now"
                        for k in sorted(set(old) | set(head)) if old.get(k) != head.get(k)]
                raise StudyError(
                    f"{self.path} holds a study with other settings ({'; '.join(diff)}); use another output "
                    "folder, or the same settings to resume it"
                )
        for n, line in enumerate(lines[1:], start=2):
            rec = _parse(line)
            problem = self._problem(rec, line)
            if problem is None:
                self.done[cell_key(rec["cell"])] = rec
            elif n == len(lines):
                keep = n - 1  # garbled last line: dropped like a cut-off one, its cell runs again
            else:
                raise StudyError(
                    f"{self.path}: line {n} {problem}; the lines after it hold finished cells, so it is no "
                    "interrupted write: repair or delete that line to resume"
                )
        if not self._writes:
            return
        size = sum(len(line) + 1 for line in lines[:keep])
        if size < len(data):
            dropped = [] if keep == len(lines) else [
                "a garbled header" if keep == 0 else f"a garbled last line (line {len(lines)})"]
            if tail:
                dropped.append("a cut-off line after it" if dropped else "a cut-off header" if not lines
                               else "a cut-off last line")
            then = "the header is written afresh" if keep == 0 else "its cell runs again"
            print(f"WARNING: {self.path}: dropped {' and '.join(dropped)} left by an interrupted write "
                  f"({len(data) - size} bytes); {then}", file=sys.stderr, flush=True)
            with open(self.path, "r+b") as f:
                f.truncate(size)
        if keep == 0:
            self._append((json.dumps(head) + "\n").encode(), f"writing the header of {self.path}")

    def _problem(self, rec: Any, line: bytes) -> str | None:
        """Why ``line`` is no record (None when it is one)."""
        if rec is None:
            return "is not valid JSON" if line.strip() else "is empty"
        if not isinstance(rec, dict):
            return "is not a JSON object"
        missing = [k for k in self._fields if k not in rec]
        if missing:
            return f"lacks {', '.join(map(repr, missing))}"
        if not isinstance(rec["cell"], dict):
            return "has a 'cell' that is not an object"
        return None

    def __contains__(self, cell: dict) -> bool:
        return cell_key(cell) in self.done

    def append(self, record: dict) -> None:
        """Record a finished cell: one line, written whole and fsynced, or not at all (RecordWriteError)."""
        key = cell_key(record["cell"])
        if self._writes:
            self._append((json.dumps(record, allow_nan=True) + "\n").encode(),
                         f"recording cell {_cell_label(record['cell'])} in {self.path}")
        self.done[key] = record

    def _append(self, line: bytes, what: str) -> None:
        if self._closed:
            raise StudyError(f"{self.path}: the records were closed; open them again to append")
        if self._broken:
            raise RecordWriteError(self._broken)
        before = None
        fd = -1
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o644)
            before = os.fstat(fd).st_size
            written = os.write(fd, line)  # one write: O_APPEND puts it whole at the end, or part of it
            if written != len(line):
                raise OSError(errno.ENOSPC, f"short write ({written} of {len(line)} bytes; disk full?)")
            os.fsync(fd)
        except OSError as e:
            undone = before is None
            if before is not None:
                try:
                    os.ftruncate(fd, before)
                    undone = True
                except OSError:
                    pass
            reason, fix = _reason(e)
            if undone:
                raise RecordWriteError(f"{reason} while {what}; nothing was lost: {fix} and run the same "
                                       "command again to resume") from e
            # The part written stays as a cut-off last line, which the next run drops.
            self._broken = (f"{reason} while {what}, and the part written could not be removed; {fix} and "
                            "run the same command again to resume (it drops that part)")
            raise RecordWriteError(self._broken) from e
        finally:
            if fd >= 0:
                os.close(fd)

    def close(self) -> None:
        """Release the folder's lock (appends are refused from here on)."""
        self._closed = True
        fd, self._lock = getattr(self, "_lock", None), None
        if fd is not None:
            os.close(fd)

    def __enter__(self) -> Records:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()


# --------------------------------------------------------------------------- #
# The table
# --------------------------------------------------------------------------- #


def _csv_value(value: Any) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else format(value + 0.0, ".10g")
    return str(value)


def write_table(path: str, columns: Sequence[str], rows: Iterable[dict]) -> None:
    """Write the table whole or not at all: a temporary file, fsynced, then renamed over the old one."""
    if not is_writer():
        return
    tmp = path + ".tmp"
    try:
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(columns)
            for row in rows:
                writer.writerow([_csv_value(row[c]) for c in columns])
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)  # atomic: a kill never leaves half a table
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        if not isinstance(e, OSError):
            raise
        reason, fix = _reason(e)
        raise RecordWriteError(f"{reason} while writing {path}; the previous table is intact and every "
                               f"finished cell is in {RECORDS}: {fix} and run the same command again") from e


def read_table(path: str) -> list[dict]:
    """``table.csv`` as a list of dicts of strings (what :mod:`hybridslam.plot` reads)."""
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))
