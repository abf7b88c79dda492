"""Identification of the LuGre parameters from constant-current sine tests.

The paper's Section III, usable on a lab's own damper: record the damper
under a sine stroke at a staircase of constant currents (one run CSV, e.g.
``config/experiments/identify.yaml``), then

1. split each record into segments of constant commanded current ``I`` and
   drop the first period(s) after every change (settling);
2. per current, fit Θ = [σ0, σ1, σ2, Fc, Fs, vs] minimising
   Q = ∫ (F_meas − F_LuGre(v_meas))² dt over whole periods, the candidate
   model driven by the *measured* velocity after a warm-up so that z's
   initial condition does not bias the fit;
3. fit the approximating laws (6)–(11) to the per-current values (eq 6 by
   variable projection on Bc, the linear laws by ordinary least squares);
4. report fit quality (NRMSE against the sensor-noise floor) and how well
   each parameter is determined (Jacobian at the optimum), and write a
   parameters YAML that ``mrctl.config.load_params_file`` accepts.

Why the inner model is vectorised across time although z is a state: the
exponential integrator of :mod:`mrctl.model.lugre` evaluates the relaxation
rate a = σ0·|v|/g(v) at the *velocity*, never at z, so with the velocity
record given, one step is the affine map z ← e_k·z + b_k with e_k, b_k
known for all k at once. A chain of affine maps is an associative product,
computed in log2(n) numpy passes (a Hillis–Steele scan). The result is the
same arithmetic as ``LuGreModel.advance`` (to rounding), for a whole batch of
parameter sets at once — which is what a finite-difference Jacobian needs.
See ``docs/identification.md`` for the optimiser comparison and measurements.

scipy is needed here (``pip install 'mrctl[identify]'``), imported lazily so
that the daemon never needs it.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence, TextIO

import numpy as np

from mrctl.errors import BadInput
from mrctl.runlog.read import align_load_cell, try_sidecar
from mrctl.util.csvtable import CsvError, read_table
from mrctl.model.params import _LANGEVIN_SERIES_BELOW, LuGreParams

__all__ = [
    "THETA_NAMES",
    "IdentificationError",
    "CurrentFit",
    "LawFit",
    "IdentificationResult",
    "lugre_force",
    "identify",
    "write_params_yaml",
    "load_identification_run",
    "cli_identify",
]

#: Per-current parameter vector Θ of eq (4), in this order (SI units).
THETA_NAMES: tuple[str, ...] = ("sigma0", "sigma1", "sigma2", "Fc", "Fs", "vs")
THETA_UNITS: dict[str, str] = {"sigma0": "N/m", "sigma1": "N·s/m", "sigma2": "N·s/m",
                               "Fc": "N", "Fs": "N", "vs": "m/s"}
#: Θ entries that must stay > 0 (g > 0 and a bounded z need them).
_POSITIVE = (0, 3, 4, 5)

#: Optimisers: "trf" trust-region reflective on log(σ0, Fc, Fs, vs) (positive by
#: construction), "trf-bounds" the same on linearly scaled Θ with bounds > 0,
#: "lm" Levenberg–Marquardt (MINPACK) on log-parameters, "nelder-mead" the
#: paper's fminsearch on Q. Compared in docs/identification.md.
METHODS = ("trf", "trf-bounds", "lm", "nelder-mead")
DEFAULT_METHOD = "trf"
_LINEAR = ("trf-bounds",)

# A commanded current that changes by more than this starts a new segment (A).
_SEGMENT_TOL_A = 1e-6
# Below this a·h the integrator uses the series of φ1 (as LuGreModel does).
_SMALL_AH = 1e-8
# Relative finite-difference step in the optimiser's (unit-scaled) coordinates.
_FD_STEP = 1e-7


class IdentificationError(BadInput):
    """The runs cannot be identified from; the message says why, for the user."""


ProgressFn = Callable[[int, int, float, float, float], None]


# ===========================================================================
# Vectorised forward model
def _exp_scan(e: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z_k = e_k·z_{k−1} + b_k along the last axis (z_{−1} = 0), in log2(n) passes.

    Element k holds the affine map of steps (k−span, k]; composing with the
    map ``span`` steps earlier doubles the span. All e_k ∈ [0, 1], so the
    running products only shrink: no overflow, and e_k = 0 resets the state
    (how separate windows share one array)."""
    E = e.copy()
    B = b.copy()
    n = E.shape[-1]
    s = 1
    while s < n:
        B[..., s:] += E[..., s:] * B[..., :-s]  # RHS is evaluated before the store
        E[..., s:] *= E[..., :-s]
        s *= 2
    return B


