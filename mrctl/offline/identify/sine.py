"""Constant-input sine tests from real records: the paper's Section III, robust.

A real test is rarely one clean periodic record: the lab's file may start at
rest, ramp the stroke in and out, pause, hold several input levels, or change
frequency. Per span (:mod:`.prep`):

1. **Levels**: runs of one constant input level (``level``/``levels`` of
   the dataset, or the input column's constant stretches).
2. **Cycles**: upward zero crossings of the velocity (hysteresis 20 % of the
   run's velocity scale); consecutive cycles whose durations agree within
   10 % form a group (a pause, a change of frequency starts a new one), the
   group's period is the median duration.
3. **Steady cycles**: the stroke of each cycle (peak-to-peak displacement,
   or of ∫v dt); the steady stroke is the one most cycles share within
   ``steady_tolerance``; the longest run of cycles at it is used, so ramps in
   and out are left out. The cycle before it warms the model up.
4. **Held out**: the last ``fraction`` (default half) of each segment's
   steady cycles, whole cycles; records with ``role: holdout`` entirely.

Per level, Θ = [σ0, σ1, σ2, Fc, Fs, vs] is fitted jointly over that level's
segments (:func:`mrctl.offline.identify.fit._fit_one_current`), the offset
and the stiffness solved exactly for every Θ (variable projection).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from mrctl.offline.identify.errors import IdentificationError
from mrctl.offline.identify.fit import _fit_one_current, _identifiability, _noise_N
from mrctl.offline.identify.guards import Support
from mrctl.offline.identify.model import THETA_NAMES, _model_batch, hys_columns, lugre_force
from mrctl.offline.identify.prep import _MIN_LEVEL_S, Span

__all__ = ["Segment", "LevelFit", "find_segments", "fit_levels", "predict_segment", "segment_hys", "choose_x_hys"]

_PERIOD_TOL = 0.10


@dataclass
class Segment:
    """Steady cycles of one span at one level: sample indices into the span."""

    span: int
    record: str
    role: str
    level: float
    w0: int  # warm-up start
    f0: int  # first fit sample
    f1: int  # end of the fit samples = first held-out sample
    h1: int  # end of the held-out samples
    period_s: float
    stroke_m: float
    cycles_fit: int
    cycles_hold: int


@dataclass
class LevelFit:
    """Θ, offset and stiffness at one input level."""

    level: float
    theta: dict[str, float]
    offset_N: float
    k_x: float
    nrmse_fit: float
    samples: int
    cycles: int
    support: Support
    nfev: int = 0
    time_s: float = 0.0
    segments: list[Segment] = field(default_factory=list)
    noise_nrmse: float = math.nan  # the load cell's noise floor of the same ratio (from the measured force)
    se: dict[str, float] = field(default_factory=dict)  # standard errors (white-noise assumption)
    rel_se: dict[str, float] = field(default_factory=dict)  # se / |θ|
    sensitivity: dict[str, float] = field(default_factory=dict)  # |Δθ|/|θ| moving F by 1 % of ptp
    corr: list[list[float]] = field(default_factory=list)
    determined: dict[str, str] = field(default_factory=dict)  # "well" / "poor" (fit._identifiability)
    theta0: dict[str, float] = field(default_factory=dict)  # the data-derived start
    #: the hysteretic stiffness per direction (N/m) at the set's x_hys (model.hysteresis), else 0
    k_hys_pos: float = 0.0
    k_hys_neg: float = 0.0


def _level_runs(sp: Span) -> list[tuple[int, int, float]]:
    """(first, end, level) of each stretch of one level (:func:`~.prep.prepare` set them)."""
    lv = sp.level
    if lv is None:  # pragma: no cover - the schema asks for levels or an input column
        return []
    runs = []
    finite = np.isfinite(lv)
    k = 0
    n = lv.size
    while k < n:
        if not finite[k]:
            k += 1
            continue
        j = k + 1
        while j < n and finite[j] and lv[j] == lv[k]:
            j += 1
        runs.append((k, j, float(lv[k])))
        k = j
    return runs


def _crossings(v: np.ndarray) -> np.ndarray:
    """Sample indices j of upward zero crossings (v[j−1] ≤ 0 < v[j]) with hysteresis."""
    amp = float(np.percentile(np.abs(v), 99.0)) if v.size else 0.0
    if not amp > 0.0:
        return np.zeros(0, int)
    hyst = 0.2 * amp
    out = []
    state = 0
    for k, x in enumerate(v.tolist()):
        if x < -hyst:
            state = -1
        elif x > hyst and state == -1:
            state = 1
            j = k
            while j > 0 and v[j - 1] > 0.0:
                j -= 1
            out.append(j)
    return np.asarray(out, int)


def _groups(c: np.ndarray) -> list[tuple[int, int]]:
    """Runs of consecutive cycles (c[i], c[i+1]) of similar duration: (first, last+1) cycle index."""
    d = np.diff(c)
    groups = []
    i = 0
    while i < d.size:
        j = i + 1
        while j < d.size and abs(d[j] - np.median(d[i:j])) <= _PERIOD_TOL * np.median(d[i:j]):
            j += 1
        groups.append((i, j))
        i = j
    return groups


def find_segments(spans: list[Span], *, fraction: float, steady_tol: float, min_cycles: int,
                  warnings: list[str]) -> list[Segment]:
    """The steady, held-out and warm-up cycles of every span (see the module
    doc). IdentificationError, listing the levels skipped and why, when no
    segment has a cycle to fit."""
    segs: list[Segment] = []
    skipped: list[str] = []
    transitions = 0
    for si, sp in enumerate(spans):
        h = sp.dt
        for a, b, level in _level_runs(sp):
            if (b - a) * h < _MIN_LEVEL_S:  # a step's transition between two levels
                transitions += 1
                continue
            v = sp.v[a:b]
            c = _crossings(v) + a
            where = f"{sp.record} at {level:g} (t = {sp.t[a]:.4g}–{sp.t[b - 1]:.4g} s)"
            if c.size < min_cycles + 1:
                skipped.append(f"{where}: {max(c.size - 1, 0)} whole cycle(s), fewer than {min_cycles}; skipped")
                continue
            x = sp.x if sp.x is not None else np.cumsum(sp.v) * h
            for g0, g1 in _groups(c):
                strokes = np.array([np.ptp(x[c[i]:c[i + 1]]) for i in range(g0, g1)])
                counts = [int(np.sum(np.abs(strokes - s) <= steady_tol * s)) for s in strokes]
                best = max(range(len(strokes)), key=lambda i: (counts[i], strokes[i]))
                ref = strokes[best]
                ok = np.abs(strokes - ref) <= steady_tol * ref
                # the longest run of steady cycles
                runs, k = [], 0
                while k < ok.size:
                    if ok[k]:
                        j = k
                        while j < ok.size and ok[j]:
                            j += 1
                        runs.append((k, j))
                        k = j
                    else:
                        k += 1
                r0, r1 = max(runs, key=lambda r: r[1] - r[0])
                i0, i1 = g0 + r0, g0 + r1  # cycle indices into c
                if i0 > 0:
                    w0 = int(c[i0 - 1])  # the cycle before warms the model up (ramp or not)
                else:
                    w0, i0 = int(c[i0]), i0 + 1
                n = i1 - i0
                if n < min_cycles:
                    if g1 - g0 >= min_cycles:
                        skipped.append(f"{where}: only {n} steady cycle(s) in a group of {g1 - g0}; skipped")
                    continue
                if sp.role == "holdout":
                    n_hold = n
                else:
                    n_hold = 0 if fraction <= 0.0 else min(max(1, int(round(fraction * n))), n - 1)
                period = float(np.median(np.diff(c[i0:i1 + 1]))) * h
                segs.append(Segment(si, sp.record, sp.role, level, w0, int(c[i0]), int(c[i1 - n_hold]),
                                    int(c[i1]), period, float(ref), n - n_hold, n_hold))
    warnings.extend(skipped)
    if not any(s.cycles_fit > 0 for s in segs):
        raise IdentificationError(
            "no steady cycles to fit (every segment too short, unsteady or held out): each level needs a warm-up "
            f"cycle and at least {min_cycles} steady whole cycles of the stroke (lengthen the steps: mrctl's "
            "inverse.step_s ≥ 4 periods), or lower fit.min_cycles / widen fit.steady_tolerance"
            + "".join(f"\n  {w}" for w in skipped[:5]) + (f"\n  … {len(skipped) - 5} more" if len(skipped) > 5 else ""))
    if transitions:
        warnings.append(f"{transitions} stretch(es) of under {_MIN_LEVEL_S:g} s at one level (transitions between "
                        "steps) left out")
    return segs


def _cluster_levels(segs: list[Segment]) -> dict[float, list[Segment]]:
    levels = sorted({s.level for s in segs})
    scale = max((abs(x) for x in levels), default=1.0) or 1.0
    groups: dict[float, list[Segment]] = {}
    keys: list[float] = []
    for lv in levels:
        if not keys or abs(lv - keys[-1]) > 1e-3 * scale:
            keys.append(lv)
    for s in segs:
        k = min(keys, key=lambda q: abs(q - s.level))
        groups.setdefault(k, []).append(s)
    return groups


def _design(sp: Span, s: Segment, a: int, b: int, use: dict[str, bool], x_hys: float = 0.0) -> np.ndarray | None:
    """The terms the force is linear in, at samples [a, b) of segment s: 1 (offset), x (stiffness),
    and with ``x_hys`` the hysteretic state per direction (from the segment's warm-up cycle)."""
    cols = []
    if use["offset"]:
        cols.append(np.ones(b - a))
    if use["stiffness"] and sp.x is not None:
        cols.append(sp.x[a:b])
    if x_hys > 0.0:
        zp, zn = hys_columns(sp.v[s.w0:b], sp.dt, s.f0 - s.w0, x_hys)
        cols += [zp[a - s.w0:], zn[a - s.w0:]]
    return np.column_stack(cols) if cols else None


#: the hysteretic stiffness's length tried, as multiples of the median stroke amplitude
_XHYS_GRID = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)


