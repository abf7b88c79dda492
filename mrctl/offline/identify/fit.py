"""The per-current fit of Θ = [σ0, σ1, σ2, Fc, Fs, vs].

Q = Σ (F_meas − F_LuGre(v_meas))² over the fit windows of one current, the
model (:mod:`mrctl.offline.identify.model`) driven by the measured velocity.
Starting values come from the data (:func:`initial_guess`), and a batched
grid of Q over (σ0, σ1) competes with them; the optimiser runs in
unit-scaled coordinates (:class:`_Problem`) from the best distinct starts.
At the optimum, the Jacobian says how well the data determine each
parameter (:func:`_identifiability`).

scipy is imported inside :func:`_optimise` only.
"""

from __future__ import annotations

import math

import numpy as np

from mrctl.offline.identify.model import THETA_NAMES, _model_batch, _Record, _window_record

__all__ = ["METHODS", "DEFAULT_METHOD", "initial_guess"]

#: Θ entries that must stay > 0 (g > 0 and a bounded z need them).
_POSITIVE = (0, 3, 4, 5)

#: Optimisers: "trf" trust-region reflective on log(σ0, Fc, Fs, vs) (positive by
#: construction), "trf-bounds" the same on linearly scaled Θ with bounds > 0,
#: "lm" Levenberg–Marquardt (MINPACK) on log-parameters, "nelder-mead" the
#: paper's fminsearch on Q. Compared in docs/identification.md.
METHODS = ("trf", "trf-bounds", "lm", "nelder-mead")
DEFAULT_METHOD = "trf"
_LINEAR = ("trf-bounds",)

# Relative finite-difference step in the optimiser's (unit-scaled) coordinates.
_FD_STEP = 1e-7


def initial_guess(v: np.ndarray, F: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, dict[str, str]]:
    """Θ0 from the measured loop (whole periods of one current), never from Table I.

    - σ2, Fc: linear fit F = σ2·v + Fc·sign(v) on the high-|v| branches
      (|v| > 0.6·max|v|, where the Stribeck term has died out);
    - Fs: |F| where the velocity crosses zero (z is then still in its
      steady-sliding state, so F = σ0·z = ±g(0) = ±Fs);
    - vs: one-dimensional fit of the Stribeck curve g(v) to sign(v)·(F − σ2·v)
      on the decelerating halves of the loop (z in quasi-steady sliding);
    - σ0: pre-sliding slope dF/dx after each velocity reversal (Δx = ∫v dt),
      where the force has moved a third of its swing; median over reversals;
    - σ1: 0 (small; its sign is not known in advance).
    The pre-sliding slope is crude at low current (a few samples, and σ1·ż
    is of the same size there), so :func:`_fit_one_current` lets a batched
    grid of Q over (σ0, σ1) compete with it.
    Returns Θ0 and a note per parameter saying how it was obtained."""
    notes: dict[str, str] = {}
    vmax = float(np.percentile(np.abs(v), 99.5))
    s = np.sign(v)
    hi = np.abs(v) > 0.6 * vmax
    A = np.column_stack([v[hi], s[hi]])
    (s2, Fc), *_ = np.linalg.lstsq(A, F[hi], rcond=None)
    notes["sigma2"] = notes["Fc"] = "high-|v| branch linear fit"
    if not Fc > 0.0:
        Fc = max(float(np.mean(np.abs(F[hi]))) * 0.5, 1e-3)
        notes["Fc"] = "half the mean |F| on the high-|v| branch (linear fit gave Fc ≤ 0)"
    # reversals: sign changes of v between k−1 and k
    rev = np.flatnonzero((v[:-1] * v[1:] < 0.0) | ((v[:-1] != 0.0) & (v[1:] == 0.0))) + 1
    # (noise may add a close pair of sign changes at a reversal: same F, the median copes)
    Fz: list[float] = []
    for k in rev.tolist():
        v0, v1 = v[k - 1], v[k]
        w = -v0 / (v1 - v0) if v1 != v0 else 0.0
        Fz.append(abs(F[k - 1] + w * (F[k] - F[k - 1])))
    if Fz:
        Fs = float(np.median(Fz))
        notes["Fs"] = f"median |F| at {len(Fz)} velocity reversal(s)"
    else:
        Fs = Fc
        notes["Fs"] = "no velocity reversal: Fs = Fc"
    Fs = float(np.clip(Fs, 0.05 * Fc, 3.0 * Fc))
    # vs: Stribeck curve on decelerating halves (|v| falling)
    dv = np.gradient(v)
    dec = (s * dv < 0.0) & (np.abs(v) < 0.9 * vmax) & (np.abs(v) > 0.02 * vmax)
    vs = 0.3 * vmax
    notes["vs"] = "0.3·max|v| (no Stribeck curve visible)"
    if np.count_nonzero(dec) >= 10 and abs(Fs - Fc) > 0.05 * Fc:
        gobs = s[dec] * (F[dec] - s2 * v[dec])
        u2 = v[dec] ** 2
        best = (math.inf, vs)
        for cand in np.geomspace(0.01 * vmax, 1.5 * vmax, 60):
            r = gobs - (Fc + (Fs - Fc) * np.exp(-u2 / (cand * cand)))
            q = float(r @ r)
            if q < best[0]:
                best = (q, float(cand))
        vs = best[1]
        notes["vs"] = "Stribeck-curve fit on the decelerating branches"
    # σ0: pre-sliding slope dF/dx after each reversal, taken where the force
    # has moved a third of the way to the opposite plateau (median over reversals)
    swing = Fs + Fc
    slopes: list[float] = []
    n = v.size
    max_len = max(int(0.05 * n), 5)
    for k in rev.tolist():
        Fr = F[k - 1]
        xr = 0.0
        for j in range(k, min(k + max_len, n)):
            xr += 0.5 * (v[j] + v[j - 1]) * h[j]
            if v[j] * v[k] <= 0.0:
                break
            if abs(F[j] - Fr) > swing / 3.0:
                if xr != 0.0:
                    slopes.append((F[j] - Fr) / xr)
                break
    s0 = float(np.median(slopes)) if slopes else math.nan
    notes["sigma0"] = f"pre-sliding slope dF/dx after {len(slopes)} reversal(s)"
    if not (math.isfinite(s0) and s0 > 0.0):
        # z must swing by ~(Fs + Fc)/σ0 while x moves through the pre-sliding
        # zone; take that zone as 1 % of the stroke
        stroke = float(np.sum(np.abs(v) * h)) / max(len(rev), 1)
        s0 = swing / max(0.01 * stroke, 1e-9)
        notes["sigma0"] = "(Fs + Fc) / (1 % of the stroke) (pre-sliding slope not measurable)"
    notes["sigma1"] = "0 (unknown sign)"
    return np.array([s0, 0.0, float(s2), float(Fc), Fs, vs]), notes


