"""Forward LuGre model, eqs (1)–(3), with a stiff-stable integrator.

Why an exponential integrator: for a held velocity v and current I, eq (2)

    ż = v − a·z,   a = σ0(I)·|v| / g(v, I)  ≥ 0

is linear in z, so its exact solution over a step h is

    z(h) = z·e^{−a·h} + v·h·φ1(a·h),   φ1(x) = (1 − e^{−x}) / x.

At 0 A and |v| = 0.5 m/s, a·h ≈ 15 for h = 1 ms: explicit RK4 diverges there
(its stability edge is a·h ≈ 2.8), while this update is exact for any a·h and
cannot overshoot. Evaluating a at the mid-step velocity makes it second order
in the velocity's variation (tested against a fine-step reference in
``tests/test_lugre.py``).

Everything here is plain-float arithmetic for the 1 kHz hot path.
"""

from __future__ import annotations

import math
from typing import Final

from mrctl.model.params import _LANGEVIN_SERIES_BELOW, LuGreParams

# Below this a·h, φ1 and e^{-x} use their series (avoids 0/0 at v = 0).
_SMALL_AH: Final = 1e-8


def advance_z(z: float, v: float, a: float, h: float) -> float:
    """Exact solution of ż = v − a·z over h for constant v and a ≥ 0."""
    x = a * h
    if x < _SMALL_AH:
        return z * (1.0 - x) + v * h * (1.0 - 0.5 * x)
    e = math.exp(-x)
    return z * e + v * (1.0 - e) / a


def rate_coefficient(p: LuGreParams, v: float, I: float, Fc: float | None = None) -> float:
    """a = σ0(I)·|v| / g(v, I) (1/s), the relaxation rate of z in eq (2)."""
    return p.sigma0(I) * abs(v) / p.g(v, I, Fc)


def force(p: LuGreParams, z: float, v: float, I: float) -> float:
    """Damper force F (N), eq (1), with ż from eq (2) at the same (z, v, I)
    (σ1 weighted by exp(−(v/v_d)²) when the set has ``sigma1_vd``)."""
    Fc = p.Fc(I)
    s0 = p.sigma0(I)  # each law, the paper's or the table's (LuGreParams)
    r = v / p.vs(I)
    g = Fc + (p.Fs(I) - Fc) * math.exp(-r * r)
    zdot = v - s0 * abs(v) * z / g
    if p.sigma1_vd > 0.0:
        zdot *= math.exp(-(v / p.sigma1_vd) ** 2)
    return s0 * z + p.sigma1(I) * zdot + p.sigma2(I) * v


