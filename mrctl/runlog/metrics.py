"""Tracking figures of a run, computed offline with numpy.

The definitions are the ones the issues and docs quote:
- force NRMSE: RMS(F − F_des) over t ≥ settle, divided by the peak-to-peak
  of F_des over the same window;
- largest current step: max |I_k − I_{k−1}| over the same window;
- shares of ticks at 0 A and at I_max.
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np

# A current within this of a limit counts as "at" it (float noise only).
_AT_LIMIT_A = 1e-9


def tracked_force(cols: Mapping[str, np.ndarray]) -> tuple[np.ndarray, str]:
    """The force a run's tracking is judged on, and its column name.

    ``F_true`` (the plant's force at that tick) when the log has it (a
    simulated bench: the in-process sim or hil_sim's ground truth joined in),
    else ``F``, the load cell. The load cell reads the previous tick's force
    plus noise, so on a simulated bench it would add a tick of lag the damper
    does not have. The daemon's summary and the report use this one rule."""
    F_true = cols.get("F_true")
    if F_true is not None and len(F_true) and math.isfinite(float(F_true[-1])):
        return F_true, "F_true"
    return cols["F"], "F"


def tracking_summary(
    t: np.ndarray, F_des: np.ndarray, F: np.ndarray, I: np.ndarray, I_max: float | None, settle_s: float
) -> dict[str, float]:
    """Figures over t ≥ t[0] + settle_s (the whole run if that leaves < 2 ticks).

    Rows where F or F_des is NaN carry no value (a daemon log while the safety
    supervisor held 0 A, no load cell): they are left out of the force
    figures, which are NaN only if fewer than 2 rows are left. ``I_max`` None
    means the run's own largest current in the window (reports of a log
    whose limit is not known)."""
    t = np.asarray(t, float)
    F_des = np.asarray(F_des, float)
    F = np.asarray(F, float)
    m = t >= t[0] + settle_s
    if m.sum() < 2:
        m = np.ones_like(t, dtype=bool)
    valid = m & np.isfinite(F) & np.isfinite(F_des)
    if valid.sum() >= 2:
        e = F[valid] - F_des[valid]
        rmse = float(math.sqrt(np.mean(e * e)))
        p2p = float(np.ptp(F_des[valid]))
        nrmse = rmse / p2p if p2p > 0 else math.nan
    else:
        rmse = nrmse = math.nan
    Iw = np.asarray(I, float)[m]
    top = float(np.max(Iw)) if I_max is None else I_max
    return {
        "window_start_s": float(t[m][0]),
        "window_ticks": float(m.sum()),
        "force_rmse_N": rmse,
        "force_nrmse": nrmse,
        "max_current_step_A": float(np.max(np.abs(np.diff(Iw)))) if Iw.size > 1 else 0.0,
        "share_at_zero": float(np.mean(Iw <= _AT_LIMIT_A)),
        "share_at_I_max": float(np.mean(Iw >= top - _AT_LIMIT_A)),
    }


#: the shortest settled window a run's tracking is judged on (s): a shorter one is mostly the
#: law's start (the first ramp from 0 A) and says little about the tracking
MIN_TRACKING_WINDOW_S = 1.0


def settled(track: Mapping[str, float], settle_s: float, dt_s: float) -> bool:
    """Whether a :func:`tracking_summary` is over a settled window the verdict
    judges: after ``settle_s`` and at least :data:`MIN_TRACKING_WINDOW_S` long
    (a run shorter than that is all start-up transient)."""
    return (float(track.get("window_start_s", math.nan)) >= settle_s - 1e-9
            and float(track.get("window_ticks", 0.0)) * dt_s >= MIN_TRACKING_WINDOW_S - 1e-9)


def format_summary(s: Mapping[str, float], I_max: float, dt_s: float | None = None, settle_s: float = 0.0) -> str:
    """The summary's lines; a run with no force to track (F_des constant, a
    current schedule) says so instead of ``nan %``. Given the period
    ``dt_s``, a run too short for a settled window gives its force RMSE
    only, and says the NRMSE is not judged: normalised by the few newtons
    a start-up demands, it reads millions of per cent."""
    nrmse = s["force_nrmse"]
    if math.isfinite(nrmse) and dt_s is not None and not settled(s, settle_s, dt_s):
        start, window = float(s["window_start_s"]), float(s.get("window_ticks", 0.0)) * dt_s
        why = (f"the run ends before excitation.settle_s ({settle_s:g} s)" if start < settle_s - 1e-9 else
               f"{window:.3f} s past excitation.settle_s ({settle_s:g} s), under the {MIN_TRACKING_WINDOW_S:g} s "
               "the verdict judges")
        force = f"force RMSE (t >= {start:.3f} s): {s['force_rmse_N']:.4f} N; NRMSE not judged: {why}"
    elif math.isfinite(nrmse):
        force = (f"force NRMSE (t >= {s['window_start_s']:.3f} s): {100 * nrmse:.3f} %"
                 f"  (RMSE {s['force_rmse_N']:.4f} N)")
    else:
        force = "force NRMSE: none (no varying force demanded: the law sets the current)"
    return (
        f"{force}\n"
        f"largest current step between ticks: {s['max_current_step_A']:.4f} A\n"
        f"ticks at 0 A: {100 * s['share_at_zero']:.1f} %   at I_max ({I_max:g} A): {100 * s['share_at_I_max']:.1f} %"
    )


#: the shortest stretch at rest before the motion that measures a load cell's zero (s)
REST_MIN_S = 0.1
#: displacement that counts as motion from the run's first reading: 20 um, above an LVDT's noise
REST_X_M = 2e-5
#: the end of the stretch at rest left out: the shaker is starting before x has moved REST_X_M
REST_MARGIN_S = 0.05


def load_cell_offset(cols: Mapping[str, np.ndarray], dt_s: float, delay_ticks: int = 0,
                     F_offset_N: float = 0.0) -> dict[str, float]:
    """The load cell's zero error (N) and its share of the demanded force's
    range, where the run can tell it; {} where it cannot.

    On a simulated bench (``F_true`` logged) it is the mean of the reading
    against the force it read (``delay_ticks`` earlier: the in-process bench's
    load cell reads the previous tick's). On hardware it is the mean reading
    over the stretch at rest before the motion (at least :data:`REST_MIN_S`,
    the displacement within :data:`REST_X_M` of its first reading, less its
    last :data:`REST_MARGIN_S`) less the
    damper's own static force ``F_offset_N`` (its accumulator's, from the
    parameter set); a run that moves from its first tick has no such stretch."""
    F = np.asarray(cols["F"], float)
    F_des = np.asarray(cols["F_des"], float)
    ok = np.isfinite(F_des)
    p2p = float(np.ptp(F_des[ok])) if ok.sum() >= 2 else math.nan
    F_true = cols.get("F_true")
    if F_true is not None and len(F_true) and math.isfinite(float(np.asarray(F_true)[-1])):
        Ft = np.asarray(F_true, float)
        d = int(delay_ticks)
        diff = F[d:] - Ft[:len(Ft) - d] if d else F - Ft
    else:
        x = np.asarray(cols["x"], float)
        if not len(x) or not math.isfinite(float(x[0])):
            return {}
        moved = np.flatnonzero(~(np.abs(x - x[0]) <= REST_X_M))
        n = int(moved[0]) if len(moved) else len(x)
        n -= int(round(REST_MARGIN_S / dt_s))  # the motion starts before x has moved 20 um
        if n * dt_s < REST_MIN_S:
            return {}
        diff = F[:n] - F_offset_N
    diff = diff[np.isfinite(diff)]
    if len(diff) < 2:
        return {}
    off = float(np.mean(diff))
    return {"load_cell_offset_N": off, "load_cell_offset": abs(off) / p2p if p2p > 0 else math.nan}
