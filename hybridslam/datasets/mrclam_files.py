"""Reading and checking the files of a UTIAS MRCLAM dataset folder (used by :mod:`.mrclam`).

Leung, Halpern, Barfoot & Liu, "The UTIAS multi-robot cooperative localization and mapping
dataset", IJRR 30(8), 2011. One folder per dataset: ``Barcodes.dat`` (subject, barcode),
``Landmark_Groundtruth.dat`` (subject, x, y, x sd, y sd), and per robot ``N`` in 1-5
``RobotN_Odometry.dat`` (time, v, ω), ``RobotN_Measurement.dat`` (time, barcode, range, bearing)
and ``RobotN_Groundtruth.dat`` (time, x, y, θ). Whitespace-separated columns, ``#`` comment lines
on top, CRLF line ends, times in Unix seconds; subjects 1-5 are robots, the rest landmarks.

Every reader raises :class:`MRCLAMError` with one line naming the file and line; the checks of
user settings (:func:`finite`, :func:`covariance`) name the setting.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from .textfile import read_ascii

ROBOTS = (1, 2, 3, 4, 5)  # MRCLAM subjects 1-5 are robots

class MRCLAMError(ValueError):
    """A missing or malformed MRCLAM file, or an import setting the data cannot serve. One line."""


@dataclass(frozen=True)
class Table:
    """The numbers of one ``.dat`` file: ``rows`` (n, columns) and the 1-based line of each row."""

    path: str
    rows: np.ndarray
    lines: np.ndarray


@dataclass(frozen=True)
class RobotLog:
    """One robot's three files; times in Unix seconds."""

    odometry: Table  # time, v [m/s], ω [rad/s]
    measurements: Table  # time, barcode, range [m], bearing [rad]
    groundtruth: Table  # time, x [m], y [m], θ [rad]


# --------------------------------------------------------------------------- #
# Reading
# --------------------------------------------------------------------------- #


def read_table(path: str, columns: int, what: str) -> Table:
    """The numeric rows of a ``.dat`` file; ``#`` lines and blank lines are skipped.

    ``what`` names the columns for messages. Raises :class:`MRCLAMError` naming the file (and the
    line) when it is missing, unreadable or holds a line that is not ``columns`` finite numbers.
    """
    rows, lines = [], []
    for lineno, line in enumerate(read_ascii(path, MRCLAMError).split("\n"), 1):
        text = line.strip()
        if text and not text.startswith("#"):
            rows.append(_numbers(text, columns, what, path, lineno))
            lines.append(lineno)
    return Table(path, np.array(rows, dtype=np.float64).reshape(len(rows), columns), np.array(lines))


def _numbers(text: str, columns: int, what: str, path: str, lineno: int) -> list[float]:
    parts = text.split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(parts) != columns or len(values) != columns or not all(map(math.isfinite, values)):
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise MRCLAMError(f"{path}:{lineno}: expected {columns} numbers ({what}), got {shown!r}")
    return values


def _check_times(table: Table, allow_empty: bool = False) -> None:
    """Times (column 0) must not decrease: the files are logs in time order."""
    t = table.rows[:, 0]
    if not len(t) and not allow_empty:
        raise MRCLAMError(f"{table.path}: no records")
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        i = back[0] + 1
        raise MRCLAMError(f"{table.path}:{table.lines[i]}: time {t[i]:.3f} is before the previous "
                          f"record's {t[i - 1]:.3f} (records must be in time order)")


def read_barcodes(dataset_dir: str) -> dict[int, int]:
    """``Barcodes.dat`` as ``{barcode: subject}``."""
    table = read_table(os.path.join(dataset_dir, "Barcodes.dat"), 2, "subject, barcode")
    return {int(b): int(s) for s, b in table.rows}


def read_landmarks(dataset_dir: str) -> Table:
    """``Landmark_Groundtruth.dat``: rows (subject, x, y, x sd, y sd) [m], subjects unique and > 5."""
    table = read_table(os.path.join(dataset_dir, "Landmark_Groundtruth.dat"), 5, "subject, x, y, x sd, y sd")
    seen: set[int] = set()
    for (subject, *_), line in zip(table.rows, table.lines):
        if subject in seen or subject in ROBOTS or subject != int(subject):
            raise MRCLAMError(f"{table.path}:{line}: subject {subject:g} is a robot, not an integer, "
                              "or listed twice")
        seen.add(subject)
    if not seen:
        raise MRCLAMError(f"{table.path}: no landmarks")
    return table


def read_robot(dataset_dir: str, robot: int) -> RobotLog:
    """Robot ``robot``'s odometry, measurements and ground truth, each checked to be in time order."""
    if robot not in ROBOTS:
        raise MRCLAMError(f"robot {robot}: no such robot (MRCLAM robots are 1-5)")
    name = os.path.join(dataset_dir, f"Robot{robot}_")
    tables = []
    for suffix, columns, what in (("Odometry", 3, "time, v, omega"),
                                  ("Measurement", 4, "time, barcode, range, bearing"),
                                  ("Groundtruth", 4, "time, x, y, theta")):
        path = f"{name}{suffix}.dat"
        if not os.path.exists(path):
            raise MRCLAMError(f"{path}: no such file (robot {robot} has no {suffix.lower()} log)")
        table = read_table(path, columns, what)
        _check_times(table, allow_empty=suffix == "Measurement")  # a robot may see nothing
        tables.append(table)
    return RobotLog(*tables)


def finite(value: Any, name: str, unit: str, positive: bool = True) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0):
        raise MRCLAMError(f"{name}: expected a {'positive' if positive else 'finite'} number of {unit}, "
                          f"got {value!r}")
    return float(value)


def covariance(value: Any, n: int, name: str) -> np.ndarray | None:
    """A user's covariance: ``None``, ``n`` variances (diagonal) or an n×n SPD matrix."""
    if value is None:
        return None
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise MRCLAMError(f"{name}: expected {n} variances or a {n}x{n} matrix, got {value!r}") from None
    m = np.diag(m) if m.shape == (n,) else m
    if m.shape != (n, n) or not np.all(np.isfinite(m)):
        raise MRCLAMError(f"{name}: expected {n} finite variances or a {n}x{n} matrix, got shape {m.shape}")
    try:
        if not np.allclose(m, m.T):
            raise np.linalg.LinAlgError
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        raise MRCLAMError(f"{name}: not symmetric positive definite") from None
    return m

