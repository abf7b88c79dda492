"""Inverse laws: the coil current (A) that makes the damper produce F_des (N).

Each law keeps its own copy of the LuGre state z, advanced with the current it
commanded on the previous tick (the tick protocol of
:class:`mrctl.model.lugre.LuGreModel`), and is called once per tick with the
measured velocity and the desired force. All laws return a current already in
[0, I_max]; :mod:`mrctl.core.safety` clamps again, independently.

Laws, by the name used in YAML (``inverse.law``):

``paper``
    Eq (12) exactly as published: Fc lagged one sample, ż computed with the
    previous current, then clamped. Its denominator ∂F/∂I (with ż frozen)
    crosses zero when the force changes sign, hence the current spikes.
``smooth``
    The improved law (see :class:`SmoothInverse`): eq (12)'s force model,
    solved as a regularised least-squares problem that holds the current
    where ∂F/∂I vanishes, inside the driver's slew bound. No spikes; the
    design study and measured figures are in ``docs/inverse-laws.md``.
    With a coil lag (``tau_input`` of the parameter set, or ``lag_s``) it
    solves for the current the coil should carry and commands what makes
    the coil reach it (:func:`lag_gains`).
``closed`` (:mod:`mrctl.laws.closed`)
    ``smooth`` as feed-forward plus the model error measured by the load
    cell.
``constant``
    A fixed current, open loop.
``schedule``
    A staircase of constant currents, open loop: the identification runs of
    the paper's Section III (one current per segment), 0 A after the last.
"""

from __future__ import annotations

from mypy_extensions import mypyc_attr

import math
from typing import Any

from mrctl.laws.base import CurrentLaw, InverseLaw, LawContext, Measurement
from mrctl.model.lugre import LuGreModel
from mrctl.model.params import LuGreParams, ThetaTable
from mrctl.util.schema import Custom, Num, check_num


def lag_gains(tau_s: float, horizon_s: float, dt: float) -> tuple[float, float]:
    """(a1, 1/ah) for a first-order coil lag τ sampled every dt.

    The coil's current follows a held command c as I ← I + a1·(c − I) per
    tick, a1 = 1 − e^(−dt/τ). Commanding c = I + (I* − I)/ah, with
    ah = 1 − e^(−h/τ), makes the coil reach the target I* after the horizon
    h (if the command is held): h = dt is dead-beat, a longer horizon asks
    for smaller steps. τ = 0: (1, 1), an ideal coil, no compensation."""
    if not tau_s > 0.0:
        return 1.0, 1.0
    h = max(horizon_s, dt)
    return 1.0 - math.exp(-dt / tau_s), 1.0 / (1.0 - math.exp(-h / tau_s))


_LAG_PARAMS = {
    "lag_s": Num(default=None, optional=True, min=0.0, max=1.0,
                 doc="coil lag to compensate (s); null = the parameter set's tau_input + tau_field (tau_input_fall "
                     "+ tau_field while the current falls), 0 = none"),
    "lag_horizon_s": Num(default=0.003, min=0.0, min_exclusive=True, max=1.0,
                         doc="with a lag: command what brings the coil to its target this long after (s)"),
}


