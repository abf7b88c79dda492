"""Two small laws on mrctl's law API (mrctl.laws.base).

``force_pi`` (an inverse law): the current that makes the load cell read
F_des, by feedback on the measured force, which the API hands every law:

    I = ff·|F_des| + kp·e + ki·∫e dt,   e = (F_des − F)·sign(v)

A damper's force grows with the current only in the direction it already
has (the sign of v), so the error is taken along it. The integrator is
clamped to [0, I_max] (anti-windup) and follows what safety actually
commanded (``applied``).

``sine_force`` (a demand law): F_des = amplitude·sin(2π·f·t + phase).

Rules of the 1 kHz path (docs/laws.md): plain floats, no I/O, no logging,
no allocation, no numpy scalars; return a finite current in [0, I_max].
"""

from __future__ import annotations

import math
from typing import Any

from mrctl.laws.base import DemandLaw, InverseLaw, LawContext, Measurement
from mrctl.util.schema import Num


class ForcePI(InverseLaw):
    """Force-feedback PI on the load cell, with a feedforward per newton."""

    name = "force_pi"
    summary = "example plugin: PI on the load cell's force error (mrctl-law-example)"
    params = {
        "kp_A_per_N": Num(default=0.004, min=0.0, max=1.0, doc="proportional gain (A/N)"),
        "ki_A_per_Ns": Num(default=0.5, min=0.0, max=1e3, doc="integral gain (A/(N·s))"),
        "ff_A_per_N": Num(default=0.01, min=0.0, max=1.0, doc="feedforward: current per newton of |F_des| (A/N)"),
    }

    def __init__(self, I_max: float, dt: float, kp_A_per_N: float, ki_A_per_Ns: float, ff_A_per_N: float) -> None:
        self.I_max = float(I_max)
        self.dt = float(dt)
        self.kp = float(kp_A_per_N)
        self.ki_dt = float(ki_A_per_Ns) * self.dt
        self.ff = float(ff_A_per_N)
        self.integ = 0.0

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "ForcePI":
        return cls(ctx.I_max, ctx.dt, cfg.kp_A_per_N, cfg.ki_A_per_Ns, cfg.ff_A_per_N)

    def reset(self, I0: float = 0.0) -> None:
        self.integ = I0  # a hot swap starts from the current the coil carries

    def current(self, m: Measurement, F_des: float) -> float:
        F = m.F
        if F != F:  # no load cell: feedforward only
            F = F_des
        e = (F_des - F) if m.v >= 0.0 else (F - F_des)
        integ = self.integ + self.ki_dt * e
        I_max = self.I_max
        integ = 0.0 if integ < 0.0 else (I_max if integ > I_max else integ)
        self.integ = integ
        I = self.ff * (F_des if F_des >= 0.0 else -F_des) + self.kp * e + integ
        return 0.0 if I < 0.0 else (I_max if I > I_max else I)

    def applied(self, I: float) -> None:
        if self.integ > I:
            self.integ = I


class SineForce(DemandLaw):
    """F_des = amplitude·sin(2π·f·t + phase)."""

    name = "sine_force"
    summary = "example plugin: F_des = amplitude·sin(2π f t + phase) (mrctl-law-example)"
    params = {
        "amplitude_N": Num(min=0.0, max=1e4, doc="force amplitude (N)"),
        "frequency_hz": Num(min=0.0, min_exclusive=True, max=500.0, doc="frequency (Hz)"),
        "phase_rad": Num(default=0.0, doc="phase at t = 0 (rad)"),
    }

    # no from_config: the default builds cls(ctx, **the section's keys)
    def __init__(self, ctx: LawContext, amplitude_N: float, frequency_hz: float, phase_rad: float) -> None:
        self.A = float(amplitude_N)
        self.w = 2.0 * math.pi * float(frequency_hz)
        self.phase = float(phase_rad)

    def force(self, m: Measurement) -> float:
        return self.A * math.sin(self.w * m.t + self.phase)
