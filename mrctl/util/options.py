"""Checks of command-line options that several commands share."""

from __future__ import annotations

import math

from mrctl.errors import BadInput

__all__ = ["MAX_DURATION_S", "check_duration"]

#: the longest run: the config's duration_s allows as much (mrctl/config/experiment.py)
MAX_DURATION_S = 7 * 86400.0


def check_duration(value: float | None, name: str = "--duration") -> float | None:
    """A run length from the command line, checked like the config's
    ``duration_s``: None (not given) or a finite number of seconds > 0, at
    most a week (leave it out to run until stopped)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise BadInput(f"{name}: must be a finite number of seconds > 0, got {value!r} "
                       f"(leave it out to run as the config says)")
    if value > MAX_DURATION_S:
        raise BadInput(f"{name}: at most {MAX_DURATION_S:g} s (a week), got {value!r}; "
                       f"leave it out and set no duration_s to run until stopped")
    return float(value)