@mypyc_attr(allow_interpreted_subclasses=True)
class _ModelBasedLaw(InverseLaw):
    """Shared state handling: the law's own LuGre model and previous current."""

    def __init__(self, params: LuGreParams, I_max: float, dt: float) -> None:
        if not I_max > 0.0:
            raise ValueError("I_max must be > 0")
        if not dt > 0.0:
            raise ValueError("dt must be > 0")
        self.p = params
        self.I_max = float(I_max)
        self.dt = float(dt)
        # compiled (mypyc), self.model.advance(...) is a native call; a bound
        # method kept in an attribute would be a Python call
        self.model = LuGreModel(params)
        self.I_prev = 0.0
        self._started = False
        # the paper's affine form ((σ0A, σ1A, σ2A), (σ0B, σ1B, σ2B)), built once, not per tick
        self._AB = ((params.sigma0A, params.sigma1A, params.sigma2A), (params.sigma0B, params.sigma1B, params.sigma2B))
        self._Fo = params.F_offset
        self._kx = params.k_x
        # laws: table: ∂Θ/∂I of the segment around the previous current, and the
        # per-level bench terms when the table has them (None: the paper's laws)
        self._table: ThetaTable | None = params.table
        self._tbench = params.table is not None and params.table.has_bench()
        # the optional terms act in the model: σ1's weight exp(-(v/v_d)²) in its zdot(), the hysteretic
        # stiffness's force from its hys_force() (independent of I: subtracted from the demand, as the
        # bench terms are; 0.0 when off)

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "_ModelBasedLaw":
        return cls(ctx.params, ctx.I_max, ctx.dt, **{k: cfg.get(k) for k in cls.params})

    def reset(self, I0: float = 0.0, z0: float = 0.0, v0: float = 0.0) -> None:
        self.model.reset(z0, v0)
        self.I_prev = I0
        self._started = False

    def applied(self, I: float) -> None:
        self.I_prev = I

    def _bench(self, I: float, x: float) -> float:
        """The force around the friction (N) at input I: the set's F_offset + k_x·x,
        or the table's per-level terms; 0.0 without either (x is not read then)."""
        table = self._table
        if table is not None and self._tbench:
            return table.bench_force(I, x)
        if self._kx != 0.0 or self._Fo != 0.0:
            return self._Fo + self._kx * x
        return 0.0

    def _slopes(self, I: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """((σ0A, σ1A, σ2A), (σ0B, σ1B, σ2B)): the laws' affine form around the input I."""
        table = self._table
        if table is None:
            return self._AB
        a0, b0 = table.local(2, I)
        a1, b1 = table.local(3, I)
        a2, b2 = table.local(4, I)
        return (a0, a1, a2), (b0, b1, b2)

    def _advance(self, v: float) -> float:
        """Step 3 of eq (12): move z to now with the previous current."""
        if self._started:
            return self.model.advance(v, self.I_prev, self.dt)
        return self._first(v)

    def _first(self, v: float) -> float:
        """First tick: no interval has elapsed; anchor the velocity history."""
        self._started = True
        self.model.v_prev = v
        return self.model.z


@mypyc_attr(allow_interpreted_subclasses=True)
class PaperInverse(_ModelBasedLaw):
    """Eq (12) as published (Palka & Maślanka 2013), then clamped to [0, I_max]."""

    name = "paper"
    summary = "eq (12) as published: spikes where the force changes sign"

    def current(self, m: Measurement, F_des: float) -> float:
        v = m.v
        Ip = self.I_prev
        F_des -= self._bench(Ip, m.x)
        (s0A, s1A, s2A), (s0B, s1B, s2B) = self._slopes(Ip)
        z = self.model.advance(v, Ip, self.dt) if self._started else self._first(v)  # step 3: z with I_{i-1}
        # steps 1-2: Fc(I_{i-1}) (F0 at 0 A) inside g, and ż from eq (2)
        zdot = self.model.zdot(v, Ip)
        F_des -= self.model.hys_force(v)
        num = F_des - (s0B * z + s1B * zdot + s2B * v)
        den = s0A * z + s1A * zdot + s2A * v
        if den != 0.0:
            I = num / den
        else:  # the published law divides by zero here: ±inf, or NaN for 0/0
            I = math.inf if num > 0.0 else (-math.inf if num < 0.0 else math.nan)
        # clamp to [0, I_max], NaN → 0 A (safety.clamp_current, inlined: every tick)
        I = (I if I < self.I_max else self.I_max) if I > 0.0 else 0.0
        self.I_prev = I
        return I


@mypyc_attr(allow_interpreted_subclasses=True)
class SmoothInverse(_ModelBasedLaw):
    """Regularised, slew-bounded eq (12): the spike-free law.

    Why eq (12) spikes: with ż frozen at the previous current the force is
    affine in the new current, F(I) = B + D·I, where D = σ0A·z + σ1A·ż + σ2A·v
    is ∂F/∂I. Near a sign change of the force, z, ż and v all pass through
    zero, so D does too, and because σ1 < 0 below 0.26 A it even goes
    *negative*: the fitted model then claims more current gives less force,
    and eq (12) jumps to I_max to exploit it, or flips between 0 and I_max as
    D changes sign. Neither helps a real damper.

    This law picks the current that minimises

        (B + D·I − F_des)² + ε²·(I − I_prev)²

    over I in [I_prev − ΔI, I_prev + ΔI] ∩ [0, I_max], i.e.

        I = (D·(F_des − B) + ε²·I_prev) / (D² + ε²),  then bounded.

    Where |D| ≫ ε (N/A) it is eq (12); where the damper has no authority
    (|D| → 0) the current holds instead of jumping. ΔI = slew·dt is the
    current driver's slew rate taken into the law, so the law never asks for
    a step the coil could not follow. Measured alternatives (solving the full
    model for I, evaluating ż at the new current, either term alone) are in
    ``docs/inverse-laws.md``; both terms are needed to beat eq (12).
    """

    name = "smooth"
    summary = "eq (12) regularised toward the previous current, inside the driver's slew bound"
    params = {
        "eps_N_per_A": Num(default=3.0, min=0.0, max=1e4, doc="regularisation: hold where dF/dI is below this (N/A)"),
        "max_slew_A_per_s": Num(default=50.0, min=0.0, min_exclusive=True, max=1e6,
                                doc="driver slew rate the law respects (A/s)"),
        **_LAG_PARAMS,
    }

    def __init__(
        self,
        params: LuGreParams,
        I_max: float,
        dt: float,
        eps_N_per_A: float = 3.0,
        max_slew_A_per_s: float = 50.0,
        lag_s: float | None = None,
        lag_horizon_s: float = 0.003,
    ) -> None:
        super().__init__(params, I_max, dt)
        if not eps_N_per_A >= 0.0:
            raise ValueError("eps_N_per_A must be >= 0")
        if not max_slew_A_per_s > 0.0:
            raise ValueError("max_slew_A_per_s must be > 0")
        # the set's lag from the command to the field: the driver's, then the damper's own (tau_field), taken
        # as one first-order lag of their sum (the same mean delay)
        tau = params.tau_input + params.tau_field if lag_s is None else lag_s
        if not (tau >= 0.0 and lag_horizon_s > 0.0):
            raise ValueError("lag_s must be >= 0 and lag_horizon_s > 0")
        self.eps2 = float(eps_N_per_A) ** 2
        self.max_step_A = float(max_slew_A_per_s) * self.dt
        #: coil lag compensated (s), and its per-tick gains (lag_gains); while the coil's current
        #: falls, the set's tau_input_fall (lag_s given: the same both ways)
        self.lag_s = float(tau)
        self.lag_fall_s = float(params.tau_fall() + params.tau_field if lag_s is None else tau)
        self._a1, self._inv_ah = lag_gains(self.lag_s, lag_horizon_s, self.dt)
        self._a1f, self._inv_ahf = lag_gains(self.lag_fall_s, lag_horizon_s, self.dt)
        self.I_coil = 0.0  # the coil's current at the last tick, as the lag model has it
        self._I_coil0 = 0.0  # ... and before that tick's command

    def reset(self, I0: float = 0.0, z0: float = 0.0, v0: float = 0.0) -> None:
        super().reset(I0, z0, v0)
        self.I_coil = self._I_coil0 = I0

    def _lag_gain(self, I: float, I0: float) -> float:
        """The lag model's per-tick gain for a command I to a coil at I0: the rise's, or the fall's."""
        return self._a1 if I >= I0 else self._a1f

    def applied(self, I: float) -> None:
        self.I_prev = I
        I0 = self._I_coil0
        self.I_coil = I0 + self._lag_gain(I, I0) * (I - I0)

    def current(self, m: Measurement, F_des: float) -> float:
        if self._a1 != 1.0 or self._a1f != 1.0:
            return self._current_lagged(m, F_des)
        v = m.v
        Ip = self.I_prev
        F_des -= self._bench(Ip, m.x)
        (s0A, s1A, s2A), (s0B, s1B, s2B) = self._slopes(Ip)
        z = self.model.advance(v, Ip, self.dt) if self._started else self._first(v)
        zdot = self.model.zdot(v, Ip)  # as in eq (12): ż with the previous current
        F_des -= self.model.hys_force(v)
        B = s0B * z + s1B * zdot + s2B * v
        D = s0A * z + s1A * zdot + s2A * v
        den = D * D + self.eps2
        # den == 0 only when ε = 0 and D = 0: no authority, hold.
        I = (D * (F_des - B) + self.eps2 * Ip) / den if den > 0.0 else Ip
        step = self.max_step_A
        if I > Ip + step:
            I = Ip + step
        elif I < Ip - step:
            I = Ip - step
        # clamp to [0, I_max] (NaN → 0 A), inlined: this runs every tick
        I = (I if I < self.I_max else self.I_max) if I > 0.0 else 0.0
        self.I_prev = I
        return I

    def _current_lagged(self, m: Measurement, F_des: float) -> float:
        """The same solve for the coil's current Ic (the model's z moves with
        it, as the damper's does), then the command that brings the coil
        there within the horizon, inside the slew bound around the previous
        command."""
        v = m.v
        Ia = self.I_coil
        F_des -= self._bench(Ia, m.x)
        (s0A, s1A, s2A), (s0B, s1B, s2B) = self._slopes(Ia)
        z = self.model.advance(v, Ia, self.dt) if self._started else self._first(v)
        zdot = self.model.zdot(v, Ia)
        F_des -= self.model.hys_force(v)
        B = s0B * z + s1B * zdot + s2B * v
        D = s0A * z + s1A * zdot + s2A * v
        den = D * D + self.eps2
        It = (D * (F_des - B) + self.eps2 * Ia) / den if den > 0.0 else Ia
        I = Ia + (It - Ia) * (self._inv_ah if It >= Ia else self._inv_ahf)
        Ip, step = self.I_prev, self.max_step_A
        if I > Ip + step:
            I = Ip + step
        elif I < Ip - step:
            I = Ip - step
        I = (I if I < self.I_max else self.I_max) if I > 0.0 else 0.0
        self.I_prev = I
        self._I_coil0 = Ia
        self.I_coil = Ia + self._lag_gain(I, Ia) * (I - Ia)
        return I


@mypyc_attr(allow_interpreted_subclasses=True)
class ConstantCurrent(CurrentLaw):
    """Open loop: always the same current (identification runs)."""

    name = "constant"
    summary = "a fixed current, open loop"
    params = {"current_A": Num(min=0.0, doc="the current (A), <= safety.I_max")}

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "ConstantCurrent":
        return cls(cfg.current_A, ctx.I_max)

    @classmethod
    def check(cls, cfg: Any, ctx: LawContext) -> list[str]:
        cur = cfg.get("current_A")
        if isinstance(cur, float) and cur > ctx.I_max:
            return [f"current_A: {cur:g} A exceeds safety.I_max = {ctx.I_max:g} A"]
        return []

    def __init__(self, I: float, I_max: float) -> None:
        if not 0.0 <= I <= I_max:
            raise ValueError(f"constant current {I} A outside [0, {I_max}] A")
        self.I = float(I)
        self.I_max = float(I_max)

    def current(self, m: Measurement, F_des: float) -> float:
        return self.I


def _current_list(value: Any, path: str) -> tuple[Any, list[str]]:
    if not isinstance(value, list) or not value:
        return None, [f"{path}: must be a non-empty list of currents (A)"]
    out, errors = [], []
    for i, v in enumerate(value):
        num, errs = check_num(Num(min=0.0), v, f"{path}[{i}]")
        out.append(num)
        errors += errs
    return out, errors


@mypyc_attr(allow_interpreted_subclasses=True)
class ScheduleCurrent(CurrentLaw):
    """Open-loop staircase: ``currents_A[i]`` for ticks in [i·step, (i+1)·step), then 0 A.

    Counts its own ticks (one call per tick), so it needs no clock."""

    name = "schedule"
    summary = "a staircase of constant currents, open loop (identification runs)"
    params = {
        "currents_A": Custom(_current_list, doc="list of currents (A), each held step_s, then 0 A"),
        "step_s": Num(min=0.0, min_exclusive=True, doc="time per current (s)"),
    }

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "ScheduleCurrent":
        return cls(cfg.currents_A, cfg.step_s, ctx.I_max, ctx.dt)

    @classmethod
    def check(cls, cfg: Any, ctx: LawContext) -> list[str]:
        return [f"currents_A[{i}]: {cur:g} A exceeds safety.I_max = {ctx.I_max:g} A"
                for i, cur in enumerate(cfg.get("currents_A") or []) if isinstance(cur, float) and cur > ctx.I_max]

    def __init__(self, currents_A: list[float], step_s: float, I_max: float, dt: float) -> None:
        if not currents_A:
            raise ValueError("currents_A must not be empty")
        for I in currents_A:
            if not 0.0 <= I <= I_max:
                raise ValueError(f"scheduled current {I} A outside [0, {I_max}] A")
        self.currents_A = [float(I) for I in currents_A]
        self.ticks_per_step = max(1, int(round(step_s / dt)))
        self.I_max = float(I_max)
        self.k = 0

    def reset(self, I0: float = 0.0) -> None:
        self.k = 0

    def current(self, m: Measurement, F_des: float) -> float:
        i = self.k // self.ticks_per_step
        self.k += 1
        return self.currents_A[i] if i < len(self.currents_A) else 0.0