@dataclass
class _Record:
    """Precomputed, parameter-free arrays of one or more fit windows.

    Each window is warm-up samples followed by fit samples; the model state is
    reset at each window's first sample (to the steady-sliding z there)."""

    v: np.ndarray  # measured velocity at each sample (m/s)
    h: np.ndarray  # step to this sample from the previous one (s)
    reset: np.ndarray  # index of each window's first sample
    fit: np.ndarray  # indices of the samples in Q
    F: np.ndarray  # measured force at the fit samples (N)

    def __post_init__(self) -> None:
        v = self.v
        vm = np.empty_like(v)
        vm[1:] = 0.5 * (v[1:] + v[:-1])  # mid-step velocity, as LuGreModel.advance
        vm[0] = v[0]
        self.vm = vm
        self.abs_vm = np.abs(vm)
        self.vm2 = vm * vm
        vf = v[self.fit]
        self.vf = vf
        self.abs_vf = np.abs(vf)
        self.vf2 = vf * vf
        self.v0 = v[self.reset]


def _model_batch(P: np.ndarray, rec: _Record, z0: float | None = None) -> np.ndarray:
    """Force at the fit samples for each row of P = [σ0, σ1, σ2, Fc, Fs, vs] (m × 6).

    Each window starts in steady sliding, z = sign(v)·g(v)/σ0 (the warm-up
    removes whatever error that leaves), unless ``z0`` is given."""
    P = np.atleast_2d(P)
    s0, s1, s2, Fc, Fs, vs = (P[:, j:j + 1] for j in range(6))
    c = 1.0 / (vs * vs)
    dF = Fs - Fc
    gm = Fc + dF * np.exp(-rec.vm2 * c)
    a = s0 * rec.abs_vm / gm
    x = a * rec.h
    small = x < _SMALL_AH
    xs = np.where(small, 1.0, x)
    phi1 = np.where(small, 1.0 - 0.5 * x, -np.expm1(-xs) / xs)  # (1 − e^{−x})/x
    e = np.exp(-x)
    b = rec.vm * rec.h * phi1
    e[:, rec.reset] = 0.0
    if z0 is None:
        v0 = rec.v0
        b[:, rec.reset] = np.sign(v0) * (Fc + dF * np.exp(-(v0 * v0) * c)) / s0
    else:
        b[:, rec.reset] = z0
    z = _exp_scan(e, b)[:, rec.fit]
    g = Fc + dF * np.exp(-rec.vf2 * c)
    zdot = rec.vf - s0 * rec.abs_vf * z / g
    return s0 * z + s1 * zdot + s2 * rec.vf


def lugre_force(theta: Sequence[float] | Mapping[str, float], v: np.ndarray, dt: float | np.ndarray,
                z0: float | None = None) -> np.ndarray:
    """Force (N) of the LuGre model with constant Θ driven by the velocity record v.

    ``theta`` is [σ0, σ1, σ2, Fc, Fs, vs] or a mapping of those names; ``dt``
    the sample interval (or the per-sample steps, h[0] unused). The tick
    protocol is :class:`mrctl.model.lugre.LuGreModel`'s: z advanced with the
    mid-step velocity, force at the sample's velocity. ``z0`` defaults to the
    steady-sliding state at v[0]."""
    if isinstance(theta, Mapping):
        theta = [theta[k] for k in THETA_NAMES]
    v = np.asarray(v, float).reshape(-1)
    n = v.size
    h = np.broadcast_to(np.asarray(dt, float), (n,)).astype(float)
    rec = _Record(v, h, np.array([0]), np.arange(n), np.zeros(n))
    return _model_batch(np.asarray(theta, float).reshape(1, 6), rec, z0)[0]


# ===========================================================================
# Loading and checking runs
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
    table = table._replace(columns=align_load_cell(table.columns, try_sidecar(p)))  # F at its own tick (runlog)
    if not table.columns:
        found = ", ".join(h for h in table.header if h) or "(none)"
        raise IdentificationError(f"{p}: none of the columns t, I, F_meas/F, v_meas/v found "
                                  f"(is this a run CSV?); header: {found[:80]}{'…' if len(found) > 80 else ''}")
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
    n = cols["t"].size
    for key in ("t", "I", "F", "v", "I_applied"):
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
        raise IdentificationError(f"{label}: negative current in column I (min {cols['I'].min():g} A)")
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
            "identification needs a constant-frequency sine stroke (or pass period_s)")
    return T


