"""Fail-safe rules. The safe state of an MR damper is 0 A.

Whatever a law computes, the driver only ever sees a finite current in
[0, I_max]; NaN and negative values become 0 A.
"""

from __future__ import annotations


def clamp_current(I: float, I_max: float) -> float:
    """Clamp to [0, I_max]; NaN → 0 A (comparisons with NaN are false)."""
    if I > 0.0:
        return I if I < I_max else I_max
    return 0.0
