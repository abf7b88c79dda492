"""A run's figures accumulated block by block, so nothing needs the whole run in memory.

``mrctl simulate`` streams: its loop runs in blocks of ticks, and each block
goes to the run log and to these accumulators, then is dropped. Each
figure is the one :mod:`mrctl.runlog.metrics` (tracking), :mod:`mrctl.runlog.ride`
(quarter car) and :func:`mrctl.runlog.acceptance.row_figures` (the verdict's
row figures) compute from whole columns, with the same definitions:

- maxima, minima, counts and shares are exact, hence equal;
- sums of squares (the RMS figures) add each block's numpy sum exactly
  (:class:`ExactSum`): a run of one block gives the same float as the
  whole-column function, a longer one agrees to ~1e-15 relative (the
  whole-column sum is numpy's pairwise one), far below any printed digit.

A figure is any object with ``add(block)`` (a mapping of column name to
1-D float arrays, the rows of one block in order) and ``result()`` (a dict
of floats); :class:`FigureSet` feeds several. A new figure is a new class
here, added to the set its command builds (tests/test_blockmetrics.py
checks each against its whole-column definition).
"""

from __future__ import annotations

import math
from typing import Mapping, Protocol, Sequence

import numpy as np

from mrctl.runlog.metrics import _AT_LIMIT_A

Block = Mapping[str, np.ndarray]


class BlockFigure(Protocol):
    def add(self, block: Block) -> None: ...

    def result(self) -> dict[str, float]: ...


class ExactSum:
    """The exactly rounded sum of the floats added (Shewchuk's partials, as
    :func:`math.fsum`), kept in a few floats; ±inf and NaN as float addition has them."""

    __slots__ = ("_partials", "_special")

    def __init__(self) -> None:
        self._partials: list[float] = []
        self._special = 0.0

    def add(self, x: float) -> None:
        if not math.isfinite(x):
            self._special += x
            return
        partials = self._partials
        i = 0
        for y in partials:
            if abs(x) < abs(y):
                x, y = y, x
            hi = x + y
            lo = y - (hi - x)
            if lo:
                partials[i] = lo
                i += 1
            x = hi
        partials[i:] = [x]

    def merge(self, other: ExactSum) -> None:
        """Add everything ``other`` holds (exactly)."""
        for p in other._partials:
            self.add(p)
        self._special += other._special

    def value(self) -> float:
        return self._special if self._special else math.fsum(self._partials)


def _max_nan(a: float, b: float) -> float:
    """max that keeps a NaN, as ``np.max`` does."""
    return math.nan if math.isnan(a) or math.isnan(b) else max(a, b)


class _Stretch:
    """The tracking figures' running parts over one stretch of rows (before
    the window, or in it), mergeable in row order."""

    __slots__ = ("rows", "t_first", "valid", "sq", "f_min", "f_max", "I_first", "I_last", "step", "at_zero",
                 "at_top")

    def __init__(self) -> None:
        self.rows = 0
        self.t_first = math.nan
        self.valid = 0
        self.sq = ExactSum()
        self.f_min = math.inf
        self.f_max = -math.inf
        self.I_first = self.I_last = math.nan
        self.step = -math.inf  # no step yet
        self.at_zero = self.at_top = 0

    def add(self, t: np.ndarray, F_des: np.ndarray, F: np.ndarray, I: np.ndarray, top: float) -> None:
        if not len(t):
            return
        if not self.rows:
            self.t_first = float(t[0])
            self.I_first = float(I[0])
        else:
            self.step = _max_nan(self.step, abs(float(I[0]) - self.I_last))
        if len(I) > 1:
            self.step = _max_nan(self.step, float(np.max(np.abs(np.diff(I)))))
        self.I_last = float(I[-1])
        self.rows += len(t)
        valid = np.isfinite(F) & np.isfinite(F_des)
        n = int(np.count_nonzero(valid))
        if n:
            e = F[valid] - F_des[valid]
            self.sq.add(float(np.add.reduce(e * e)))
            fd = F_des[valid]
            self.f_min = min(self.f_min, float(np.min(fd)))
            self.f_max = max(self.f_max, float(np.max(fd)))
            self.valid += n
        self.at_zero += int(np.count_nonzero(I <= _AT_LIMIT_A))
        self.at_top += int(np.count_nonzero(I >= top - _AT_LIMIT_A))

    def then(self, later: _Stretch) -> _Stretch:
        """This stretch followed by ``later``."""
        if not later.rows:
            return self
        if not self.rows:
            return later
        out = _Stretch()
        out.rows = self.rows + later.rows
        out.t_first = self.t_first
        out.valid = self.valid + later.valid
        out.sq.merge(self.sq)
        out.sq.merge(later.sq)
        out.f_min, out.f_max = min(self.f_min, later.f_min), max(self.f_max, later.f_max)
        out.I_first, out.I_last = self.I_first, later.I_last
        out.step = _max_nan(_max_nan(self.step, later.step), abs(later.I_first - self.I_last))
        out.at_zero, out.at_top = self.at_zero + later.at_zero, self.at_top + later.at_top
        return out