# ===========================================================================
# Segments of constant current
def _segments(I: np.ndarray) -> list[tuple[int, int]]:
    cut = np.flatnonzero(np.abs(np.diff(I)) > _SEGMENT_TOL_A) + 1
    edges = np.concatenate(([0], cut, [I.size]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


# ===========================================================================
# Starting values from the data
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


# ===========================================================================
# Per-current fit
@dataclass
class CurrentFit:
    """Identification at one constant current."""

    current: float  # A (mean applied current over the fit windows)
    current_cmd: float  # commanded current (A)
    theta: dict[str, float]
    theta0: dict[str, float]  # starting values (from the data)
    start_notes: dict[str, str]
    nrmse: float  # RMS(F_meas − F_fit) / ptp(F_meas) with this current's Θ
    noise_nrmse: float  # sensor-noise floor of the same ratio (estimated from F_meas)
    nrmse_laws: float = math.nan  # same with Θ from the fitted laws (6)–(11)
    rms_N: float = math.nan
    ptp_N: float = math.nan
    noise_N: float = math.nan
    se: dict[str, float] = field(default_factory=dict)  # standard errors (white-noise assumption)
    rel_se: dict[str, float] = field(default_factory=dict)  # se / |θ|
    sensitivity: dict[str, float] = field(default_factory=dict)  # |Δθ|/|θ| moving F by 1 % of ptp
    corr: list[list[float]] = field(default_factory=list)
    determined: dict[str, str] = field(default_factory=dict)  # "well" / "poor"
    nfev: int = 0
    starts: int = 1
    time_s: float = 0.0
    samples: int = 0
    periods: float = 0.0
    segments: list[tuple[int, float, float]] = field(default_factory=list)  # (run, t0, t1) of fit windows
    # plotting data (fit samples only)
    v: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    F_meas: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    F_fit: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    F_laws: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)


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
            R = _model_batch(self.theta(P), self.rec) - self.rec.F
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
    s2 = Q / max(N - 6, 1)
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


def _window_record(windows: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]]) -> _Record:
    """Concatenate (v, F, h, n_warm) windows into one record with state resets."""
    vs_, hs, Fs_, fit, reset = [], [], [], [], []
    off = 0
    for v, F, h, nw in windows:
        reset.append(off)
        fit.append(np.arange(off + nw, off + v.size))
        vs_.append(v)
        hs.append(h)
        Fs_.append(F[nw:])
        off += v.size
    return _Record(np.concatenate(vs_), np.concatenate(hs), np.asarray(reset), np.concatenate(fit),
                   np.concatenate(Fs_))


#: Grid for the σ0, σ1 starting values: pre-sliding lengths λ = Fc/σ0 as a
#: fraction of the stroke amplitude, and σ1 in units of Fc/max|v|.
_GRID_LAMBDA = np.geomspace(1e-4, 0.3, 16)
_GRID_SIGMA1 = (-10.0, -3.0, -1.0, 0.0, 1.0, 3.0)


def _grid_starts(rec: _Record, theta0: np.ndarray, vmax: float, amp: float, k: int = 2) -> list[np.ndarray]:
    """The k best (σ0, σ1) of a batched grid of Q, the other four at their
    data-derived starting values; the slope-based σ0 (with σ1 = 0) competes."""
    scale = theta0[3] / max(vmax, 1e-9)
    cands = [theta0.copy()]
    for lam in _GRID_LAMBDA:
        for s1 in _GRID_SIGMA1:
            th = theta0.copy()
            th[0] = theta0[3] / (lam * amp)
            th[1] = s1 * scale
            cands.append(th)
    P = np.array(cands)
    with np.errstate(all="ignore"):
        R = _model_batch(P, rec) - rec.F
    q = np.where(np.isfinite(R).all(axis=1), np.einsum("ij,ij->i", R, R), np.inf)
    order = np.argsort(q)
    out: list[np.ndarray] = []
    for i in order.tolist():
        # distinct basins: skip candidates next to one already taken
        if all(abs(math.log(P[i, 0] / o[0])) > 1.0 or abs(P[i, 1] - o[1]) > 1.5 * scale for o in out):
            out.append(P[i])
        if len(out) == k:
            break
    return out


