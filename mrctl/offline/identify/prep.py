"""From records to fit-ready spans: windows, anti-aliased resampling, velocity.

A :class:`Span` is one contiguous stretch of a record at the fit rate with
every signal the fit needs. Choices, documented in docs/identification.md:

- **Windows**: a record's samples inside a ``use`` window (default: all)
  and outside every ``exclude`` window; each contiguous run is a span.
- **Fit rate**: records faster than needed are decimated by the integer
  factor q = floor(rate / target), target = ``resample_hz`` or
  max(20 × motion band, 500 Hz): twenty samples per period of the fastest
  motion, and never so slow that the LuGre transients after a reversal
  vanish between samples. Decimation is anti-aliased (a zero-phase FIR
  low-pass at 0.8 × the new Nyquist frequency, ``scipy.signal.resample_poly``
  with linear edge padding), never plain subsampling. The drive input, often
  a switched command, is averaged over each q samples instead (centred, zero
  phase): a low-pass too, and one that never overshoots the command's range.
- **Velocity from displacement** when none is recorded: a cubic
  Savitzky–Golay differentiator (``scipy.signal.savgol_filter``) at the
  original rate whose window puts its −3 dB cutoff, (p + 1)/(3.2·N − 4.6)·rate
  (Schafer 2011), at 4 × the motion band; odd N ≥ 5.
- **Acceleration** (only for the inertia term): the same differentiator on
  the velocity at the fit rate.
- **Motion band** when not given: the frequency below which 99 % of the
  velocity's power lies (its periodogram).
- **Input**: a negative drive input is read as 0, as the driver's input stage
  (and the simulated bench) clamps it; the count is a warning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrctl.offline.identify.errors import IdentificationError
from mrctl.offline.identify.records import Record

__all__ = ["Span", "prepare", "savgol_window", "motion_band_hz", "fit_rate"]

#: cubic Savitzky–Golay
_SG_ORDER = 3
#: the differentiator's cutoff, as a multiple of the motion band
_SG_CUTOFF_BANDS = 4.0
#: fit rate target: this many samples per period of the fastest motion, at least _MIN_RATE_HZ
_RATE_PER_BAND = 20.0
_MIN_RATE_HZ = 500.0


@dataclass
class Span:
    """A contiguous stretch of one record at the fit rate (SI units)."""

    record: str
    role: str
    t: np.ndarray
    v: np.ndarray
    F: np.ndarray
    x: np.ndarray | None
    u: np.ndarray | None
    a: np.ndarray | None = None  # acceleration (inertia term only)
    level: np.ndarray | None = None  # constant-input level at each sample (NaN = none)

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0]) if self.t.size > 1 else math.nan

    @property
    def n(self) -> int:
        return int(self.t.size)


def savgol_window(rate_hz: float, band_hz: float) -> int:
    """Odd window N ≥ 5 whose cubic Savitzky–Golay cutoff is ~4 × the motion band."""
    fc = min(_SG_CUTOFF_BANDS * band_hz, 0.45 * rate_hz)
    N = ((_SG_ORDER + 1) * rate_hz / fc + 4.6) / 3.2
    N = max(5, int(math.ceil(N)))
    return N if N % 2 else N + 1


def motion_band_hz(v: np.ndarray, rate_hz: float) -> float:
    """Frequency below which 99 % of the velocity's power lies (periodogram)."""
    v = np.asarray(v, float) - np.mean(v)
    if v.size < 16 or not np.any(v):
        return rate_hz / 10.0
    P = np.abs(np.fft.rfft(v * np.hanning(v.size))) ** 2
    f = np.fft.rfftfreq(v.size, 1.0 / rate_hz)
    c = np.cumsum(P)
    k = int(np.searchsorted(c, 0.99 * c[-1]))
    return float(max(f[min(k, f.size - 1)], 2.0 * rate_hz / v.size))