class _Window:
    """Splits each block at the settling window: rows with t ≥ t[0] + settle_s
    (t[0]: the run's first row), as the whole-column figures do."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = float(settle_s)
        self.start: float | None = None

    def mask(self, t: np.ndarray) -> np.ndarray:
        if self.start is None:
            self.start = float(t[0]) + self.settle_s
        return t >= self.start


class TrackingFigures:
    """:func:`mrctl.runlog.metrics.tracking_summary`, block by block: force
    RMSE and NRMSE, the largest current step, the shares at 0 A and at
    ``I_max``, over the settling window (the whole run if that leaves < 2
    rows). ``force``, ``demand``, ``current``: the column names."""

    def __init__(self, settle_s: float, I_max: float, force: str = "F", demand: str = "F_des",
                 current: str = "I") -> None:
        self.I_max = float(I_max)
        self.names = ("t", demand, force, current)
        self._window = _Window(settle_s)
        self._before = _Stretch()
        self._in = _Stretch()

    def add(self, block: Block) -> None:
        t, F_des, F, I = (np.asarray(block[c], float) for c in self.names)
        if not len(t):
            return
        m = self._window.mask(t)
        if m.all():
            self._in.add(t, F_des, F, I, self.I_max)
            return
        if m.any():  # the block the window starts in
            self._before.add(t[~m], F_des[~m], F[~m], I[~m], self.I_max)
            self._in.add(t[m], F_des[m], F[m], I[m], self.I_max)
            return
        self._before.add(t, F_des, F, I, self.I_max)

    def result(self) -> dict[str, float]:
        s = self._in if self._in.rows >= 2 else self._before.then(self._in)
        if s.valid >= 2:
            rmse = float(math.sqrt(s.sq.value() / s.valid))
            p2p = s.f_max - s.f_min
            nrmse = rmse / p2p if p2p > 0 else math.nan
        else:
            rmse = nrmse = math.nan
        return {
            "window_start_s": s.t_first,
            "window_ticks": float(s.rows),
            "force_rmse_N": rmse,
            "force_nrmse": nrmse,
            "max_current_step_A": s.step if s.rows > 1 else 0.0,
            "share_at_zero": s.at_zero / s.rows if s.rows else math.nan,
            "share_at_I_max": s.at_top / s.rows if s.rows else math.nan,
        }


class _Squares:
    """Sum of squares and count of the finite values of one column."""

    __slots__ = ("sq", "n")

    def __init__(self) -> None:
        self.sq = ExactSum()
        self.n = 0

    def add(self, a: np.ndarray) -> None:
        a = a[np.isfinite(a)]
        if a.size:
            self.sq.add(float(np.add.reduce(a * a)))
            self.n += a.size

    def rms(self) -> float:
        return float(math.sqrt(self.sq.value() / self.n)) if self.n else math.nan


class RideFigures:
    """:func:`mrctl.runlog.ride.ride_summary`, block by block: RMS body
    acceleration, tyre deflection and stroke over the settling window."""

    KEYS = (("rms_a_sprung_mps2", "a_sprung"), ("rms_tyre_defl_m", "tyre_defl"), ("rms_stroke_m", "x"))

    def __init__(self, settle_s: float) -> None:
        self._window = _Window(settle_s)
        self._rows = [0, 0]  # before, in the window
        self._parts = [[_Squares() for _ in self.KEYS] for _ in range(2)]

    def add(self, block: Block) -> None:
        t = np.asarray(block["t"], float)
        if not len(t):
            return
        m = self._window.mask(t)
        for side, rows in ((1, m), (0, ~m)):
            n = int(np.count_nonzero(rows))
            if n:
                self._rows[side] += n
                for part, (_, col) in zip(self._parts[side], self.KEYS):
                    part.add(np.asarray(block[col], float)[rows])

    def result(self) -> dict[str, float]:
        if self._rows[1] >= 2:
            return {key: part.rms() for part, (key, _) in zip(self._parts[1], self.KEYS)}
        out = {}
        for i, (key, _) in enumerate(self.KEYS):
            both = _Squares()
            for side in (0, 1):
                both.sq.merge(self._parts[side][i].sq)
                both.n += self._parts[side][i].n
            out[key] = both.rms()
        return out


class RowFigures:
    """:func:`mrctl.runlog.acceptance.row_figures`, block by block: the share
    of rows in fault, the longest forced-0 A stretch and the longest gap
    between logged ticks (s). ``x``: the column whose NaN means no usable
    sample; ``fault``, ``k``: the fault bits and tick index columns (None:
    no fault bits, every row fault-free; consecutive ticks from 0, as
    offline)."""

    def __init__(self, dt_s: float, x: str = "x", fault: str | None = "fault", k: str | None = "k") -> None:
        self.dt_s = float(dt_s)
        self.names = (x, fault, k)
        self.rows = 0
        self.in_fault = 0
        self.longest = 0.0  # ticks
        self.gap = -math.inf
        self._open: float | None = None  # k of the first row of a forced-0 A stretch still open
        self._last_k = math.nan

    def add(self, block: Block) -> None:
        xc, fc, kc = self.names
        x = np.asarray(block[xc], float)
        if not len(x):
            return
        k = np.asarray(block[kc], float) if kc is not None else np.arange(self.rows, self.rows + len(x), dtype=float)
        if fc is not None:
            f = np.asarray(block[fc], float)
            faulted = np.isfinite(f) & (f != 0)
        else:
            faulted = np.zeros(len(x), bool)
        self.in_fault += int(np.count_nonzero(faulted))
        zero = ~np.isfinite(x) | faulted
        d = np.diff(np.concatenate(([1 if self._open is not None else 0], zero.view(np.int8))))
        starts = k[np.flatnonzero(d == 1)]
        if self._open is not None:
            starts = np.concatenate(([self._open], starts))
        stops = k[np.flatnonzero(d == -1)]  # a stretch lasts until the next row that is not in it
        if len(stops):
            self.longest = max(self.longest, float(np.max(stops - starts[: len(stops)])))
        self._open = float(starts[len(stops)]) if len(starts) > len(stops) else None
        steps = np.diff(k) if not self.rows else np.diff(np.concatenate(([self._last_k], k)))
        if len(steps):
            self.gap = _max_nan(self.gap, float(np.max(steps)))
        self._last_k = float(k[-1])
        self.rows += len(k)

    def result(self) -> dict[str, float]:
        if not self.rows:
            return {}
        longest = self.longest
        if self._open is not None:  # open at the run's end: it lasted until the tick after the last
            longest = max(longest, self._last_k + 1 - self._open)
        out = {"fault_share": self.in_fault / self.rows, "longest_zero_stretch_s": longest * self.dt_s}
        if self.rows > 1:
            out["longest_gap_s"] = self.gap * self.dt_s
        return out


class LoadCellFigures:
    """:func:`mrctl.runlog.metrics.load_cell_offset` on a simulated bench,
    block by block: the mean of the load cell's reading (``reading``, the
    force of the tick before) against the plant's ``force``, and that as a
    share of the demanded force's range (every row)."""

    def __init__(self, force: str = "F", reading: str = "F_rx", demand: str = "F_des") -> None:
        self.names = (force, reading, demand)
        self.sum = ExactSum()
        self.n = 0
        self.d_min = math.inf
        self.d_max = -math.inf
        self._prev = math.nan  # the last force of the block before

    def add(self, block: Block) -> None:
        F, R, D = (np.asarray(block[c], float) for c in self.names)
        if not len(F):
            return
        e = R - np.concatenate(([self._prev], F[:-1]))
        ok = np.isfinite(e)
        if ok.any():
            self.sum.add(float(np.add.reduce(e[ok])))
            self.n += int(np.count_nonzero(ok))
        d = D[np.isfinite(D)]
        if len(d):
            self.d_min, self.d_max = min(self.d_min, float(np.min(d))), max(self.d_max, float(np.max(d)))
        self._prev = float(F[-1])

    def result(self) -> dict[str, float]:
        if self.n < 2:
            return {}
        off = self.sum.value() / self.n
        p2p = self.d_max - self.d_min
        return {"load_cell_offset_N": off, "load_cell_offset": abs(off) / p2p if p2p > 0 else math.nan}


class FigureSet:
    """Several figures fed the same blocks; their results in one dict (later ones win a shared key)."""

    def __init__(self, figures: Sequence[BlockFigure]) -> None:
        self.figures = list(figures)

    def add(self, block: Block) -> None:
        for f in self.figures:
            f.add(block)

    def result(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for f in self.figures:
            out.update(f.result())
        return out
