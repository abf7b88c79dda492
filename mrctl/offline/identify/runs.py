"""Identification runs: loading and checking them, the period, the fit windows.

A run is ``{column: array}`` with t, I (commanded current), F_meas (or F),
v_meas (or v), optionally I_applied: a ``mrctl simulate``/``mrctl run`` log
of a sine stroke through a staircase of constant currents. Here each run is
checked (every problem an IdentificationError naming the run, column and
sample), decimated if sampled fast, its excitation period estimated, and cut
into segments of constant commanded current; each segment gives one fit
window (warm-up samples, then whole periods for Q), grouped by current.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from mrctl.offline.identify.errors import IdentificationError
from mrctl.runlog.read import align_load_cell, try_sidecar
from mrctl.util.csvtable import CsvError, read_table, shown_header

__all__ = ["load_identification_run", "estimate_period"]

#: what to do with measured data these runs' rules refuse
_DATASET_HINT = (" (measured data with a switched, broadband or voltage input: describe it in a dataset and use "
                 "mrctl identify --dataset, docs/identification.md)")

# A commanded current that changes by more than this starts a new segment (A).
_SEGMENT_TOL_A = 1e-6

#: A fit window: (run index, first warm-up sample, first fit sample, end of the fit samples).
Window = tuple[int, int, int, int]

_F_COLUMNS = ("F_meas", "F")
_V_COLUMNS = ("v_meas", "v")
#: the columns identification reads from a run CSV (whichever are there)
_RUN_COLUMNS = ("t", "I", "I_applied", "F_meas", "F", "v_meas", "v", "x_meas", "x")


def load_identification_run(path: str | Path) -> dict[str, np.ndarray]:
    """Read a run CSV (``mrctl simulate``/``mrctl run`` log) for identification.

    Reads only the columns identification uses (t, I, I_applied, F_meas or F,
    v_meas or v, x_meas or x), found by header name; other columns may hold
    anything. ``#`` lines are comments. Errors are IdentificationError naming
    the file, column and line."""
    p = Path(path)
    try:
        table = read_table(p, _RUN_COLUMNS, torn_last_line_ok=True)  # a full disk or SIGKILL tears the last line
    except CsvError as exc:
        raise IdentificationError(str(exc)) from None
    if not table.columns:
        raise IdentificationError(f"{p}: none of the columns t, I, F_meas/F, v_meas/v found "
                                  f"(is this a run CSV?); header: {shown_header(table.header, 80)}")
    table = table._replace(columns=align_load_cell(table.columns, try_sidecar(p)))  # F at its own tick (runlog)
    return table.columns


def _pick(run: Mapping[str, Any], names: Sequence[str]) -> tuple[str | None, np.ndarray | None]:
    for c in names:
        if c in run and run[c] is not None:
            return c, np.asarray(run[c], float)
    return None, None


def _check_run(run: Mapping[str, Any], label: str) -> dict[str, np.ndarray]:
    if not isinstance(run, Mapping):
        raise IdentificationError(f"{label}: must be a mapping of column name to array")
    cols: dict[str, np.ndarray] = {}
    for key, names, what in (("t", ("t",), "time column 't' (s)"),
                             ("I", ("I",), "current column 'I' (commanded current, A)"),
                             ("F", _F_COLUMNS, "force column 'F_meas' or 'F' (N)"),
                             ("v", _V_COLUMNS, "velocity column 'v_meas' or 'v' (m/s)")):
        name, arr = _pick(run, names)
        if arr is None:
            raise IdentificationError(f"{label}: no {what}; identification needs t, I, F_meas (or F) "
                                      f"and v_meas (or v). Found: {', '.join(map(str, run)) or '(none)'}")
        cols[key] = arr.reshape(-1)
        cols[key + "_name"] = name  # type: ignore[assignment]
    _, Ia = _pick(run, ("I_applied",))
    if Ia is not None:
        cols["I_applied"] = Ia.reshape(-1)
    xname, xa = _pick(run, ("x_meas", "x"))
    if xa is not None:
        cols["x"] = xa.reshape(-1)
        cols["x_name"] = xname  # type: ignore[assignment]
    n = cols["t"].size
    for key in ("t", "I", "F", "v", "I_applied", "x"):
        if key not in cols:
            continue
        if cols[key].size != n:
            raise IdentificationError(f"{label}: column {cols.get(key + '_name', key)} has {cols[key].size} "
                                      f"samples, t has {n}")
        bad = np.flatnonzero(~np.isfinite(cols[key]))
        if bad.size:
            raise IdentificationError(f"{label}: column {cols.get(key + '_name', key)} is not finite at "
                                      f"sample {bad[0]} (t = {cols['t'][bad[0]] if key != 't' else float('nan'):g} s)")
    if n < 3:
        raise IdentificationError(f"{label}: {n} sample(s); far too short to identify from")
    dt = np.diff(cols["t"])
    if np.any(dt <= 0.0):
        k = int(np.flatnonzero(dt <= 0.0)[0])
        raise IdentificationError(f"{label}: time t is not strictly increasing at sample {k + 1} "
                                  f"(t = {cols['t'][k]:g} → {cols['t'][k + 1]:g} s)")
    if np.any(cols["I"] < -1e-9):
        raise IdentificationError(f"{label}: negative current in column I (min {cols['I'].min():g} A)"
                                  f"{_DATASET_HINT}")
    return cols


def estimate_period(t: np.ndarray, v: np.ndarray) -> float:
    """Excitation period (s) from the upward zero crossings of the velocity.

    A hysteresis of 20 % of the velocity amplitude keeps sensor noise from
    adding crossings. Raises IdentificationError unless the velocity is
    clearly periodic (a sine stroke, as the method needs)."""
    amp = float(np.percentile(np.abs(v), 99.0))
    if not amp > 0.0:
        raise IdentificationError("the velocity is zero throughout: the damper was not moved")
    hyst = 0.2 * amp
    state = 0
    ups: list[float] = []
    vl = v.tolist()
    tl = t.tolist()
    for k in range(1, len(vl)):
        x = vl[k]
        if x < -hyst:
            state = -1
        elif x > hyst and state == -1:
            state = 1
            # the crossing itself: last sign change before k
            j = k
            while j > 0 and vl[j - 1] > 0.0:
                j -= 1
            if j > 0:
                v0, v1 = vl[j - 1], vl[j]
                ups.append(tl[j - 1] + (tl[j] - tl[j - 1]) * (-v0) / (v1 - v0))
    if len(ups) < 3:
        raise IdentificationError(
            f"the velocity has {max(len(ups) - 1, 0)} full period(s); identification needs a periodic "
            "(sine) stroke of several periods per current")
    d = np.diff(ups)
    T = float(np.median(d))
    spread = float(np.percentile(d, 90) - np.percentile(d, 10))
    if spread > 0.05 * T:
        raise IdentificationError(
            f"the excitation is not periodic (period varies {np.percentile(d, 10):.3g}–{np.percentile(d, 90):.3g} s); "
            "identification needs a constant-frequency sine stroke: pass the period (mrctl identify --period S), "
            "or describe the record in a dataset (--dataset, docs/identification.md) to estimate it per segment")
    return T


def _segments(I: np.ndarray) -> list[tuple[int, int]]:
    cut = np.flatnonzero(np.abs(np.diff(I)) > _SEGMENT_TOL_A) + 1
    edges = np.concatenate(([0], cut, [I.size]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def decimate(checked: list[dict[str, np.ndarray]], labels: Sequence[str], max_rate_hz: float | None,
             warnings: list[str]) -> list[float]:
    """Decimate (in place) the checked runs sampled faster than ``max_rate_hz``;
    returns each run's sample interval (s) after that.

    Anti-aliased: the measured signals (F, v, x, I_applied) go through a
    zero-phase FIR low-pass at 0.8 × the new Nyquist frequency
    (``scipy.signal.resample_poly``, linear edge padding) before every
    ``step``-th sample is kept; t and the commanded current I, a staircase
    the segments are cut on, are subsampled."""
    from scipy.signal import resample_poly

    dts = []
    for c, lab in zip(checked, labels):
        dt = float(np.median(np.diff(c["t"])))
        if max_rate_hz is not None and dt < 1.0 / max_rate_hz * 0.999:
            step = int(round(1.0 / (max_rate_hz * dt)))
            if step > 1:
                n = c["t"][::step].size
                for key in ("F", "v", "I_applied", "x"):
                    if key in c:
                        c[key] = resample_poly(c[key], 1, step, padtype="line")[:n]
                for key in ("t", "I"):
                    c[key] = c[key][::step]
                warnings.append(f"{lab}: decimated by {step} to {1.0 / (dt * step):.0f} Hz (anti-aliased)")
                dt *= step
        dts.append(dt)
    return dts


def common_period(checked: list[dict[str, np.ndarray]], labels: Sequence[str], period_s: float | None) -> float:
    """The excitation period T (s) of all runs: ``period_s``, or estimated per
    run; runs whose periods differ by more than 2 % are refused."""
    periods = []
    for c, lab in zip(checked, labels):
        if period_s is None:
            try:
                periods.append(estimate_period(c["t"], c["v"]))
            except IdentificationError as exc:
                raise IdentificationError(f"{lab}: {exc}") from None
        else:
            periods.append(float(period_s))
    T = float(np.median(periods))
    if any(abs(p - T) > 0.02 * T for p in periods):
        raise IdentificationError("the runs have different excitation periods "
                                  f"({', '.join(f'{p:.4g}' for p in periods)} s); identify them separately")
    return T


def fit_windows(checked: list[dict[str, np.ndarray]], labels: Sequence[str], dts: Sequence[float], T: float,
                settle_periods: float, warmup_periods: float, fit_periods: float | None,
                warnings: list[str]) -> dict[float, list[Window]]:
    """Segments of constant commanded current → fit windows, grouped by current.

    After every change of current ``max(settle_periods, warmup_periods)``
    periods are dropped from Q, the last ``warmup_periods`` of them run the
    model (warm-up); then whole periods (``fit_periods``, or all there are).
    A too-short fragment at a run's start or end is ignored with a warning;
    any other too-short step, a closed-loop run or fewer than 3 currents are
    refused."""
    n_settle = max(settle_periods, warmup_periods)
    groups: dict[float, list[Window]] = {}  # I → [(run, w0, f0, f1)]
    need_s = (n_settle + (fit_periods or 1.0)) * T
    for r, (c, lab) in enumerate(zip(checked, labels)):
        t = c["t"]
        dt = dts[r]
        segs = _segments(c["I"])
        if len(segs) > max(50, 4 * (t[-1] - t[0]) / T):
            raise IdentificationError(
                f"{lab}: the commanded current changes {len(segs) - 1} times; identification needs steps of "
                "constant current (inverse law 'schedule' or 'constant'), not a closed-loop run"
                f"{_DATASET_HINT}")
        for si, (a, b) in enumerate(segs):
            I_cmd = float(c["I"][a])
            dur = t[b - 1] - t[a] + dt
            if dur < need_s - 0.5 * dt:
                edge = si == 0 or si == len(segs) - 1
                if edge and dur < T:
                    warnings.append(f"{lab}: ignored a {dur:.3g} s fragment at {I_cmd:g} A "
                                    f"(t = {t[a]:.4g}–{t[b - 1]:.4g} s)")
                    continue
                raise IdentificationError(
                    f"{lab}: current {I_cmd:g} A is held for only {dur:.3g} s (t = {t[a]:.4g}–{t[b - 1]:.4g} s); "
                    f"identification needs ≥ {need_s:.3g} s per current: {n_settle:g} settling + "
                    f"{fit_periods or 1:g} fit period(s) of {T:.3g} s. Lengthen the steps (inverse.step_s) "
                    "or lower settle_periods")
            f0 = a + int(round(n_settle * T / dt))
            w0 = f0 - int(round(warmup_periods * T / dt))
            avail = (b - f0 + 0.5) * dt / T  # half a sample of slack: T is estimated
            nper = math.floor(avail) if fit_periods is None else min(fit_periods, math.floor(avail))
            f1 = f0 + int(round(nper * T / dt))
            f1 = min(f1, b)
            groups.setdefault(round(I_cmd, 6), []).append((r, w0, f0, f1))
    if len(groups) < 3:
        have = ", ".join(f"{i:g} A" for i in sorted(groups)) or "none"
        raise IdentificationError(
            f"the runs hold {len(groups)} distinct current(s) ({have}); laws (6)–(11) need at least 3 "
            "(the paper used twelve, 0–0.55 A), each held for several periods")
    return groups
