"""The full model over a record, vectorised across parameter sets: lagged input
→ input-dependent laws → LuGre → + offset + stiffness (+ inertia).

For broadband and switched-input records Θ changes every sample, through
the input the damper feels, u_d = first-order lag of the command u. The
exponential integrator still evaluates the relaxation rate a_k at the
velocity and at u_d (never at z), so each step stays the affine map
z ← e_k·z + b_k, now with per-sample coefficients: the same Hillis–Steele
scan as :mod:`.model` computes all of it in log2(n) numpy passes, for a
batch of parameter sets at once (the finite-difference Jacobian's columns).
The lag is ``scipy.signal.lfilter``, once per distinct τ in the batch.

Tick protocol: :class:`mrctl.model.plant.DamperPlant`'s, so that a record
made by our own plant is reproduced to rounding: z moves from sample k−1
to k with the mid-step velocity and the input applied at k−1; the force at
k uses the input applied at k; u_d follows u_k with α = 1 − e^{−h/τ}.

Parameter vector (:data:`PHYS`): Fc's eq (6) as F0, Ac, Bc; every linear law
(7)–(11) by its values at the ends of the fitted input range [u_lo, u_hi]
(a linear law positive at both ends is positive between them); then
F_offset, k_x, tau_input and the load-cell inertia m; then the optional
terms of :class:`~mrctl.model.params.LuGreParams`, each off at 0:
sigma1_vd, tau_input_fall (0: tau_input), k_hys_pos, k_hys_neg, x_hys,
tau_field (a second lag after the first; simulated, not fitted: force
alone cannot tell it from the driver's).
A falling lag apart from the rising one makes the input path nonlinear
(which lag acts depends on the state): :func:`felt_input` solves it as a
time-varying first-order recursion by the same scan, a few passes until
the rising/falling pattern repeats.
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np

from mrctl.model.params import LuGreParams
from mrctl.offline.identify.laws import _langevin_np
from mrctl.offline.identify.model import _SMALL_AH, _exp_scan, hys_state

__all__ = ["PHYS", "EXTRAS", "LINEAR_LAWS", "LINEAR_IN_F", "linear_columns", "SpanData", "simulate", "to_params",
           "from_params", "felt_input", "hys_state"]

#: the linear laws (7)–(11), each as (value at u_lo, value at u_hi)
LINEAR_LAWS = ("sigma0", "sigma1", "sigma2", "Fs", "vs")
#: the optional model terms, after the bench terms (LuGreParams' names)
EXTRAS = ("sigma1_vd", "tau_input_fall", "k_hys_pos", "k_hys_neg", "x_hys", "tau_field")
PHYS: tuple[str, ...] = ("F0", "Ac", "Bc") + tuple(f"{k}_{e}" for k in LINEAR_LAWS for e in ("lo", "hi")) + (
    "F_offset", "k_x", "tau_input", "m") + EXTRAS
IDX = {k: j for j, k in enumerate(PHYS)}


@dataclass
class SpanData:
    """One contiguous stretch at a fixed step h, with parameter-free precomputation."""

    u: np.ndarray  # commanded input
    v: np.ndarray
    x: np.ndarray  # displacement (zeros if not recorded: k_x then fixed at 0)
    a: np.ndarray  # acceleration (zeros unless the inertia term is fitted)
    h: float

    def __post_init__(self) -> None:
        v = self.v
        vm = np.empty_like(v)
        vm[1:] = 0.5 * (v[1:] + v[:-1])
        vm[0] = v[0]
        self.vm = vm
        self.abs_vm = np.abs(vm)
        self.vm2 = vm * vm
        self.abs_v = np.abs(v)
        self.v2 = v * v


def felt_input(u: np.ndarray, tau: float, h: float, tau_fall: float = 0.0) -> np.ndarray:
    """u_d: the first-order lag of u (DamperPlant's DriverLag), starting settled at u[0];
    ``tau_fall`` (> 0 and ≠ tau) while u is below u_d, as the driver has it."""
    u = np.asarray(u, float)
    if tau_fall > 0.0 and tau_fall != tau:
        return _felt_asymmetric(u, tau, tau_fall, h)
    if not tau > 0.0:
        return u
    from scipy.signal import lfilter

    alpha = -np.expm1(-h / tau)
    return lfilter([alpha], [1.0, alpha - 1.0], u, zi=[(1.0 - alpha) * u[0]])[0]


def _felt_asymmetric(u: np.ndarray, tau: float, tau_fall: float, h: float) -> np.ndarray:
    """u_d_k = u_d_{k−1} + a_k·(u_k − u_d_{k−1}), a_k the rise's gain where u_k ≥ u_d_{k−1} and the
    fall's where not: for a given pattern of rises and falls a linear recursion (the affine scan);
    the pattern from the last pass's u_d until it repeats (a switched input settles in 2–3 passes),
    then exact. At most 30 passes; the last pattern otherwise (never met on recorded commands)."""
    ar = 1.0 if not tau > 0.0 else -math.expm1(-h / tau)
    af = -math.expm1(-h / tau_fall)
    ud = felt_input(u, tau, h)
    rise = None
    for _ in range(30):
        prev = np.concatenate(([u[0]], ud[:-1]))
        r = u >= prev
        if rise is not None and np.array_equal(r, rise):
            break
        rise = r
        a = np.where(r, ar, af)
        e, b = 1.0 - a, a * u
        e[0], b[0] = 0.0, u[0]  # settled at u[0]
        ud = _exp_scan(e[None, :], b[None, :])[0]
    return ud


def _laws(P: np.ndarray, ud: np.ndarray, u_lo: float, u_hi: float):
    s = (ud - u_lo) / (u_hi - u_lo)
    out = []
    for k in LINEAR_LAWS:
        lo = P[:, IDX[k + "_lo"]][:, None]
        hi = P[:, IDX[k + "_hi"]][:, None]
        out.append(lo + (hi - lo) * s)
    Bc = P[:, IDX["Bc"]][:, None]
    L = _langevin_np(ud / Bc)
    Fc = P[:, IDX["F0"]][:, None] + P[:, IDX["Ac"]][:, None] * L * L
    s0, s1, s2, Fs, vs = out
    return s0, s1, s2, Fc, Fs, vs


#: parameters the force is linear in (z does not depend on them): their
#: Jacobian columns are exact from one simulation (:func:`linear_columns`)
LINEAR_IN_F = ("F_offset", "k_x", "m", "sigma1_lo", "sigma1_hi", "sigma2_lo", "sigma2_hi", "k_hys_pos", "k_hys_neg")


def simulate(P: np.ndarray, sp: SpanData, u_lo: float, u_hi: float, parts: dict | None = None) -> np.ndarray:
    """Force (N) at every sample for each row of P (m × len(PHYS)), m × n.

    z starts in steady sliding at the first sample (the caller leaves a
    warm-up out of the objective). ``parts``, if given, receives the first
    row's ż and normalised input s (for :func:`linear_columns`)."""
    P = np.atleast_2d(P)
    m, n = P.shape[0], sp.v.size
    lags = P[:, [IDX["tau_input"], IDX["tau_input_fall"], IDX["tau_field"]]]
    ud = np.empty((m, n))
    for tau, tf, tfield in np.unique(lags, axis=0):
        rows = (lags[:, 0] == tau) & (lags[:, 1] == tf) & (lags[:, 2] == tfield)
        ud[rows] = felt_input(felt_input(sp.u, float(tau), sp.h, float(tf)), float(tfield), sp.h)  # driver, field
    s0, s1, s2, Fc, Fs, vs = _laws(P, ud, u_lo, u_hi)
    # advance k-1 → k with the input applied at k-1 (shifted by one sample)
    s0p = np.concatenate((s0[:, :1], s0[:, :-1]), axis=1)
    Fcp = np.concatenate((Fc[:, :1], Fc[:, :-1]), axis=1)
    Fsp = np.concatenate((Fs[:, :1], Fs[:, :-1]), axis=1)
    vsp = np.concatenate((vs[:, :1], vs[:, :-1]), axis=1)
    gm = Fcp + (Fsp - Fcp) * np.exp(-sp.vm2 / (vsp * vsp))
    xh = s0p * sp.abs_vm / gm * sp.h
    small = xh < _SMALL_AH
    xs = np.where(small, 1.0, xh)
    phi1 = np.where(small, 1.0 - 0.5 * xh, -np.expm1(-xs) / xs)
    e = np.exp(-xh)
    b = sp.vm * sp.h * phi1
    v0 = sp.v[0]
    g0 = Fc[:, 0] + (Fs[:, 0] - Fc[:, 0]) * np.exp(-(v0 * v0) / (vs[:, 0] * vs[:, 0]))
    e[:, 0] = 0.0
    b[:, 0] = np.sign(v0) * g0 / s0[:, 0]
    z = _exp_scan(e, b)
    g = Fc + (Fs - Fc) * np.exp(-sp.v2 / (vs * vs))
    zdot = sp.v - s0 * sp.abs_v * z / g
    vd = P[:, IDX["sigma1_vd"]]
    if np.any(vd > 0.0):  # sigma1(v): the weight exp(-(v/vd)²) on ż (1 where vd is 0: off)
        inv = np.where(vd > 0.0, 1.0 / np.where(vd > 0.0, vd, 1.0) ** 2, 0.0)
        zdot = zdot * np.exp(-sp.v2 * inv[:, None])
    F = s0 * z + s1 * zdot + s2 * sp.v
    if parts is not None:
        parts["zdot"] = zdot[0]
        parts["s"] = (ud[0] - u_lo) / (u_hi - u_lo)
    F += P[:, IDX["F_offset"]][:, None] + P[:, IDX["k_x"]][:, None] * sp.x + P[:, IDX["m"]][:, None] * sp.a
    kp, kn, xh = P[:, IDX["k_hys_pos"]], P[:, IDX["k_hys_neg"]], P[:, IDX["x_hys"]]
    if np.any((kp != 0.0) | (kn != 0.0)) or parts is not None and xh[0] > 0.0:
        pos = sp.v >= 0.0
        for x in np.unique(xh[xh > 0.0]):
            rows = xh == x
            zh = hys_state(sp.v, sp.h, float(x))
            F[rows] += np.where(pos, kp[rows, None], kn[rows, None]) * zh
            if parts is not None and rows[0]:
                parts["zh_pos"], parts["zh_neg"] = np.where(pos, zh, 0.0), np.where(pos, 0.0, zh)
    return F


def linear_columns(name: str, sp: SpanData, parts: dict) -> np.ndarray:
    """∂F/∂θ for a parameter in :data:`LINEAR_IN_F`, from one simulation's ``parts``."""
    s, zdot = parts["s"], parts["zdot"]
    return {"F_offset": lambda: np.ones_like(sp.v), "k_x": lambda: sp.x, "m": lambda: sp.a,
            "sigma1_lo": lambda: (1.0 - s) * zdot, "sigma1_hi": lambda: s * zdot,
            "sigma2_lo": lambda: (1.0 - s) * sp.v, "sigma2_hi": lambda: s * sp.v,
            "k_hys_pos": lambda: parts["zh_pos"], "k_hys_neg": lambda: parts["zh_neg"]}[name]()


def to_params(p: np.ndarray, u_lo: float, u_hi: float) -> LuGreParams:
    """The 13 constants (Table I's form, laws in the input's unit) and the bench terms."""
    d = {k: float(p[j]) for j, k in enumerate(PHYS)}
    span = u_hi - u_lo
    vals: dict[str, float] = {"F0": d["F0"], "Ac": d["Ac"], "Bc": -abs(d["Bc"])}
    for k, name in zip(LINEAR_LAWS, ("sigma0", "sigma1", "sigma2", "Fs", "vs")):
        A = (d[k + "_hi"] - d[k + "_lo"]) / span
        vals[name + "A"] = A
        vals[name + "B"] = d[k + "_lo"] - A * u_lo
    vals.update(F_offset=d["F_offset"], k_x=d["k_x"], tau_input=d["tau_input"])
    vals.update({k: d[k] for k in EXTRAS})
    if vals["tau_input_fall"] == vals["tau_input"]:
        vals["tau_input_fall"] = 0.0  # one lag both ways: the set says so by leaving it off
    if vals["k_hys_pos"] == 0.0 and vals["k_hys_neg"] == 0.0:
        vals["x_hys"] = 0.0
    return LuGreParams(**vals)


def from_params(params: LuGreParams, u_lo: float, u_hi: float, m: float = 0.0) -> np.ndarray:
    """The inverse of :func:`to_params` (for simulating a given set)."""
    out = np.empty(len(PHYS))
    out[IDX["F0"]], out[IDX["Ac"]], out[IDX["Bc"]] = params.F0, params.Ac, abs(params.Bc)
    for k in LINEAR_LAWS:
        fn = getattr(params, k)
        out[IDX[k + "_lo"]], out[IDX[k + "_hi"]] = fn(u_lo), fn(u_hi)
    out[IDX["F_offset"]], out[IDX["k_x"]], out[IDX["tau_input"]], out[IDX["m"]] = (
        params.F_offset, params.k_x, params.tau_input, m)
    for k in EXTRAS:
        out[IDX[k]] = getattr(params, k)
    return out