def fit_rate(rate_hz: float, band_hz: float, resample_hz: float | None) -> int:
    """The integer decimation factor q of a record sampled at ``rate_hz``."""
    target = resample_hz if resample_hz is not None else max(_RATE_PER_BAND * band_hz, _MIN_RATE_HZ)
    return max(1, int(math.floor(rate_hz / target * (1 + 1e-9))))


def _decimate(y: np.ndarray, q: int) -> np.ndarray:
    from scipy.signal import resample_poly

    return resample_poly(y, 1, q, padtype="line")


def _decimate_input(u: np.ndarray, q: int) -> np.ndarray:
    """A switched command decimated by a centred moving average over q samples
    (zero phase; a convex combination, so no Gibbs overshoot past the command's range)."""
    w = np.ones(q + 1 - q % 2)
    if q % 2 == 0:
        w[0] = w[-1] = 0.5
    w /= w.sum()
    half = w.size // 2
    padded = np.concatenate((np.full(half, u[0]), u, np.full(half, u[-1])))
    return np.convolve(padded, w, mode="valid")[::q]


def _runs(m: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate(([0], m.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _level_of(rec: Record) -> np.ndarray | None:
    if rec.level is None and not rec.levels:
        return None
    lv = np.full(rec.t.size, np.nan)
    if rec.level is not None:
        lv[:] = rec.level
    for a, b, val in rec.levels:
        lv[(rec.t >= a) & (rec.t < b)] = val
    return lv


#: a record whose input holds still for less than this (s) over most of its samples is not a set of constant levels
_MIN_LEVEL_S = 0.1


def levels_from_input(rec: Record, u: np.ndarray) -> np.ndarray:
    """The constant levels of a staircase input at the record's own rate.

    A stretch holds while the input (a 5-sample running median, so that one
    noisy sample starts nothing) stays within a tolerance of its value at the
    stretch's start: 2 % of the input's range, or 8 × its sample-to-sample
    noise (a measured current), whichever is larger; a drift starts another.
    Each stretch's level is its median; a step's transition samples form
    stretches of their own, too short to hold a cycle. Non-finite samples
    (outside the used windows) have no level. Refuses an input that never
    holds still (a closed-loop run)."""
    from scipy.signal import medfilt

    lv = np.full(u.size, np.nan)
    idx = np.flatnonzero(np.isfinite(u))
    if idx.size == 0:
        return lv
    uf = u[idx]
    d = np.diff(uf)
    noise = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0) if d.size else 0.0
    tol = max(0.02 * float(np.ptp(uf)), 8.0 * noise, 1e-9 * max(1.0, float(np.max(np.abs(uf)))))
    sm = medfilt(uf, 5) if uf.size >= 5 else uf
    cuts = [0]
    ref = float(sm[0])
    for k, x in enumerate(sm.tolist()):  # a new stretch where the input leaves this one's first value
        if abs(x - ref) > tol:
            cuts.append(k)
            ref = x
    edges = np.asarray(cuts + [uf.size])
    lengths = np.diff(edges)
    short = int(lengths[lengths < _MIN_LEVEL_S * rec.fs].sum())
    if edges.size > 3 and short > 0.5 * uf.size:
        raise IdentificationError(
            f"{rec.name}: the input changes {edges.size - 2} times and holds still for less than "
            f"{_MIN_LEVEL_S:g} s over {100 * short / uf.size:.0f} % of the record: constant_input identification "
            "needs steps of constant input (mrctl: the inverse law 'schedule' or 'constant'), not a closed-loop "
            "run; describe such a record as protocol: broadband")
    for a, b in zip(edges[:-1].tolist(), edges[1:].tolist()):
        lv[idx[a:b]] = float(np.median(uf[a:b]))
    return lv


def prepare(records: list[Record], *, band_hz: float | None, resample_hz: float | None, need_accel: bool,
            warnings: list[str], constant_input: bool = False) -> tuple[list[Span], dict]:
    """Spans of every record at the fit rate, and what was done (for the JSON
    summary). ``constant_input``: the levels of a record without ``level``/
    ``levels`` come from its input column, found at its own rate
    (:func:`levels_from_input`) before any decimation blurs the steps."""
    from scipy.signal import savgol_filter

    spans: list[Span] = []
    info: dict = {"records": {}}
    for rec in records:
        warnings.extend(f"{rec.name}: {note}" for note in rec.notes)
        m = rec.kept()
        if not m.any():
            raise IdentificationError(f"{rec.name}: its use/exclude windows leave no samples (record spans "
                                      f"{rec.t[0]:g}–{rec.t[-1]:g} s)")
        fs = rec.fs
        v_all = rec.v
        if v_all is None:
            x = rec.x
            assert x is not None  # the schema asks for displacement when velocity is missing
            band0 = band_hz or motion_band_hz(np.gradient(x[m], 1.0 / fs), fs)
            N = savgol_window(fs, band0)
            if N > x.size:
                raise IdentificationError(f"{rec.name}: {x.size} samples, fewer than the differentiator's "
                                          f"window of {N}")
            v_all = savgol_filter(x, N, _SG_ORDER, deriv=1, delta=1.0 / fs)
            velocity = f"Savitzky-Golay derivative of displacement, cubic, window {N} samples ({N / fs:.3g} s)"
        else:
            velocity = "recorded"
        band = band_hz or motion_band_hz(v_all[m], fs)
        q = fit_rate(fs, band, resample_hz)
        lv = _level_of(rec)
        u = rec.u
        if u is not None and np.any(u < 0.0):
            warnings.append(f"{rec.name}: {int(np.count_nonzero(u < 0.0))} negative input sample(s) (min "
                            f"{u.min():.3g}) read as 0, as the driver clamps them")
            u = np.maximum(u, 0.0)
        if lv is None and constant_input and u is not None:
            lv = levels_from_input(rec, u)
        info["records"][rec.name] = {"rate_hz": fs, "fit_rate_hz": fs / q, "decimation": q,
                                     "motion_band_hz": band, "velocity": velocity}
        for a, b in _runs(m):
            if (b - a) < max(8 * q, 4):
                warnings.append(f"{rec.name}: ignored a {(b - a) / fs:.3g} s window at {rec.t[a]:.4g} s (too "
                                "short to fit)")
                continue
            sl = slice(a, b)
            if q > 1:
                t = rec.t[a] + np.arange(int(math.ceil((b - a) / q))) * (q / fs)
                v = _decimate(v_all[sl], q)
                F = _decimate(rec.F[sl], q)
                x = _decimate(rec.x[sl], q) if rec.x is not None else None
                uu = _decimate_input(u[sl], q) if u is not None else None
                lev = lv[sl][::q] if lv is not None else None
            else:
                t, v, F = rec.t[sl].copy(), v_all[sl].copy(), rec.F[sl].copy()
                x = rec.x[sl].copy() if rec.x is not None else None
                uu = u[sl].copy() if u is not None else None
                lev = lv[sl].copy() if lv is not None else None
            n = min(t.size, v.size)
            sp = Span(rec.name, rec.role, t[:n], v[:n], F[:n], None if x is None else x[:n],
                      None if uu is None else np.maximum(uu[:n], 0.0), level=None if lev is None else lev[:n])
            if need_accel:
                N = savgol_window(fs / q, band)
                if N <= sp.n:
                    sp.a = savgol_filter(sp.v, N, _SG_ORDER, deriv=1, delta=q / fs)
                else:
                    sp.a = np.gradient(sp.v, q / fs)
            spans.append(sp)
        if q > 1:
            warnings.append(f"{rec.name}: decimated by {q} to {fs / q:.5g} Hz (anti-aliased)")
    if not spans:
        raise IdentificationError("no usable data: every window is too short")
    return spans, info