def _fit_one_current(windows, method: str, starts_max: int = 2):
    """Fit Θ at one current over its windows: data-derived start, the
    ``starts_max`` best distinct (σ0, σ1) grid points, one optimiser run from
    each, the lowest Q kept. Returns (θ, problem, p, notes, nfev, θ0, starts)."""
    rec = _window_record(windows)
    vf, Ff = rec.v[rec.fit], rec.F
    hf = rec.h[rec.fit]
    theta0, notes = initial_guess(vf, Ff, hf)
    vmax = float(np.percentile(np.abs(vf), 99.5))
    amp = 0.5 * float(np.ptp(np.cumsum(vf * hf)))  # stroke amplitude from ∫v dt
    starts = _grid_starts(rec, theta0, vmax, max(amp, 1e-9), starts_max)
    if starts[0][0] != theta0[0] or starts[0][1] != theta0[1]:
        notes["sigma0"] = (f"best of a Q grid (pre-sliding length Fc/σ0 = 1e-4…0.3 × stroke); "
                           f"slope estimate was {theta0[0]:.4g}")
        notes["sigma1"] = "best of a Q grid (0, ±1, ±3, −10 × Fc/max|v|)"
    linear = method in _LINEAR
    best = None
    total_nfev = len(_GRID_LAMBDA) * len(_GRID_SIGMA1) + 1
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


# ===========================================================================
# Approximating laws (6)–(11)
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


def _fit_Fc_law(I: np.ndarray, Fc: np.ndarray, F0_fixed: float | None = None) -> tuple[float, float, float]:
    """(Ac, Bc, F0) of eq (6) by variable projection: for each Bc, Ac and F0 are linear."""
    from scipy.optimize import minimize_scalar

    def solve(Bc: float) -> tuple[float, float, float]:
        L2 = _langevin_np(I / Bc) ** 2
        if F0_fixed is None:
            A = np.column_stack([L2, np.ones_like(L2)])
            (Ac, F0), *_ = np.linalg.lstsq(A, Fc, rcond=None)
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


def fit_laws(I: np.ndarray, thetas: Mapping[str, np.ndarray], F0: str = "fit") -> tuple[LuGreParams, dict[str, LawFit]]:
    """Laws (6)–(11) fitted to per-current values (arrays indexed like I).

    ``F0``: "fit" (eq 6's offset fitted with Ac, Bc) or "measured" (F0 pinned
    to the identified Fc at the smallest current, which must be 0 A)."""
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
    Ac, Bc, F0v = _fit_Fc_law(I, Fc, F0_fixed)
    # Table I writes Bc < 0; the square makes its sign irrelevant: keep the paper's
    Bc = -abs(Bc)
    values.update(F0=F0v, Ac=Ac, Bc=Bc)
    p_tmp = LuGreParams(F0=F0v, Ac=Ac, Bc=Bc)
    Fc_hat = np.array([p_tmp.Fc(float(i)) for i in I])
    laws["Fc"] = _law_stats("Fc", "Fc = Ac·(coth(I/Bc) − Bc/I)² + F0   (6)", {"Ac": Ac, "Bc": Bc, "F0": F0v}, Fc, Fc_hat)
    X = np.column_stack([I, np.ones_like(I)])
    for name, kA, kB, eq in _LINEAR_LAWS:
        y = np.asarray(thetas[name], float)
        (a, b), *_ = np.linalg.lstsq(X, y, rcond=None)
        values[kA], values[kB] = float(a), float(b)
        laws[name] = _law_stats(name, f"{name} = {kA}·I + {kB}   {eq}", {kA: float(a), kB: float(b)}, y, a * I + b)
    return LuGreParams(**values), laws


def theta_from_params(p: LuGreParams, I: float) -> np.ndarray:
    """Θ at current I from a 13-constant parameter set (laws 6–11)."""
    return np.array([p.sigma0(I), p.sigma1(I), p.sigma2(I), p.Fc(I), p.Fs(I), p.vs(I)])


# ===========================================================================
# Top level
@dataclass
class IdentificationResult:
    params: LuGreParams  # the 13 constants (laws 6–11)
    fits: list[CurrentFit]  # per current, ascending
    laws: dict[str, LawFit]
    method: str
    period_s: float
    dt_s: float
    settle_periods: float
    warmup_periods: float
    fit_periods: float | None
    sources: list[str]
    time_s: float
    warnings: list[str] = field(default_factory=list)

    @property
    def currents(self) -> np.ndarray:
        return np.array([f.current for f in self.fits])

    def theta(self, name: str) -> np.ndarray:
        return np.array([f.theta[name] for f in self.fits])

    def summary_determined(self) -> dict[str, str]:
        """Per parameter: 'well' (at ≥ 75 % of the currents), 'poor' (≤ 25 %) or 'mixed'."""
        out = {}
        for k in THETA_NAMES:
            share = float(np.mean([f.determined.get(k) == "well" for f in self.fits]))
            out[k] = "well" if share >= 0.75 else ("poor" if share <= 0.25 else "mixed")
        return out