class LuGreModel:
    """The forward model with its state z (m), stepped once per tick.

    Tick protocol (shared with the inverse laws so that, with no driver lag,
    the inverse's z equals the plant's bit for bit):

    1. ``advance(v, I_held, dt)``: integrate z from the previous tick to now,
       the current held at the value applied over that interval and the
       velocity taken at mid-interval (mean of previous and present v);
    2. ``force(v, I)``: the force with the current applied at this tick.

    The coefficients for the last current seen (eq 6 costs a tanh) are cached:
    per tick a plant or a law asks twice about the same current.

    The set's optional terms (:class:`LuGreParams`) act here when on: the
    bristle damping's weight exp(−(v/v_d)²) on ż (:meth:`zdot`, :meth:`force`), and the
    hysteretic stiffness's state ``zh`` (m), advanced with z by the same
    exact step, its force k_hys·zh in :meth:`force` (:meth:`hys_force`
    alone; a table's per-level stiffness at the present current). Off, each
    costs one comparison and changes no bit.
    """

    __slots__ = ("p", "z", "v_prev", "substeps", "_I", "_Fc", "_s0", "_s1", "_s2", "_Fs", "_vs",
                 "zh", "_vd2", "_hys", "_xh", "_kp", "_kn")

    def __init__(self, params: LuGreParams, z0: float = 0.0, v0: float = 0.0, substeps: int = 1) -> None:
        if substeps < 1:
            raise ValueError("substeps must be >= 1")
        self.p = params
        self.z = z0
        self.v_prev = v0
        self.substeps = substeps
        self.zh = 0.0  # the hysteretic stiffness's state (m)
        vd = params.sigma1_vd
        self._vd2 = 1.0 / (vd * vd) if vd > 0.0 else 0.0  # 1/v_d² (0: sigma1 constant)
        self._hys = params.has_hysteresis
        self._xh = params.x_hys
        self._kp = params.k_hys_pos
        self._kn = params.k_hys_neg
        self._set_current(0.0)

    def reset(self, z0: float = 0.0, v0: float = 0.0) -> None:
        self.z = z0
        self.v_prev = v0
        self.zh = 0.0

    def hys_force(self, v: float) -> float:
        """The hysteretic stiffness's force (N) at the present zh for velocity v (0.0 when off)."""
        if not self._hys:
            return 0.0
        return (self._kn if v < 0.0 else self._kp) * self.zh

    def _advance_hys(self, v0: float, v: float, dt: float) -> None:
        """zh from the previous tick to this one: ż_h = v − |v|·zh/x_hys, exact for the mid-step velocity."""
        vm = 0.5 * (v0 + v)
        xh = self._xh
        x = abs(vm) * dt / xh
        if x < _SMALL_AH:
            self.zh = self.zh * (1.0 - x) + vm * dt * (1.0 - 0.5 * x)
        else:
            e = math.exp(-x)
            self.zh = self.zh * e + (xh if vm > 0.0 else -xh) * (1.0 - e)

    def _set_current(self, I: float) -> None:
        p = self.p
        self._I = I
        table = p.table
        if table is not None:  # laws: table (one branch per change of current)
            self._Fc = table.value(0, I)
            self._Fs = table.value(1, I)
            self._s0 = table.value(2, I)
            self._s1 = table.value(3, I)
            self._s2 = table.value(4, I)
            self._vs = table.value(5, I)
            if table.has_hys():  # the hysteretic stiffness per level, at this input
                self._kp = table.value(8, I)
                self._kn = table.value(9, I)
            return
        Bc = p.Bc
        x = I / Bc if Bc != 0.0 else math.inf
        if -_LANGEVIN_SERIES_BELOW < x < _LANGEVIN_SERIES_BELOW or Bc == 0.0:
            self._Fc = p.Fc(I)  # series branch and degenerate fits: the reference code
        else:
            # eq (6) inlined: this runs every tick. coth from exp, which the compiled
            # build calls natively (math.tanh would be a Python call there)
            e = math.exp(-2.0 * abs(x))
            c = (1.0 + e) / (1.0 - e)
            L = (c if x > 0.0 else -c) - 1.0 / x
            self._Fc = p.Ac * L * L + p.F0
        self._s0 = p.sigma0A * I + p.sigma0B
        self._s1 = p.sigma1A * I + p.sigma1B
        self._s2 = p.sigma2A * I + p.sigma2B
        self._Fs = p.FsA * I + p.FsB
        self._vs = p.vsA * I + p.vsB

    def advance(self, v: float, I: float, dt: float) -> float:
        """Move z from the previous tick to this one; returns the new z."""
        if I != self._I:
            self._set_current(I)
        Fc = self._Fc
        dFs = self._Fs - Fc
        s0 = self._s0
        vs = self._vs
        v0 = self.v_prev
        self.v_prev = v
        if self._hys:
            self._advance_hys(v0, v, dt)
        z = self.z
        n = self.substeps
        if n == 1:
            vm = 0.5 * (v0 + v)
            r = vm / vs
            a = s0 * abs(vm) / (Fc + dFs * math.exp(-r * r))
            x = a * dt
            if x < _SMALL_AH:
                z = z * (1.0 - x) + vm * dt * (1.0 - 0.5 * x)
            else:
                e = math.exp(-x)
                z = z * e + vm * (1.0 - e) / a
        else:
            h = dt / n
            for k in range(n):
                vm = v0 + (v - v0) * ((k + 0.5) / n)
                r = vm / vs
                z = advance_z(z, vm, s0 * abs(vm) / (Fc + dFs * math.exp(-r * r)), h)
        self.z = z
        return z

    def look_ahead(self, v: float, dv: float, I: float, dI: float, dt: float, probe: LuGreModel,
                   out: list[float], out1: list[float]) -> None:
        """The forces (N) of the next ``len(out)`` ticks from the present state
        (left as it is), the velocity going on by dv per tick: into ``out``
        with the current held at I, into ``out1`` at I + dI (``probe`` holds
        the coefficients for it; ``out1`` as long as ``out``). The closed
        law's horizon and its finite difference in I: one call and no list
        per tick; each trajectory is bit for bit what ``advance`` then
        ``force`` give tick by tick with ``substeps`` 1 (the laws' models;
        this one step per tick whatever ``substeps`` says), less the
        hysteretic stiffness's force, which the closed law holds over its
        horizon (it does not depend on I)."""
        if I != self._I:
            self._set_current(I)
        Fc = self._Fc
        dFs = self._Fs - Fc
        s0, s1, s2, vs = self._s0, self._s1, self._s2, self._vs
        z = self.z
        I1 = I + dI
        if I1 != probe._I:
            probe._set_current(I1)
        Fc1 = probe._Fc
        dFs1 = probe._Fs - Fc1
        t0, t1, t2, ws = probe._s0, probe._s1, probe._s2, probe._vs
        vd2 = self._vd2
        y = z
        for j in range(len(out)):
            v1 = v + dv
            vm = 0.5 * (v + v1)
            avm = abs(vm)
            av1 = abs(v1)
            r = vm / vs
            a = s0 * avm / (Fc + dFs * math.exp(-r * r))
            x = a * dt
            if x < _SMALL_AH:
                z = z * (1.0 - x) + vm * dt * (1.0 - 0.5 * x)
            else:
                e = math.exp(-x)
                z = z * e + vm * (1.0 - e) / a
            r = vm / ws
            a = t0 * avm / (Fc1 + dFs1 * math.exp(-r * r))
            x = a * dt
            if x < _SMALL_AH:
                y = y * (1.0 - x) + vm * dt * (1.0 - 0.5 * x)
            else:
                e = math.exp(-x)
                y = y * e + vm * (1.0 - e) / a
            w = math.exp(-v1 * v1 * vd2) if vd2 > 0.0 else 1.0  # sigma1's weight (1.0: exact, no bit moves)
            r = v1 / vs
            out[j] = s0 * z + s1 * ((v1 - s0 * av1 * z / (Fc + dFs * math.exp(-r * r))) * w) + s2 * v1
            r = v1 / ws
            out1[j] = t0 * y + t1 * ((v1 - t0 * av1 * y / (Fc1 + dFs1 * math.exp(-r * r))) * w) + t2 * v1
            v = v1

    def zdot(self, v: float, I: float) -> float:
        """ż (m/s) from eq (2) at the present z, velocity v and current I, as
        σ1 sees it: weighted by exp(−(v/v_d)²) when the set has ``sigma1_vd``
        (as in :meth:`force`)."""
        if I != self._I:
            self._set_current(I)
        Fc = self._Fc
        r = v / self._vs
        zdot = v - self._s0 * abs(v) * self.z / (Fc + (self._Fs - Fc) * math.exp(-r * r))
        vd2 = self._vd2
        if vd2 > 0.0:
            zdot *= math.exp(-v * v * vd2)
        return zdot

    def force(self, v: float, I: float) -> float:
        """Force (N) at the present state for velocity v (m/s) and current I (A),
        the hysteretic stiffness's included."""
        if I != self._I:
            self._set_current(I)
        Fc = self._Fc
        s0 = self._s0
        z = self.z
        r = v / self._vs
        zdot = v - s0 * abs(v) * z / (Fc + (self._Fs - Fc) * math.exp(-r * r))
        vd2 = self._vd2
        if vd2 > 0.0:
            zdot *= math.exp(-v * v * vd2)
        F = s0 * z + self._s1 * zdot + self._s2 * v
        if self._hys:
            F += (self._kn if v < 0.0 else self._kp) * self.zh
        return F
