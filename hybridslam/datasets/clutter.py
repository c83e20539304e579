"""The clutter hypothesis an importer declares: ``sensor.clutter_log_density``, from the user's
option or the importer's default, with the one-line errors every importer gives."""

from __future__ import annotations

import math


def declared_clutter(value: float | str | None, default: float | None, error: type[ValueError]) -> float | None:
    """``sensor.clutter_log_density`` to write (log of a density in 1 / (m rad)): ``value`` when it
    is a finite number, none for ``"none"``, ``default`` when ``value`` is ``None``; anything else
    is an ``error`` (the importer's own error type) naming the option."""
    if value is None:
        return default
    if isinstance(value, str):
        if value != "none":
            raise error(f"clutter_log_density: expected a finite number or 'none', got {value!r}")
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise error(f"clutter_log_density: expected a finite number of nats, got {value!r}")
    return float(value)
