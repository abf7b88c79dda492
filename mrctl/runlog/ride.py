"""Ride figures of a quarter-car run: comfort and road holding (docs/quarter-car.md).

- ride comfort: RMS of the body's (sprung mass's) acceleration, m/s²;
- road holding: RMS of the tyre's deflection x_u − x_r, m (a varying tyre
  load is a varying grip);
- RMS suspension stroke (the damper's x), m, the rattle space used.

Each over t ≥ t[0] + settle_s (the whole run if that leaves < 2 rows).
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np


def _rms(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(math.sqrt(np.mean(a * a))) if a.size else math.nan


def ride_summary(cols: Mapping[str, np.ndarray], settle_s: float) -> dict[str, float]:
    """RMS body acceleration, tyre deflection and stroke of a run's columns
    (``t``, ``a_sprung``, ``tyre_defl``, ``x``)."""
    t = np.asarray(cols["t"], float)
    m = t >= t[0] + settle_s
    if m.sum() < 2:
        m = np.ones_like(t, dtype=bool)
    return {
        "rms_a_sprung_mps2": _rms(np.asarray(cols["a_sprung"], float)[m]),
        "rms_tyre_defl_m": _rms(np.asarray(cols["tyre_defl"], float)[m]),
        "rms_stroke_m": _rms(np.asarray(cols["x"], float)[m]),
    }


def format_ride(s: Mapping[str, float]) -> str:
    return (f"ride: RMS body acceleration {s['rms_a_sprung_mps2']:.4f} m/s², RMS tyre deflection "
            f"{1e3 * s['rms_tyre_defl_m']:.4f} mm, RMS stroke {1e3 * s['rms_stroke_m']:.3f} mm")