def identify(runs: Sequence[Mapping[str, Any]], *, method: str = DEFAULT_METHOD,
             settle_periods: float = 1.0, warmup_periods: float = 1.0, fit_periods: float | None = None,
             max_rate_hz: float | None = 2000.0, period_s: float | None = None, F0: str = "fit",
             progress: ProgressFn | None = None, sources: Sequence[str] | None = None) -> IdentificationResult:
    """Identify the 13 LuGre constants from constant-current sine runs.

    Args:
        runs: run records ``{column: array}`` with t, I (commanded current),
            F_meas (or F), v_meas (or v); I_applied is used when present.
        method: "trf" (default), "trf-bounds", "lm" or "nelder-mead" (the
            paper's fminsearch); see :data:`METHODS` and docs/identification.md.
        settle_periods: periods dropped after every change of current.
        warmup_periods: periods the candidate model runs before Q is
            accumulated (taken from the settling part when it is long enough).
        fit_periods: whole periods per segment in Q (None: all available).
        max_rate_hz: records sampled faster are decimated (plain subsampling).
        period_s: excitation period; estimated from the velocity if None.
        F0: "fit" or "measured" (see :func:`fit_laws`).
        progress: called after each current as
            ``progress(index, total, current_A, elapsed_s, nrmse)``, index 1-based,
            elapsed since the start of identify.
        sources: a name per run for messages and the YAML (default "run 1"…).
    Raises:
        IdentificationError: bad or insufficient input, with a message for the user.
    """
    if method not in METHODS:
        raise IdentificationError(f"unknown method {method!r} (one of {', '.join(METHODS)})")
    if isinstance(runs, Mapping):
        runs = [runs]
    runs = list(runs)
    if not runs:
        raise IdentificationError("no runs given")
    labels = list(sources) if sources is not None else [f"run {k + 1}" for k in range(len(runs))]
    if len(labels) != len(runs):
        raise IdentificationError("sources: need one name per run")
    if settle_periods < 0 or warmup_periods < 0 or (fit_periods is not None and fit_periods < 1):
        raise IdentificationError("settle/warm-up periods must be ≥ 0 and fit_periods ≥ 1")
    try:
        import scipy.optimize  # noqa: F401  (imported here, not inside the first fit's timing)
    except ImportError:
        raise IdentificationError("scipy is needed for identification: pip install 'mrctl[identify]'") from None
    t_start = time.perf_counter()
    warnings: list[str] = []
    checked = [_check_run(r, lab) for r, lab in zip(runs, labels)]

    # decimation and period
    dts = []
    for c, lab in zip(checked, labels):
        dt = float(np.median(np.diff(c["t"])))
        if max_rate_hz is not None and dt < 1.0 / max_rate_hz * 0.999:
            step = int(round(1.0 / (max_rate_hz * dt)))
            if step > 1:
                for key in ("t", "I", "F", "v", "I_applied"):
                    if key in c:
                        c[key] = c[key][::step]
                warnings.append(f"{lab}: decimated by {step} to {1.0 / (dt * step):.0f} Hz")
                dt *= step
        dts.append(dt)
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

    # segments → fit windows, grouped by commanded current
    n_settle = max(settle_periods, warmup_periods)
    groups: dict[float, list[tuple[int, int, int, int]]] = {}  # I → [(run, w0, f0, f1)]
    need_s = (n_settle + (fit_periods or 1.0)) * T
    for r, (c, lab) in enumerate(zip(checked, labels)):
        t = c["t"]
        dt = dts[r]
        segs = _segments(c["I"])
        if len(segs) > max(50, 4 * (t[-1] - t[0]) / T):
            raise IdentificationError(
                f"{lab}: the commanded current changes {len(segs) - 1} times; identification needs steps of "
                "constant current (inverse law 'schedule' or 'constant'), not a closed-loop run")
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

    fits: list[CurrentFit] = []
    total = len(groups)
    for gi, I_cmd in enumerate(sorted(groups)):
        t0 = time.perf_counter()
        windows = []
        Iapp = []
        segs_info = []
        for r, w0, f0, f1 in groups[I_cmd]:
            c = checked[r]
            h = np.empty(f1 - w0)
            h[1:] = np.diff(c["t"][w0:f1])
            h[0] = dts[r]
            windows.append((c["v"][w0:f1], c["F"][w0:f1], h, f0 - w0))
            Iapp.append(c.get("I_applied", c["I"])[f0:f1])
            segs_info.append((r, float(c["t"][f0]), float(c["t"][f1 - 1])))
        theta, prob, p, notes, nfev, theta0, starts = _fit_one_current(windows, method)
        rec = prob.rec
        F_fit = _model_batch(theta[None, :], rec)[0]
        res = F_fit - rec.F
        rms = float(np.sqrt(np.mean(res * res)))
        ptp = float(np.ptp(rec.F))
        noise = float(np.median([_noise_N(w[1][w[3]:]) for w in windows]))
        se, rel_se, sens, corr, det = _identifiability(prob, p, theta, ptp)
        cf = CurrentFit(
            current=float(np.mean(np.concatenate(Iapp))), current_cmd=float(I_cmd),
            theta={k: float(theta[j]) for j, k in enumerate(THETA_NAMES)},
            theta0={k: float(theta0[j]) for j, k in enumerate(THETA_NAMES)}, start_notes=notes,
            nrmse=rms / ptp if ptp > 0 else math.nan, noise_nrmse=noise / ptp if ptp > 0 else math.nan,
            rms_N=rms, ptp_N=ptp, noise_N=noise, se=se, rel_se=rel_se, sensitivity=sens, corr=corr,
            determined=det,
            nfev=nfev, starts=starts, time_s=time.perf_counter() - t0, samples=int(rec.F.size),
            periods=float(sum((f1 - f0) for _, _, f0, f1 in groups[I_cmd]) * dts[groups[I_cmd][0][0]] / T),
            segments=segs_info, v=rec.v[rec.fit].copy(), F_meas=rec.F.copy(), F_fit=F_fit,
        )
        cf._rec = rec  # type: ignore[attr-defined]  # for the law-based NRMSE below
        fits.append(cf)
        if progress is not None:
            progress(gi + 1, total, cf.current, time.perf_counter() - t_start, cf.nrmse)

    I_arr = np.array([f.current for f in fits])
    params, laws = fit_laws(I_arr, {k: np.array([f.theta[k] for f in fits]) for k in THETA_NAMES}, F0)
    for f in fits:
        th = theta_from_params(params, f.current)
        rec = f._rec  # type: ignore[attr-defined]
        if th[0] > 0 and th[3] > 0 and th[4] > 0 and th[5] != 0:
            with np.errstate(all="ignore"):
                F_law = _model_batch(th[None, :], rec)[0]
            f.F_laws = F_law
            f.nrmse_laws = float(np.sqrt(np.mean((F_law - rec.F) ** 2))) / f.ptp_N
        del f._rec  # type: ignore[attr-defined]
    problems = params.check_range(float(I_arr.max()))
    warnings += [f"fitted laws: {p_}" for p_ in problems]
    return IdentificationResult(params=params, fits=fits, laws=laws, method=method, period_s=T,
                                dt_s=float(np.median(dts)), settle_periods=settle_periods,
                                warmup_periods=warmup_periods, fit_periods=fit_periods,
                                sources=labels, time_s=time.perf_counter() - t_start, warnings=warnings)


