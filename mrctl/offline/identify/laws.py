"""The approximating laws (6)–(11) fitted to the per-current values of Θ.

Eq (6), Fc = Ac·(coth(I/Bc) − Bc/I)² + F0, by variable projection on Bc
(for a given Bc, Ac and F0 are linear); the linear laws (7)–(11) by ordinary
least squares. The result is the 13-constant :class:`LuGreParams` the
daemon's laws use, and a :class:`LawFit` per law saying how well it fits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from dataclasses import replace

from mrctl.model.params import _LANGEVIN_SERIES_BELOW, TABLE_NAMES, LuGreParams, ThetaTable
from mrctl.offline.identify.errors import IdentificationError

__all__ = ["LawFit", "fit_laws", "theta_from_params", "table_set", "bench_at", "hys_at"]


@dataclass
class LawFit:
    """One approximating law fitted to the per-current values."""

    name: str  # the Θ entry (Fc, sigma0, …)
    equation: str
    coefficients: dict[str, float]
    rms: float  # RMS residual (unit of the parameter)
    rel_rms: float  # rms / mean |value|
    max_abs: float
    r2: float


def _langevin_np(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, float)
    out = np.empty_like(x)
    small = np.abs(x) < _LANGEVIN_SERIES_BELOW
    xs = x[small]
    x2 = xs * xs
    out[small] = xs * (1.0 / 3.0 + x2 * (-1.0 / 45.0 + x2 * (2.0 / 945.0 - x2 / 4725.0)))
    xl = x[~small]
    out[~small] = 1.0 / np.tanh(xl) - 1.0 / xl
    return out


def _fit_Fc_law(I: np.ndarray, Fc: np.ndarray, F0_fixed: float | None = None,
                F0_min: float | None = None) -> tuple[float, float, float]:
    """(Ac, Bc, F0) of eq (6) by variable projection: for each Bc, Ac and F0 are
    linear. With ``F0_min``, bounded: Ac ≥ 0 and F0 ≥ F0_min, so Fc ≥ F0_min
    at every input (the squared Langevin function is ≥ 0)."""
    from scipy.optimize import lsq_linear, minimize_scalar

    def solve(Bc: float) -> tuple[float, float, float]:
        L2 = _langevin_np(I / Bc) ** 2
        if F0_fixed is None:
            A = np.column_stack([L2, np.ones_like(L2)])
            (Ac, F0), *_ = np.linalg.lstsq(A, Fc, rcond=None)
            if F0_min is not None and (Ac < 0.0 or F0 < F0_min):
                Ac, F0 = lsq_linear(A, Fc, bounds=([0.0, F0_min], [np.inf, np.inf])).x
        else:
            y = Fc - F0_fixed
            Ac = float(L2 @ y / (L2 @ L2)) if L2 @ L2 > 0 else 0.0
            F0 = F0_fixed
        r = Fc - (Ac * L2 + F0)
        return float(r @ r), float(Ac), float(F0)

    Imax = float(np.max(I))
    grid = np.geomspace(max(Imax, 1e-3) * 1e-3, max(Imax, 1e-3) * 100.0, 121)
    qs = [solve(b)[0] for b in grid]
    k = int(np.argmin(qs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    if hi > lo:
        res = minimize_scalar(lambda lb: solve(math.exp(lb))[0], bounds=(math.log(lo), math.log(hi)),
                              method="bounded", options={"xatol": 1e-10})
        Bc = math.exp(res.x) if res.fun <= qs[k] else float(grid[k])
    else:  # pragma: no cover
        Bc = float(grid[k])
    _, Ac, F0 = solve(Bc)
    return Ac, Bc, F0


def _law_stats(name: str, eq: str, coefs: dict[str, float], y: np.ndarray, yhat: np.ndarray) -> LawFit:
    r = y - yhat
    rms = float(np.sqrt(np.mean(r * r)))
    ss = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(r @ r) / ss if ss > 0 else math.nan
    mean_abs = float(np.mean(np.abs(y)))
    return LawFit(name, eq, coefs, rms, rms / mean_abs if mean_abs > 0 else math.nan,
                  float(np.max(np.abs(r))), r2)


_LINEAR_LAWS = (("sigma0", "sigma0A", "sigma0B", "(7)"), ("sigma1", "sigma1A", "sigma1B", "(8)"),
                ("sigma2", "sigma2A", "sigma2B", "(9)"), ("Fs", "FsA", "FsB", "(10)"),
                ("vs", "vsA", "vsB", "(11)"))


def _linear_law(I: np.ndarray, y: np.ndarray, lower: float | None) -> tuple[float, float]:
    """(A, B) of y ≈ A·I + B; with ``lower``, bounded so that the law is ≥ lower
    at both ends of [min I, max I], hence everywhere between (it is linear)."""
    lo, hi = float(I.min()), float(I.max())
    if hi - lo <= 0.0:
        return 0.0, float(np.mean(y))
    (a, b), *_ = np.linalg.lstsq(np.column_stack([I, np.ones_like(I)]), y, rcond=None)
    if lower is None or (a * lo + b >= lower and a * hi + b >= lower):
        return float(a), float(b)
    from scipy.optimize import lsq_linear

    s = (I - lo) / (hi - lo)
    q_lo, q_hi = lsq_linear(np.column_stack([1.0 - s, s]), y, bounds=([lower, lower], [np.inf, np.inf])).x
    a = (q_hi - q_lo) / (hi - lo)
    return float(a), float(q_lo - a * lo)


#: laws kept at or above a floor over the fitted range when bounded (σ1 may change sign)
_FLOORED = {"sigma0", "sigma2", "Fs", "vs"}


def fit_laws(I: np.ndarray, thetas: Mapping[str, np.ndarray], F0: str = "fit",
             floors: Mapping[str, float] | None = None) -> tuple[LuGreParams, dict[str, LawFit]]:
    """Laws (6)–(11) fitted to per-current values (arrays indexed like I).

    ``F0``: "fit" (eq 6's offset fitted with Ac, Bc) or "measured" (F0 pinned
    to the identified Fc at the smallest current, which must be 0 A).
    ``floors``: the least value each of sigma0, sigma2, Fs, vs and Fc may take
    over [min I, max I]; the laws are then fitted within those bounds (the
    unbounded least-squares fit whenever it already stays above them)."""
    I = np.asarray(I, float)
    laws: dict[str, LawFit] = {}
    values: dict[str, float] = {}
    Fc = np.asarray(thetas["Fc"], float)
    F0_fixed = None
    if F0 == "measured":
        k = int(np.argmin(I))
        if I[k] > 1e-9:
            raise IdentificationError("F0 = 'measured' needs a run at 0 A")
        F0_fixed = float(Fc[k])
    if I.size == 1 or float(np.ptp(I)) == 0.0:  # one level: constant laws (valid there only)
        Ac, Bc, F0v = 0.0, 1.0, float(np.mean(Fc))
    else:
        Ac, Bc, F0v = _fit_Fc_law(I, Fc, F0_fixed, None if floors is None else floors.get("Fc"))
    # Table I writes Bc < 0; the square makes its sign irrelevant: keep the paper's
    Bc = -abs(Bc)
    values.update(F0=F0v, Ac=Ac, Bc=Bc)
    p_tmp = LuGreParams(F0=F0v, Ac=Ac, Bc=Bc)
    Fc_hat = np.array([p_tmp.Fc(float(i)) for i in I])
    laws["Fc"] = _law_stats("Fc", "Fc = Ac·(coth(I/Bc) − Bc/I)² + F0   (6)", {"Ac": Ac, "Bc": Bc, "F0": F0v}, Fc, Fc_hat)
    for name, kA, kB, eq in _LINEAR_LAWS:
        y = np.asarray(thetas[name], float)
        a, b = _linear_law(I, y, floors.get(name) if floors is not None and name in _FLOORED else None)
        values[kA], values[kB] = float(a), float(b)
        laws[name] = _law_stats(name, f"{name} = {kA}·I + {kB}   {eq}", {kA: float(a), kB: float(b)}, y, a * I + b)
    return LuGreParams(**values), laws


def theta_from_params(p: LuGreParams, I: float) -> np.ndarray:
    """Θ at current I from a 13-constant parameter set (laws 6–11)."""
    return np.array([p.sigma0(I), p.sigma1(I), p.sigma2(I), p.Fc(I), p.Fs(I), p.vs(I)])



def table_set(params: LuGreParams, levels: np.ndarray, thetas: Mapping[str, np.ndarray],
              offsets: np.ndarray | None = None, k_xs: np.ndarray | None = None,
              k_hys: tuple[np.ndarray, np.ndarray] | None = None) -> LuGreParams:
    """``params`` with ``laws: table``: Θ at each level (ascending), and the
    per-level offset and stiffness when given (both or neither), then the
    per-level hysteretic stiffness per direction (with them), interpolated
    piecewise linearly (:class:`mrctl.model.params.ThetaTable`)."""
    cols = [tuple(float(x) for x in np.asarray(thetas[k], float)) for k in TABLE_NAMES]
    if offsets is not None and k_xs is not None:
        cols += [tuple(float(x) for x in offsets), tuple(float(x) for x in k_xs)]
        if k_hys is not None:
            cols += [tuple(float(x) for x in k_hys[0]), tuple(float(x) for x in k_hys[1])]
    return replace(params, table=ThetaTable(tuple(float(u) for u in levels), tuple(cols)))


def bench_at(p: LuGreParams, level: float) -> tuple[float, float]:
    """(F_offset, k_x) of a set at an input level: a table's per-level terms, or the constants."""
    if p.table is not None and p.table.has_bench():
        return p.table.value(6, level), p.table.value(7, level)
    return p.F_offset, p.k_x


def hys_at(p: LuGreParams, level: float) -> tuple[float, float, float] | None:
    """(k_hys_pos, k_hys_neg, x_hys) of a set at an input level, None without the hysteretic stiffness."""
    if not p.has_hysteresis:
        return None
    if p.table is not None and p.table.has_hys():
        return p.table.value(8, level), p.table.value(9, level), p.x_hys
    return p.k_hys_pos, p.k_hys_neg, p.x_hys