def choose_x_hys(spans: list[Span], fits: list[LevelFit], use: dict[str, bool]) -> tuple[float, dict[str, float]]:
    """x_hys for the hysteretic stiffness, one for the set: each level's Θ held at its fit without
    it, the linear terms (offset, stiffness, the two stiffnesses) solved per level, the length of
    the least total squared residual: a grid (:data:`_XHYS_GRID` × the median stroke amplitude),
    then a bounded search between the best point's neighbours. The levels are then fitted again
    with it. Returns it and the sum at each grid point."""
    from scipy.optimize import minimize_scalar

    amp = 0.5 * float(np.median([s.stroke_m for lf in fits for s in lf.segments]))
    held = []  # per level: the segments and the force less the LuGre force of its Θ (independent of x_hys)
    for lf in fits:
        th = np.array([lf.theta[k] for k in THETA_NAMES])
        r = [spans[s.span].F[s.f0:s.f1] - lugre_force(th, spans[s.span].v[s.w0:s.f1], spans[s.span].dt)[s.f0 - s.w0:]
             for s in lf.segments]
        held.append((lf.segments, np.concatenate(r)))

    def sse(xh: float) -> float:
        q = 0.0
        for segs, r in held:
            X = np.vstack([_design(spans[s.span], s, s.f0, s.f1, use, xh) for s in segs])
            res = r - X @ np.linalg.lstsq(X, r, rcond=None)[0]
            q += float(res @ res)
        return q

    grid = [mul * amp for mul in _XHYS_GRID]
    qs = [sse(xh) for xh in grid]
    k = int(np.argmin(qs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    best = minimize_scalar(lambda lx: sse(float(np.exp(lx))), bounds=(np.log(lo), np.log(hi)), method="bounded",
                           options={"xatol": 0.02})
    x_hys = float(np.exp(best.x)) if best.fun < qs[k] else grid[k]
    return x_hys, {f"{xh:.6g}": q for xh, q in zip(grid, qs)}


def fit_levels(spans: list[Span], segs: list[Segment], *, use: dict[str, bool], method: str = "trf",
               bar=None, x_hys: float = 0.0, before: list[LevelFit] | None = None) -> list[LevelFit]:
    """One fit per input level over its segments' fit cycles (``segs`` from
    :func:`find_segments`, which refuses a record with none); with ``x_hys``
    the hysteretic stiffness per direction among the linear terms, and
    ``before`` the same levels' fits without it, each a start beside the
    grid's best."""
    groups = _cluster_levels([s for s in segs if s.cycles_fit > 0])
    fits = []
    for level in sorted(groups):
        t0 = time.perf_counter()
        windows, Xs, Fall, vall, xall = [], [], [], [], []
        for s in groups[level]:
            sp = spans[s.span]
            h = np.full(s.f1 - s.w0, sp.dt)
            windows.append((sp.v[s.w0:s.f1], sp.F[s.w0:s.f1], h, s.f0 - s.w0))
            Xs.append(_design(sp, s, s.f0, s.f1, use, x_hys))
            Fall.append(sp.F[s.f0:s.f1])
            vall.append(sp.v[s.f0:s.f1])
            if sp.x is not None:
                xall.append(sp.x[s.f0:s.f1])
        X = None if Xs[0] is None else np.vstack(Xs)
        prev = None if before is None else next((np.array([f.theta[k] for k in THETA_NAMES]) for f in before
                                                  if f.level == level), None)
        theta, prob, p, _notes, nfev, theta0, _starts = _fit_one_current(windows, method, starts_max=4, X=X,
                                                                         theta_start=prev)
        rec = prob.rec
        Fm = _model_batch(theta[None, :], rec)[0]
        beta = rec.linear_terms(Fm)
        resid = rec.with_terms(Fm) - rec.F
        F = np.concatenate(Fall)
        j = 0
        off = float(beta[j]) if use["offset"] else 0.0
        j += 1 if use["offset"] else 0
        kx = float(beta[j]) if (use["stiffness"] and X is not None and X.shape[1] > j) else 0.0
        kp, kn = (float(beta[-2]), float(beta[-1])) if x_hys > 0.0 else (0.0, 0.0)
        F_lin = F - off - (kx * np.concatenate(xall) if xall and kx else 0.0)
        sup = Support.of(F_lin, np.concatenate(vall), np.concatenate(xall) if xall else None)
        ptp = float(np.ptp(F))
        se, rel_se, sens, corr, det = _identifiability(prob, p, theta, ptp)
        noise = float(np.median([_noise_N(w[1][w[3]:]) for w in windows]))
        fits.append(LevelFit(level, {k: float(theta[i]) for i, k in enumerate(THETA_NAMES)}, off, kx,
                             float(np.sqrt(np.mean(resid * resid)) / ptp), int(F.size),
                             sum(s.cycles_fit for s in groups[level]), sup, nfev, time.perf_counter() - t0,
                             groups[level], noise / ptp, se, rel_se, sens, corr, det,
                             {k: float(theta0[i]) for i, k in enumerate(THETA_NAMES)}, kp, kn))
        if bar is not None:
            bar.update(1, level=f"{level:g}", nrmse=f"{100 * fits[-1].nrmse_fit:.2f}%")
    return fits


def segment_hys(sp: Span, s: Segment, x_hys: float) -> tuple[np.ndarray, np.ndarray]:
    """The hysteretic state's columns over a segment from its warm-up cycle to its end
    (:func:`~mrctl.offline.identify.model.hys_columns`): the same for every prediction of
    the segment at that ``x_hys``, so a caller predicting it many times computes them once."""
    return hys_columns(sp.v[s.w0:s.h1], sp.dt, s.f0 - s.w0, x_hys)


def predict_segment(sp: Span, s: Segment, theta: dict[str, float] | np.ndarray, offset: float, k_x: float,
                    start: int | None = None, hys: tuple[float, float, float] | None = None,
                    hys_cols: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(measured, predicted) force of a segment from ``start`` (default: its held-out part) to its end,
    the model run from the warm-up cycle; ``hys``: (k_hys_pos, k_hys_neg, x_hys) when on, and
    ``hys_cols`` the segment's :func:`segment_hys` at that x_hys when already computed."""
    if isinstance(theta, dict):
        theta = [theta[k] for k in THETA_NAMES]
    a = s.f1 if start is None else start
    F = lugre_force(np.asarray(theta, float), sp.v[s.w0:s.h1], sp.dt)[a - s.w0:]
    F = F + offset + (k_x * sp.x[a:s.h1] if sp.x is not None else 0.0)
    if hys is not None and hys[2] > 0.0:
        zp, zn = hys_cols if hys_cols is not None else segment_hys(sp, s, hys[2])
        F = F + hys[0] * zp[a - s.w0:] + hys[1] * zn[a - s.w0:]
    if not np.all(np.isfinite(F)):  # pragma: no cover - Θ is checked before
        F = np.where(np.isfinite(F), F, math.nan)
    return sp.F[a:s.h1], F