# ===========================================================================
# Output
def _r(x: float, digits: int = 6) -> float | str:
    if x is None or not math.isfinite(x):
        return "nan" if x is None or math.isnan(x) else ("inf" if x > 0 else "-inf")
    return float(f"{x:.{digits}g}")


_METHOD_TEXT = {
    "trf": "per-current least squares, trust-region reflective (scipy) on log(sigma0, Fc, Fs, vs) and scaled "
           "sigma1, sigma2; vectorised LuGre model driven by the measured velocity",
    "lm": "per-current least squares, Levenberg-Marquardt (scipy MINPACK) on log(sigma0, Fc, Fs, vs) "
          "and scaled sigma1, sigma2; vectorised LuGre model driven by the measured velocity",
    "trf-bounds": "per-current least squares, trust-region reflective (scipy) with bounds sigma0, Fc, Fs, vs > 0; "
           "vectorised LuGre model driven by the measured velocity",
    "nelder-mead": "per-current Nelder-Mead on Q (as the paper's fminsearch), log-scaled parameters; "
                   "vectorised LuGre model driven by the measured velocity",
}


def result_metadata(result: IdentificationResult) -> dict[str, Any]:
    """The ``fit:`` block of the parameters YAML (plain types only)."""
    per = []
    for f in result.fits:
        per.append({
            "current_A": _r(f.current), "current_cmd_A": _r(f.current_cmd),
            "theta": {k: _r(v) for k, v in f.theta.items()},
            "nrmse": _r(f.nrmse, 4), "nrmse_noise_floor": _r(f.noise_nrmse, 4), "nrmse_laws": _r(f.nrmse_laws, 4),
            "rms_N": _r(f.rms_N, 4), "noise_N": _r(f.noise_N, 4),
            "std_error": {k: _r(v, 3) for k, v in f.se.items()},
            "rel_std_error": {k: _r(v, 3) for k, v in f.rel_se.items()},
            "sensitivity_1pct": {k: _r(v, 3) for k, v in f.sensitivity.items()},
            "determined": dict(f.determined),
            "correlation": f.corr,
            "start": {k: _r(v, 4) for k, v in f.theta0.items()},
            "periods": _r(f.periods, 4), "samples": f.samples, "nfev": f.nfev, "starts": f.starts,
            "time_s": _r(f.time_s, 3),
        })
    return {
        "method": _METHOD_TEXT[result.method],
        "optimiser": result.method,
        "objective": "Q = sum over whole periods of (F_meas - F_LuGre(v_meas))^2, after a model warm-up",
        "period_s": _r(result.period_s), "sample_interval_s": _r(result.dt_s),
        "settle_periods": result.settle_periods, "warmup_periods": result.warmup_periods,
        "fit_periods": result.fit_periods if result.fit_periods is not None else "all",
        "source_runs": list(result.sources),
        "nrmse_definition": "RMS(F_meas - F_model) / peak-to-peak(F_meas) over the fit windows",
        "identifiability": {
            "summary": result.summary_determined(),
            "criterion": f"'well' at a current if rel_std_error < {_WELL_REL_SE:.0%} (std_error from the "
                         "Jacobian at the optimum, white sensor noise assumed) and sensitivity_1pct < "
                         f"{_WELL_SENS:.0%}; summary: 'well' at >= 75 % of the currents, 'poor' at <= 25 %, "
                         "else 'mixed'",
            "sensitivity_1pct": "relative parameter change that, the other five re-fitted, changes the "
                                "model force by 1 % of its peak-to-peak (noise-independent)",
            "correlation_order": list(THETA_NAMES),
        },
        "laws": {k: {"equation": lf.equation, "coefficients": {c: _r(v) for c, v in lf.coefficients.items()},
                     "rms": _r(lf.rms, 4), "rel_rms": _r(lf.rel_rms, 4), "max_abs": _r(lf.max_abs, 4),
                     "r2": _r(lf.r2, 4)} for k, lf in result.laws.items()},
        "per_current": per,
        "warnings": list(result.warnings),
        "time_s": _r(result.time_s, 3),
    }


