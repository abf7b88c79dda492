"""Output-error fit of the input-dependent laws, offset, stiffness and lag on
broadband or switched-input records.

The whole model (:mod:`.bbmodel`) is simulated over each fit span from the
measured velocity, displacement and commanded input; the residual is the
measured minus the simulated force after a warm-up (:data:`WARMUP_S`, so
z's and the lag's initial states do not bias the fit). The optimiser is
``scipy.optimize.least_squares`` (trust-region reflective) with bounds from
:class:`.guards.Support` in unit-scaled coordinates (logarithmic for the
positive quantities), the Jacobian by forward differences with all columns
simulated in one batch, and a few starts (input lags spread over 2–25 ms:
at τ → 0 the lag's effect is flat, so a start at 0 would stay there).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mrctl.model.params import LuGreParams
from mrctl.offline.identify.bbmodel import (
    IDX,
    LINEAR_IN_F,
    PHYS,
    SpanData,
    felt_input,
    linear_columns,
    simulate,
    to_params,
)
from mrctl.offline.identify.guards import Support
from mrctl.offline.identify.laws import _langevin_np
from mrctl.util.progress import make_bar

__all__ = ["BroadbandFit", "fit_broadband", "predict", "WARMUP_S"]

#: samples at the start of every simulated span left out of objective and scores (s)
WARMUP_S = 0.1
_FD_STEP = 1e-6
_LOG = {"F0", "Ac", "Bc", "sigma0_lo", "sigma0_hi", "sigma2_lo", "sigma2_hi", "Fs_lo", "Fs_hi", "vs_lo", "vs_hi",
        "sigma1_vd", "tau_input_fall", "x_hys"}
#: the parameters each ``use`` flag frees: flag → parameters; without a lag no falling lag either
#: (the rising one's other half)
TERMS = {"offset": ("F_offset",), "stiffness": ("k_x",), "lag": ("tau_input", "tau_input_fall"), "inertia": ("m",)}
#: the optional terms a ``use`` flag frees (docs/identification.md, "Model terms"): flag → parameters
OPTIONAL = {"lag_fall": ("tau_input_fall",), "sigma1_v": ("sigma1_vd",),
            "hysteresis": ("k_hys_pos", "k_hys_neg", "x_hys")}


@dataclass
class BroadbandFit:
    """The fitted parameter vector and how it was obtained."""

    phys: np.ndarray
    params: LuGreParams
    u_lo: float
    u_hi: float
    inertia_kg: float
    cost: float
    nfev: int
    starts: list[dict[str, Any]] = field(default_factory=list)
    time_s: float = 0.0
    at_bound: list[str] = field(default_factory=list)

    @property
    def tau_s(self) -> float:
        return float(self.phys[IDX["tau_input"]])


def warmup_samples(h: float) -> int:
    return max(10, int(round(WARMUP_S / h)))


def _initial(spans: list[SpanData], Fs_: list[np.ndarray], u_lo: float, u_hi: float, tau: float, sup: Support,
             use: dict[str, bool]) -> np.ndarray:
    """A data-derived start: a linear regression of the force on sign(v), v (each
    affine in the lagged input), x and a, then the LuGre quantities from it."""
    rows, ys = [], []
    for sp, F in zip(spans, Fs_):
        ud = felt_input(sp.u, tau, sp.h)
        sg = np.sign(sp.v)
        cols = [np.ones_like(sp.v), sg, ud * sg, sp.v, ud * sp.v]
        cols += [sp.x] if use["stiffness"] else []
        cols += [sp.a] if use["inertia"] else []
        rows.append(np.column_stack(cols))
        ys.append(F)
    A, y = np.vstack(rows), np.concatenate(ys)
    c, *_ = np.linalg.lstsq(A, y, rcond=None)
    du = u_hi - u_lo
    lo_F, hi_F = 0.05 * sup.F_amp, 2.0 * sup.F_amp
    Fc_lo = float(np.clip(c[1] + c[2] * u_lo, lo_F, hi_F))
    Fc_hi = float(np.clip(c[1] + c[2] * u_hi, Fc_lo * 1.05, hi_F * 1.1))
    s2max = 10.0 * sup.F_amp / sup.v_max
    s2_lo = float(np.clip(c[3] + c[4] * u_lo, 0.01 * sup.F_amp / sup.v_max, s2max))
    s2_hi = float(np.clip(c[3] + c[4] * u_hi, 0.01 * sup.F_amp / sup.v_max, s2max))
    p = np.zeros(len(PHYS))
    Bc = du / 3.0
    L2 = float(_langevin_np(np.array([u_hi / Bc]))[0] ** 2 - _langevin_np(np.array([u_lo / Bc]))[0] ** 2)
    p[IDX["F0"]], p[IDX["Ac"]], p[IDX["Bc"]] = Fc_lo, max((Fc_hi - Fc_lo) / max(L2, 1e-6), 1e-3 * sup.F_amp), Bc
    x_amp = sup.x_amp if sup.x_amp is not None else sup.v_max * 0.01
    lam = 3e-3 * x_amp
    for k, lo, hi in (("sigma0", Fc_lo / lam, Fc_hi / lam), ("sigma1", 0.0, 0.0), ("sigma2", s2_lo, s2_hi),
                      ("Fs", Fc_lo, Fc_hi), ("vs", 0.05 * sup.v_max, 0.05 * sup.v_max)):
        p[IDX[k + "_lo"]], p[IDX[k + "_hi"]] = lo, hi
    p[IDX["F_offset"]] = c[0] if use["offset"] else 0.0
    j = 5
    if use["stiffness"]:
        p[IDX["k_x"]] = c[j]
        j += 1
    if use["inertia"]:
        p[IDX["m"]] = c[j]
    p[IDX["tau_input"]] = tau if use["lag"] else 0.0
    if use.get("lag_fall"):
        p[IDX["tau_input_fall"]] = tau  # the fit moves it from the rise's (0 without a lag: fixed there)
    if use.get("sigma1_v"):
        p[IDX["sigma1_vd"]] = 0.5 * sup.v_max
    if use.get("hysteresis"):
        p[IDX["x_hys"]] = 0.2 * x_amp
    return p


def _bounds(sup: Support, du: float, Fmax: float, tau_max: float, a_amp: float) -> dict[str, tuple[float, float]]:
    fl, fh = sup.force_bounds()
    vl, vh = sup.vs_bounds()
    s_v = sup.F_amp / sup.v_max
    x_amp = sup.x_amp if sup.x_amp is not None else sup.v_max * 0.01
    b = {"F0": (fl, fh), "Ac": (1e-6 * sup.F_amp, 5.0 * sup.F_amp), "Bc": (1e-3 * du, 100.0 * du),
         "F_offset": (-3.0 * Fmax, 3.0 * Fmax), "k_x": (-100.0 * sup.F_amp / x_amp, 100.0 * sup.F_amp / x_amp),
         "tau_input": (0.0, tau_max), "m": (-10.0 * sup.F_amp / a_amp, 10.0 * sup.F_amp / a_amp),
         "tau_input_fall": (2e-4, tau_max), "sigma1_vd": (0.01 * sup.v_max, 100.0 * sup.v_max),
         "k_hys_pos": (-100.0 * sup.F_amp / x_amp, 100.0 * sup.F_amp / x_amp),
         "k_hys_neg": (-100.0 * sup.F_amp / x_amp, 100.0 * sup.F_amp / x_amp), "x_hys": (1e-3 * x_amp, 10.0 * x_amp)}
    for e in ("lo", "hi"):
        b[f"sigma0_{e}"] = (1e-2 * sup.F_amp / x_amp, 1.5 * sup.sigma0_max())
        b[f"sigma1_{e}"] = (-100.0 * s_v, 100.0 * s_v)
        b[f"sigma2_{e}"] = (1e-6 * s_v, 20.0 * s_v)
        b[f"Fs_{e}"] = (fl, fh)
        b[f"vs_{e}"] = (vl, vh)
    return b


class _Problem:
    """Residuals over the fit spans in unit-scaled coordinates of the free parameters."""

    def __init__(self, spans, Fs_, warm, p0, free, bounds, u_lo, u_hi, bar):
        self.spans, self.Fs, self.warm = spans, Fs_, warm
        self.p0, self.free, self.u_lo, self.u_hi = p0.copy(), free, u_lo, u_hi
        self.bar = bar
        self.nfev = 0
        self.scale = np.ones(len(free))
        for i, k in enumerate(free):
            if k not in _LOG:
                lo, hi = bounds[k]
                self.scale[i] = 0.01 if k == "tau_input" else max((hi - lo) / 200.0, 1e-12)
        self.lo = np.empty(len(free))
        self.hi = np.empty(len(free))
        for i, k in enumerate(free):
            lo, hi = bounds[k]
            v0 = p0[IDX[k]]
            if k in _LOG:
                self.lo[i], self.hi[i] = math.log(lo / v0), math.log(hi / v0)
            else:
                self.lo[i], self.hi[i] = (lo - v0) / self.scale[i], (hi - v0) / self.scale[i]
        self._cache: tuple[bytes, np.ndarray] | None = None

    def phys(self, Q: np.ndarray) -> np.ndarray:
        Q = np.atleast_2d(Q)
        P = np.repeat(self.p0[None, :], Q.shape[0], axis=0)
        for i, k in enumerate(self.free):
            j = IDX[k]
            P[:, j] = self.p0[j] * np.exp(Q[:, i]) if k in _LOG else self.p0[j] + self.scale[i] * Q[:, i]
        return P

    def residuals(self, Q: np.ndarray, parts: list | None = None) -> np.ndarray:
        P = self.phys(Q)
        self.nfev += P.shape[0]
        out = []
        with np.errstate(all="ignore"):
            for sp, F in zip(self.spans, self.Fs):
                d: dict | None = {} if parts is not None else None
                out.append(simulate(P, sp, self.u_lo, self.u_hi, d)[:, self.warm:] - F[self.warm:])
                if parts is not None:
                    parts.append(d)
        R = np.concatenate(out, axis=1)
        return np.where(np.isfinite(R), R, 1e9)

    def fun(self, q: np.ndarray) -> np.ndarray:
        key = q.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        parts: list = []
        r = self.residuals(q[None, :], parts)[0]
        self._cache = (key, r)
        self._parts = parts
        if self.bar is not None:
            self.bar.update(1, rms=f"{math.sqrt(float(r @ r) / r.size):.4g} N")
        return r

    def jac(self, q: np.ndarray) -> np.ndarray:
        """Forward differences for the parameters z depends on (one batch);
        exact columns for those the force is linear in."""
        r0 = self.fun(q)
        J = np.empty((r0.size, q.size))
        lin = [i for i, k in enumerate(self.free) if k in LINEAR_IN_F]
        nl = [i for i in range(q.size) if i not in lin]
        for i in lin:
            k = self.free[i]
            dth = (self.p0[IDX[k]] * math.exp(q[i])) if k in _LOG else self.scale[i]  # dθ/dq
            J[:, i] = np.concatenate([linear_columns(k, sp, d)[self.warm:]
                                      for sp, d in zip(self.spans, self._parts)]) * dth
        if nl:
            steps = _FD_STEP * np.maximum(1.0, np.abs(q[nl]))
            steps = np.where(q[nl] + steps > self.hi[nl], -steps, steps)  # stay inside the bounds
            Q = np.repeat(q[None, :], len(nl), axis=0)
            Q[np.arange(len(nl)), nl] += steps
            J[:, nl] = ((self.residuals(Q) - r0) / steps[:, None]).T
        return J


def fit_broadband(spans: list[SpanData], Fs_: list[np.ndarray], u_lo: float, u_hi: float, sup: Support, *,
                  use: dict[str, bool], starts: int = 3, max_nfev: int = 60, progress: bool = False,
                  Fmax: float | None = None) -> BroadbandFit:
    """Fit the model to the fit spans (forces ``Fs_``); the best of ``starts`` starts."""
    from scipy.optimize import least_squares

    t0 = time.perf_counter()
    h = spans[0].h
    warm = warmup_samples(h)
    if u_hi - u_lo <= 0.0:
        u_hi = u_lo + 1.0  # one input level: the laws are constants (ends equal)
    Fmax = Fmax if Fmax is not None else float(max(np.max(np.abs(F)) for F in Fs_))
    dur = min(sp.v.size for sp in spans) * h
    a_amp = max(float(max(np.percentile(np.abs(sp.a), 99.5) for sp in spans)), 1e-9)
    bounds = _bounds(sup, u_hi - u_lo, Fmax, min(0.2, dur / 10.0), a_amp)
    fixed = ({"tau_field"}  # never
             | {k for flag, names in TERMS.items() if not use[flag] for k in names}
             | {k for flag, names in OPTIONAL.items() if not use.get(flag) for k in names})
    free = [k for k in PHYS if k not in fixed]
    taus = np.geomspace(2e-3, 25e-3, starts) if use["lag"] and starts > 1 else np.array([8e-3 if use["lag"] else 0.0])
    taus = np.resize(taus, starts)
    bar = make_bar(starts * max_nfev, "identify (broadband)", enabled=progress)
    best: BroadbandFit | None = None
    info = []
    total = 0
    for i in range(starts):
        p0 = _initial(spans, Fs_, u_lo, u_hi, float(taus[i]), sup, use)
        if not use["lag"] and starts > 1:
            p0[IDX["sigma0_lo"]] *= 10.0 ** (i - starts // 2)
            p0[IDX["sigma0_hi"]] *= 10.0 ** (i - starts // 2)
        for k in free:  # the start inside the bounds
            lo, hi = bounds[k]
            p0[IDX[k]] = float(np.clip(p0[IDX[k]], lo + 1e-9 * abs(lo) if k in _LOG else lo,
                                       hi - 1e-9 * abs(hi) if k in _LOG else hi))
        prob = _Problem(spans, Fs_, warm, p0, free, bounds, u_lo, u_hi, bar)
        q0 = np.clip(np.zeros(len(free)), prob.lo + 1e-12, prob.hi - 1e-12)
        res = least_squares(prob.fun, q0, jac=prob.jac, bounds=(prob.lo, prob.hi), method="trf", x_scale=1.0,
                            xtol=1e-8, ftol=1e-8, gtol=1e-8, max_nfev=max_nfev)
        bar.update(max(0, (i + 1) * max_nfev - bar.n))
        total += prob.nfev
        p = prob.phys(res.x)[0]
        cost = float(res.fun @ res.fun)
        info.append({"tau0_s": float(taus[i]), "cost": cost, "nfev": int(res.nfev), "tau_s": float(p[IDX["tau_input"]]),
                     "status": int(res.status)})
        if best is None or cost < best.cost:
            tol = 1e-3
            at = [k for i_, k in enumerate(free)
                  if res.x[i_] - prob.lo[i_] < tol * max(1.0, abs(prob.lo[i_]))
                  or prob.hi[i_] - res.x[i_] < tol * max(1.0, abs(prob.hi[i_]))]
            best = BroadbandFit(p, to_params(p, u_lo, u_hi), u_lo, u_hi, float(p[IDX["m"]]), cost, 0, at_bound=at)
    bar.close()
    assert best is not None
    best.nfev, best.starts, best.time_s = total, info, time.perf_counter() - t0
    return best


def predict(fit_or_phys: BroadbandFit | np.ndarray, sp: SpanData, u_lo: float | None = None,
            u_hi: float | None = None) -> np.ndarray:
    """The model's force over one span (N)."""
    if isinstance(fit_or_phys, BroadbandFit):
        P, u_lo, u_hi = fit_or_phys.phys, fit_or_phys.u_lo, fit_or_phys.u_hi
    else:
        P = fit_or_phys
    with np.errstate(all="ignore"):
        return simulate(P[None, :], sp, float(u_lo), float(u_hi))[0]