class _Problem:
    """Residuals in unit-scaled coordinates p, with a batched FD Jacobian.

    Coordinates: log(θ/θ0) for σ0, Fc, Fs, vs (positive by construction, no
    bounds needed), (θ − θ0)/scale for σ1 and σ2 with scale = Fc0/max|v| (the
    damper's natural damping). ``linear=True`` instead uses θ/θ0 for the
    positive four, for the bounded trust-region method ("trf-bounds")."""

    def __init__(self, rec: _Record, theta0: np.ndarray, vmax: float, linear: bool = False) -> None:
        self.rec = rec
        self.theta0 = theta0.copy()
        self.dscale = max(theta0[3] / max(vmax, 1e-9), 1e-6)
        self.linear = linear
        self.nfev = 0
        self._cache: tuple[bytes, np.ndarray] | None = None

    def theta(self, p: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(p)
        th = np.empty_like(p)
        t0 = self.theta0
        for j in range(6):
            if j in _POSITIVE:
                th[:, j] = t0[j] * (p[:, j] if self.linear else np.exp(p[:, j]))
            else:
                th[:, j] = t0[j] + self.dscale * p[:, j]
        return th

    def p_of(self, theta: np.ndarray) -> np.ndarray:
        t0 = self.theta0
        p = np.empty(6)
        for j in range(6):
            if j in _POSITIVE:
                p[j] = theta[j] / t0[j] if self.linear else math.log(theta[j] / t0[j])
            else:
                p[j] = (theta[j] - t0[j]) / self.dscale
        return p

    def p_start(self) -> np.ndarray:
        return self.p_of(self.theta0)

    def residuals_batch(self, P: np.ndarray) -> np.ndarray:
        self.nfev += P.shape[0]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            R = self.rec.project(_model_batch(self.theta(P), self.rec) - self.rec.F)
        return np.where(np.isfinite(R), R, 1e6)

    def fun(self, p: np.ndarray) -> np.ndarray:
        key = p.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        r = self.residuals_batch(p[None, :])[0]
        self._cache = (key, r)
        return r

    def jac(self, p: np.ndarray) -> np.ndarray:
        """Forward differences, all six perturbed models in one batch."""
        r0 = self.fun(p)
        steps = _FD_STEP * np.maximum(1.0, np.abs(p))
        P = np.repeat(p[None, :], 6, axis=0)
        P[np.arange(6), np.arange(6)] += steps
        R = self.residuals_batch(P)
        return ((R - r0) / steps[:, None]).T

    def cost(self, p: np.ndarray) -> float:
        r = self.fun(p)
        return float(r @ r)


def _optimise(prob: _Problem, method: str, max_nfev: int | None = None) -> tuple[np.ndarray, int]:
    from scipy.optimize import least_squares, minimize

    p0 = prob.p_start()
    if method == "lm":
        res = least_squares(prob.fun, p0, jac=prob.jac, method="lm", x_scale=1.0,
                            xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=max_nfev or 400)
        return res.x, prob.nfev
    if method == "trf":
        res = least_squares(prob.fun, p0, jac=prob.jac, method="trf", x_scale=1.0,
                            xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=max_nfev or 400)
        return res.x, prob.nfev
    if method == "trf-bounds":
        lo = np.full(6, -np.inf)
        for j in _POSITIVE:
            lo[j] = 1e-6  # θ/θ0 > 0
        res = least_squares(prob.fun, p0, jac=prob.jac, method="trf", bounds=(lo, np.full(6, np.inf)),
                            x_scale=1.0, xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=max_nfev or 400)
        return res.x, prob.nfev
    if method == "nelder-mead":
        res = minimize(prob.cost, p0, method="Nelder-Mead",
                       options={"xatol": 1e-6, "fatol": 1e-10 * max(prob.cost(p0), 1e-300),
                                "maxfev": max_nfev or 6000, "adaptive": False})
        return res.x, prob.nfev
    raise ValueError(f"unknown method {method!r} (one of {', '.join(METHODS)})")


def _noise_N(F: np.ndarray) -> float:
    """Sensor noise σ (N) from the median absolute second difference (robust
    to the few fast pre-sliding transitions): var(Δ²F) = 6σ² for white noise."""
    if F.size < 5:
        return 0.0
    d2 = F[2:] - 2.0 * F[1:-1] + F[:-2]
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _identifiability(prob: _Problem, p: np.ndarray, theta: np.ndarray, ptp: float):
    """How well the data determine each parameter, from the Jacobian at the optimum.

    Returns (se, rel_se, sens, corr, determined):
    - se: standard errors, s²·(JᵀJ)⁻¹ with s² = Q/(N − 6) (white sensor noise;
      coloured noise or model error make them optimistic);
    - rel_se = se/|θ|;
    - sens: the relative change of θ_i that, with the other five re-fitted,
      changes the model force by 1 % of its peak-to-peak (RMS) — a property
      of model and excitation only, independent of the noise;
    - corr: the correlation matrix of the estimates;
    - determined: "well" if rel_se < 5 % (95 % interval within ±10 %) and
      sens < 100 % (a 1 % model error cannot move it by its own size), else "poor".
    """
    J = prob.jac(p)
    r = prob.fun(p)
    dth = np.empty(6)  # dθ/dp, to express J per physical unit: J_θ = J_p / (dθ/dp)
    for j in range(6):
        if j in _POSITIVE:
            dth[j] = prob.theta0[j] if prob.linear else theta[j]
        else:
            dth[j] = prob.dscale
    Jt = J / dth[None, :]
    N = r.size
    Q = float(r @ r)
    s2 = Q / max(N - 6 - (0 if prob.rec.X is None else prob.rec.X.shape[1]), 1)
    col = np.linalg.norm(Jt, axis=0)  # scale columns first: σ0 ~ 1e5 next to vs ~ 1e-2
    col[col == 0.0] = 1.0
    Js = Jt / col
    C = np.linalg.pinv(Js.T @ Js, rcond=1e-13) / np.outer(col, col)
    diag = np.clip(np.diag(C), 0.0, None)
    se = np.sqrt(s2 * diag)
    # best-compensated model change for Δθ_i: ||J δ|| = |Δθ_i| / sqrt(C_ii)
    dtheta_1pct = 0.01 * ptp * math.sqrt(N) * np.sqrt(diag)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.nan_to_num(C / np.sqrt(np.outer(diag, diag)), nan=0.0)
        rel = se / np.abs(theta)
        sens = dtheta_1pct / np.abs(theta)
    names = THETA_NAMES
    se_d = {k: float(se[j]) for j, k in enumerate(names)}
    rel_d = {k: float(rel[j]) for j, k in enumerate(names)}
    sens_d = {k: float(sens[j]) for j, k in enumerate(names)}
    det = {k: ("well" if rel_d[k] < _WELL_REL_SE and sens_d[k] < _WELL_SENS else "poor") for k in names}
    return se_d, rel_d, sens_d, [[float(round(x, 3)) for x in row] for row in corr], det


#: A parameter is "well determined" at one current if its relative standard
#: error is below _WELL_REL_SE (95 % interval within about ±10 %) and its
#: 1 % sensitivity below _WELL_SENS (a model error of 1 % of the force's
#: peak-to-peak cannot shift it by as much as its own value).
_WELL_REL_SE = 0.05
_WELL_SENS = 1.0


#: Grid for the σ0, σ1 starting values: pre-sliding lengths λ = Fc/σ0 as a
#: fraction of the stroke amplitude, and σ1 in units of Fc/max|v|.
_GRID_LAMBDA = np.geomspace(1e-4, 0.3, 16)
_GRID_SIGMA1 = (-10.0, -3.0, -1.0, 0.0, 1.0, 3.0)


#: Stribeck velocities tried with the grid, as multiples of the data-derived
#: start: the decelerating-branch estimate can be far too large when the
#: Stribeck peak rises above Fc, and from there the fit slides into a
#: degenerate basin (vs above the stroke's velocities, Fc traded against σ2).
_GRID_VS = (1.0, 0.3, 0.1)


def _grid_starts(rec: _Record, theta0: np.ndarray, vmax: float, amp: float, k: int = 2) -> list[np.ndarray]:
    """The k best (σ0, σ1, vs) of a batched grid of Q, the other three at their
    data-derived starting values; the slope-based σ0 (with σ1 = 0) competes."""
    scale = theta0[3] / max(vmax, 1e-9)
    cands = [theta0.copy()]
    for vs_mul in _GRID_VS:
        for lam in _GRID_LAMBDA:
            for s1 in _GRID_SIGMA1:
                th = theta0.copy()
                th[0] = theta0[3] / (lam * amp)
                th[1] = s1 * scale
                th[5] = theta0[5] * vs_mul
                cands.append(th)
    P = np.array(cands)
    with np.errstate(all="ignore"):
        R = rec.project(_model_batch(P, rec) - rec.F)
    q = np.where(np.isfinite(R).all(axis=1), np.einsum("ij,ij->i", R, R), np.inf)
    order = np.argsort(q)
    out: list[np.ndarray] = []
    for i in order.tolist():
        # distinct basins: skip candidates next to one already taken
        if all(abs(math.log(P[i, 0] / o[0])) > 1.0 or abs(P[i, 1] - o[1]) > 1.5 * scale
               or abs(math.log(P[i, 5] / o[5])) > 1.0 for o in out):
            out.append(P[i])
        if len(out) == k:
            break
    return out


def _fit_one_current(windows, method: str, starts_max: int = 2, X: np.ndarray | None = None,
                     theta_start: np.ndarray | None = None):
    """Fit Θ at one current over its windows: data-derived start, the
    ``starts_max`` best distinct (σ0, σ1) grid points, one optimiser run from
    each, the lowest Q kept. ``X``: linear terms at the fit samples (offset,
    stiffness), solved exactly for every Θ. ``theta_start`` (a fit of the same
    level with fewer linear terms) competes with the grid's best as a start.
    Returns (θ, problem, p, notes, nfev, θ0, starts)."""
    rec = _window_record(windows, X)
    vf, Ff = rec.v[rec.fit], rec.F
    hf = rec.h[rec.fit]
    if X is not None:  # the start on the force without its linear terms (regressed with the branches)
        A = np.column_stack([X, vf, np.sign(vf)])
        beta = np.linalg.lstsq(A, Ff, rcond=None)[0][:X.shape[1]]
        Ff = Ff - X @ beta
    theta0, notes = initial_guess(vf, Ff, hf)
    vmax = float(np.percentile(np.abs(vf), 99.5))
    amp = 0.5 * float(np.ptp(np.cumsum(vf * hf)))  # stroke amplitude from ∫v dt
    starts = _grid_starts(rec, theta0, vmax, max(amp, 1e-9), starts_max)
    if theta_start is not None:  # the level's fit of before, and the grid's best
        starts = [np.asarray(theta_start, float), starts[0]]
    if starts[0][0] != theta0[0] or starts[0][1] != theta0[1]:
        notes["sigma0"] = (f"best of a Q grid (pre-sliding length Fc/σ0 = 1e-4…0.3 × stroke); "
                           f"slope estimate was {theta0[0]:.4g}")
        notes["sigma1"] = "best of a Q grid (0, ±1, ±3, −10 × Fc/max|v|)"
    if starts[0][5] != theta0[5]:
        notes["vs"] += f"; {starts[0][5] / theta0[5]:.1f} × that, the best of a Q grid"
    linear = method in _LINEAR
    best = None
    total_nfev = len(_GRID_VS) * len(_GRID_LAMBDA) * len(_GRID_SIGMA1) + 1
    for th in starts:
        prob = _Problem(rec, th, vmax, linear=linear)
        p, _ = _optimise(prob, method)
        total_nfev += prob.nfev
        c = prob.cost(p)
        if best is None or c < best[0]:
            best = (c, p, prob)
    _, p, prob = best
    theta = prob.theta(p)[0]
    return theta, prob, p, notes, total_nfev, starts[0], len(starts)