def _compact_dumper():
    import yaml

    class Dumper(yaml.SafeDumper):
        """Flow style for lists and mappings of scalars: one line per Θ, per matrix row."""

    def _flat(items) -> bool:
        return all(isinstance(x, (int, float, str, bool)) or x is None for x in items)

    def rep_list(d, data):
        return d.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=_flat(data) and len(data) > 0)

    def rep_dict(d, data):
        flat = _flat(data.values()) and len(data) <= 8 and all(not isinstance(v, str) or len(v) < 20
                                                                for v in data.values())
        return d.represent_mapping("tag:yaml.org,2002:map", data.items(), flow_style=flat and len(data) > 0)

    Dumper.add_representer(list, rep_list)
    Dumper.add_representer(dict, rep_dict)
    return Dumper


def write_params_yaml(result: IdentificationResult, path: str | Path, description: str | None = None) -> None:
    """Parameters YAML: the 13 spec names at top level, ``fit:`` metadata below.

    ``mrctl.config.load_params_file`` reads it (metadata keys are ignored there)."""
    import yaml

    from mrctl import __version__

    _CompactDumper = _compact_dumper()
    p = result.params
    currents = result.currents
    doc: dict[str, Any] = {
        "version": 1,
        "description": description or (
            f"LuGre parameters identified by mrctl {__version__} from {len(result.fits)} constant-current "
            f"sine tests ({currents.min():g}–{currents.max():g} A, period {result.period_s:.4g} s)"),
        "source": ", ".join(result.sources),
    }
    values = p.as_dict()
    doc.update({k: float(values[k]) for k in p.names()})
    doc.update({k: float(values[k]) for k in p.bench_names() if values[k] != 0.0})  # only the terms a fit set
    doc["fit"] = result_metadata(result)
    out = Path(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with out.open("w", encoding="utf-8") as fh:
            fh.write("# mrctl identify: LuGre parameters (SI units), laws (6)-(11) of Palka & Maslanka 2013\n")
            yaml.dump(doc, fh, Dumper=_CompactDumper, sort_keys=False, allow_unicode=True, width=120)
    except OSError as exc:
        raise IdentificationError(f"{out}: cannot write: {exc.strerror or exc}") from None


def format_summary(result: IdentificationResult) -> str:
    """The per-current table and the law residuals, as printed by the CLI."""
    lines = [f"{'I (A)':>7} {'Fc (N)':>8} {'Fs (N)':>8} {'σ0 (N/m)':>10} {'σ1 (N·s/m)':>11} "
             f"{'σ2 (N·s/m)':>11} {'vs (mm/s)':>10} {'NRMSE':>7} {'floor':>7} {'laws':>7}  poorly determined"]
    for f in result.fits:
        th = f.theta
        poor = ",".join(k for k in THETA_NAMES if f.determined.get(k) == "poor") or "-"
        lines.append(f"{f.current:7.3f} {th['Fc']:8.3f} {th['Fs']:8.3f} {th['sigma0']:10.4g} {th['sigma1']:11.4g} "
                     f"{th['sigma2']:11.4g} {1e3 * th['vs']:10.3f} {100 * f.nrmse:6.2f}% {100 * f.noise_nrmse:6.2f}% "
                     f"{100 * f.nrmse_laws:6.2f}%  {poor}")
    lines.append("laws (6)-(11): " + "; ".join(
        f"{k} rms {lf.rms:.4g} ({100 * lf.rel_rms:.1f} %)" for k, lf in result.laws.items()))
    lines.append("identifiability: " + ", ".join(f"{k} {v}" for k, v in result.summary_determined().items()))
    p = result.params
    lines.append("parameters: " + ", ".join(f"{k}={v:.5g}" for k, v in p.as_dict().items()))
    for w in result.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def cli_identify(run_paths: Sequence[str], out: str, progress_stream: TextIO = sys.stdout,
                 method: str = DEFAULT_METHOD, report_png: str | None = None, **kwargs: Any) -> int:
    """``mrctl identify RUNS... --out PARAMS.yaml [--method M] [--report FIG.png]``.

    Exit 0 ok, 2 bad input, 1 failure. Prints one progress line per current
    and a summary table to ``progress_stream``; errors go to stderr as one
    line, never a traceback. ``report_png``: also draw the identification
    figure (:func:`mrctl.offline.report.make_identification_report`). Other keyword
    arguments go to :func:`identify`."""
    def err(msg: str) -> None:
        print(f"mrctl identify: {msg}", file=sys.stderr)

    if not run_paths:
        err("no run CSV given")
        return 2
    try:
        import scipy  # noqa: F401
    except ImportError:
        err("scipy is needed for identification: pip install 'mrctl[identify]'")
        return 1
    try:
        runs = [load_identification_run(p) for p in run_paths]

        def progress(i: int, n: int, I: float, elapsed: float, nrmse: float) -> None:
            print(f"[{i:2d}/{n}] I = {I:.3f} A  NRMSE {100 * nrmse:5.2f} %  ({elapsed:.1f} s)",
                  file=progress_stream, flush=True)

        result = identify(runs, method=method, progress=progress, sources=[str(p) for p in run_paths], **kwargs)
        write_params_yaml(result, out)
    except IdentificationError as exc:
        err(str(exc))
        return 2
    except KeyboardInterrupt:
        err("interrupted")
        return 130
    except Exception as exc:  # noqa: BLE001 - a lab user gets one line, not a traceback
        err(f"internal error: {type(exc).__name__}: {exc}")
        return 1
    print(format_summary(result), file=progress_stream)
    print(f"wrote {out} ({len(result.fits)} currents, {result.time_s:.1f} s, optimiser {result.method})",
          file=progress_stream)
    if report_png:
        from mrctl.offline.report import ReportError, make_identification_report

        try:
            make_identification_report(result, report_png)
        except ReportError as exc:
            err(str(exc))
            return 1
        print(f"wrote {report_png}", file=progress_stream)
    return 0
