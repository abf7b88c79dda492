"""A finished run's verdict: ``ok``, or ``degraded`` with the bounds it broke.

Why here: the verdict is a judgement of the run log and of the counters the
loop and the safety supervisor keep anyway (ticks in fault, skipped
deadlines, the longest gap between tick starts); nothing is added to the
per-tick path. The figures that need rows (the longest forced-0 A stretch,
the force NRMSE) are computed after the run from the log as written; a run
without a log estimates the stretch from the supervisor's longest run of
bad samples and says so. The bounds come from the experiment's
``acceptance`` section (:mod:`mrctl.config.acceptance`), handed in as a
plain dict so this module stays below the config layer.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from mrctl.runlog.metrics import settled

OK = "ok"
DEGRADED = "degraded"

#: (figure key, bound key, what it is, how it is shown)
_CHECKS: tuple[tuple[str, str, str, str], ...] = (
    ("fault_share", "max_fault_share", "ticks in fault", "%"),
    ("skipped_share", "max_skipped_share", "deadlines skipped", "%"),
    ("longest_gap_s", "max_gap_s", "longest gap between tick starts", "s"),
    ("longest_zero_stretch_s", "max_zero_stretch_s", "longest stretch at forced 0 A", "s"),
    ("force_nrmse", "max_force_nrmse", "force NRMSE", "%"),
    ("latched_s", "max_latched_s", "time latched (0 A until mrctl arm)", "s"),
    ("share_at_I_max", "max_share_at_I_max", "ticks at I_max (of the settled window)", "%"),
    ("load_cell_offset", "max_load_cell_offset", "load-cell zero error (of the demanded force's range)", "%"),
)


def _show(value: float, unit: str) -> str:
    return f"{100 * value:.1f} %" if unit == "%" else f"{1e3 * value:.0f} ms"


def forced_zero(cols: Mapping[str, np.ndarray]) -> np.ndarray:
    """Rows where the supervisor forced 0 A: a fault bit set, or no usable
    sample (``x`` NaN: the law was not asked)."""
    bad = ~np.isfinite(np.asarray(cols["x"], float))
    if "fault" in cols:
        f = np.asarray(cols["fault"], float)
        bad |= np.isfinite(f) & (f != 0)
    return bad


def longest_run(mask: np.ndarray) -> int:
    """Length of the longest run of True in ``mask``."""
    m = np.asarray(mask, bool)
    if not m.any():
        return 0
    d = np.diff(np.concatenate(([0], m.view(np.int8), [0])))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return int(np.max(ends - starts))


def row_figures(cols: Mapping[str, np.ndarray], dt_s: float) -> dict[str, float]:
    """What the rows tell: the share of rows in fault, the longest forced-0 A
    stretch (s, counting ticks the ``k`` column skipped inside it), and the
    longest gap between logged ticks (s, from ``k``)."""
    n = len(cols["t"])
    out: dict[str, float] = {}
    if n == 0:
        return out
    if "fault" in cols:
        f = np.asarray(cols["fault"], float)
        out["fault_share"] = float(np.mean(np.isfinite(f) & (f != 0)))
    zero = forced_zero(cols)
    k = np.asarray(cols["k"], float) if "k" in cols else np.arange(n, dtype=float)
    if zero.any():
        d = np.diff(np.concatenate(([0], zero.view(np.int8), [0])))
        starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
        # a stretch lasts from its first zero row to the next row that is not
        # (or the run's end): ticks skipped within it were at 0 A too
        stop = np.where(ends < n, k[np.minimum(ends, n - 1)], k[-1] + 1)
        out["longest_zero_stretch_s"] = float(np.max(stop - k[starts])) * dt_s
    else:
        out["longest_zero_stretch_s"] = 0.0
    if n > 1:
        out["longest_gap_s"] = float(np.max(np.diff(k))) * dt_s
    return out


def judge(figures: Mapping[str, Any], bounds: Mapping[str, Any], dt_s: float) -> dict[str, Any]:
    """The verdict of a run's figures against its bounds.

    Returns ``{"verdict": "ok"|"degraded", "reasons": [...], "figures": {...},
    "bounds": {...}}``; a figure that is missing or NaN is not judged (a
    simulate run has no gaps; a run without a load cell no NRMSE). The gap
    bound is never tighter than two periods (a rate reduced at start-up)."""
    b = dict(bounds)
    if b.get("max_gap_s") is not None:
        b["max_gap_s"] = max(float(b["max_gap_s"]), 2.0 * dt_s)
    reasons = []
    for key, bkey, what, unit in _CHECKS:
        value, bound = figures.get(key), b.get(bkey)
        if value is None or bound is None or not math.isfinite(float(value)):
            continue
        if float(value) > float(bound):
            reasons.append(f"{what} {_show(float(value), unit)} > {_show(float(bound), unit)} "
                           f"(acceptance.{bkey}: by {_show(float(value) - float(bound), unit)})")
    figs = {k: (None if v is None or not math.isfinite(float(v)) else float(v)) for k, v in figures.items()}
    return {"verdict": DEGRADED if reasons else OK, "reasons": reasons, "figures": figs, "bounds": b}


def tracking_judged(track: Mapping[str, Any] | None, settle_s: float, dt_s: float) -> dict[str, Any]:
    """The tracking figures the verdict judges: the force NRMSE and the share
    at I_max, only over a settled window of at least
    :data:`mrctl.runlog.metrics.MIN_TRACKING_WINDOW_S` (a run shorter than its settling time is
    all start-up transient: not judged on them), and the load cell's zero
    error."""
    t = track or {}
    judged = settled(t, settle_s, dt_s)
    return {"force_nrmse": t.get("force_nrmse") if judged else None,
            "share_at_I_max": t.get("share_at_I_max") if judged else None,
            "load_cell_offset": t.get("load_cell_offset")}


def offline_judgement(row_figs: Mapping[str, float], summary: Mapping[str, Any], bounds: Mapping[str, Any],
                      dt_s: float, settle_s: float = 0.0) -> dict[str, Any]:
    """The verdict of an offline run (``mrctl simulate``) on what it has:
    faults, forced 0 A, tracking; no real clock, so no skips or gaps. From
    the run's :func:`row_figures`, however they were computed (``mrctl
    simulate`` accumulates them block by block: :mod:`mrctl.runlog.blockmetrics`)."""
    figs = dict(row_figs)
    figs.pop("longest_gap_s", None)
    figs.update(tracking_judged(summary, settle_s, dt_s))
    return judge(figs, bounds, dt_s)


def format_verdict(v: Mapping[str, Any]) -> str:
    """One line: ``verdict: ok (...)`` or ``verdict: degraded: reason; reason``."""
    if v.get("verdict") == DEGRADED:
        return "verdict: degraded: " + "; ".join(v.get("reasons", ()))
    f = v.get("figures", {})
    parts = [f"{what} {_show(f[key], unit)}" for key, _, what, unit in _CHECKS if f.get(key) is not None]
    return "verdict: ok" + (f" ({', '.join(parts)})" if parts else "")


def format_bounds(b: Mapping[str, Any]) -> str:
    """The bounds as ``mrctl check`` prints them."""
    parts = [f"{bkey} {_show(float(b[bkey]), unit) if b.get(bkey) is not None else 'not judged'}"
             for _, bkey, _, unit in _CHECKS]
    return "acceptance: " + ", ".join(parts) + " (a run that breaks one ends with exit 5)"
