"""``closed``: the smooth inverse as feed-forward, corrected by the load cell.

Every damper differs from its identified model: parameters off by tens of
per cent, a coil that lags, a structure the model does not have. The
``smooth`` law inverts the model and cannot see any of it; the load cell
most benches carry can. Each tick this law

1. **estimates the model error** from the load cell, which reads the force
   of the previous tick, with an alpha-beta tracker (a level d̂ and its
   slope ṡ, so an error that ramps is followed without lag):

       d̂ ← d̂ + ṡ,  u = (F_meas − F_model) − d̂,  d̂ ← d̂ + g·u,  ṡ ← ṡ + β·u

   β = ``correction_ramp``·(4 − 2g − 4√(1−g)) (1: critically damped, 0:
   first order). The gain is g = g_min + (g_max − g_min)·p̂/(p̂ + r̂), with
   g_min, g_max = 1 − e^(−2π·f·dt) at f = ``correction_min_hz`` (10 Hz) and
   ``correction_hz`` (40 Hz), and p̂/(p̂ + r̂) the share of the model error in
   what the load cell says: r̂, the load cell's white
   noise, is half the mean square of the tick-to-tick difference of
   F_meas − F_model (a smooth model error hardly adds to it), p̂ the mean
   square of that error less r̂, both over ~0.5 s. A noisy load cell on a
   model that is right gets the slow correction; a large model error the
   fast one. F_model is the law's own LuGre model's force at the previous tick
   *for the current the coil actually carried then* (the command actually
   sent, through the lag model). That is integral action on the tracking
   error whose anti-windup knows the damper is semi-active: it compares
   the measurement with the model at the *applied* current, saturated at
   0 A or I_max or held by the slew bound, not with the force demanded, so
   an out-of-reach demand does not wind it up. When the load cell reads a
   force on the wrong side of the demand, short of what the model expected
   by more than ``guard_N`` (after a reversal, a damper whose hysteresis
   swings slower than the model's), no current can help: a semi-active
   damper cannot push, and more current only stiffens the force it has.
   Then d̂ holds and the coil's current ramps down at the slew bound.
   |d̂| ≤ ``correction_max_N``, against a broken load cell;
2. **solves for the coil's current** as ``smooth`` does, on F_des − d̂, over
   a short horizon: the current I, held for ``horizon_ticks`` more ticks,
   that minimises

       Σ_{j=0..H} (F_j(I) − F_des,j)² + ε²·(I − I_coil)²

   with F_j the model's force j ticks ahead (its state advanced with I,
   velocity and demand extrapolated, linearised in I by a finite
   difference). H = 0 is ``smooth``'s one-tick solve; looking 2 ms ahead
   damps the current oscillation after a reversal that the one-tick solve
   shows at low forces (docs/inverse-laws.md);
3. **compensates the coil lag** (``lag_s``, default the parameter set's
   ``tau_input``): commands what brings the coil to that current within
   ``lag_horizon_s`` (:func:`mrctl.laws.inverse.lag_gains`), inside the
   slew bound around the previous command and clamped to [0, I_max].

4. **learns from one velocity reversal to the next** (``reversal_learning``).
   A damper whose hysteresis differs from the model's errs the same way after
   every reversal, and a correction that only looks back cannot anticipate
   it. Reversals are found on the velocity (hysteresis ``reversal_v_mps``,
   so motion need not be periodic); the ticks around each (8 before it,
   predicted from the velocity and its slope, and 56 after) index two small
   tables per direction of the new motion, updated only from the load cell
   of past reversals:

   - the *reversal table* (N): in each bin, the tracking error F_meas − F_des
     it saw, added at ``reversal_rate`` × p̂/(p̂ + r̂) to the bin of the
     command ``reversal_lead_ticks`` before (an iterative-learning update,
     slowed by the load cell's noise share). Not where the force opposed the
     demand (no current helps there), nor where the guard or the guard table
     acted, nor where the command was held at 0 A, I_max or the slew bound
     with the error asking for more of the same;
     bounded by ``correction_max_N``. Its value for the present bin is added
     to d̂ in the solve;
   - the *guard table*: in each bin, the average of "the guard fired". Where
     it and the bin before are ≥ 0.5 ``reversal_lead_ticks`` ahead, the
     current ramps down now, ahead of the guard (kept armed while the force
     still opposes the demand there).

   Without a load cell nothing is learned and both fade like d̂; ``reset()``
   empties them. Plain lists, a few float operations per call.

The previous command is read from the measurement (``m.I_cmd``: what the
controller sent, 0 A during a safety fault) and ticks skipped since the
last call from ``m.k``, so after a fault the current ramps up from 0 A
within the slew bound and the lag model follows what the coil got.

A reading identical to the previous one (a sample the safety supervisor
holds over a link error) says nothing new and leaves d̂ alone.

No load cell (F is NaN): d̂ decays to 0 at the rate g_max, and the law is
feed-forward alone. It counts those ticks; :meth:`notices` reports them
once, after the run (nothing is printed or logged from the 1 kHz path).

Design and measured figures: ``docs/inverse-laws.md``.
"""

from __future__ import annotations

import math
from typing import Final

from mypy_extensions import mypyc_attr

from mrctl.laws.base import Measurement
from mrctl.laws.inverse import SmoothInverse
from mrctl.model.lugre import LuGreModel
from mrctl.model.params import LuGreParams
from mrctl.util.schema import Bool, Num

__all__ = ["ClosedLoopInverse"]

#: finite-difference step for the horizon's ∂F/∂I (A)
_DI: Final = 0.02
#: time constant of the velocity and demand slopes used to extrapolate (s)
_SLOPE_S: Final = 0.005
#: time constant of the load-cell noise and model-error power estimates (s)
_NOISE_S: Final = 0.5
#: bins of the reversal table (ticks after a velocity reversal), per direction
_REV_BINS: Final = 64
#: of which before the reversal (predicted from the velocity and its slope)
_PRE: Final = 8
#: length of the ring of the last commands' bins (> the largest reversal_lead_ticks)
_HIST: Final = 11
#: learning rate of the guard table (one reversal on which the guard fires arms it)
_GUARD_RATE: Final = 0.5
#: a bin acts ahead when it and the bin before it are at least this (noise rarely fires twice in a row)
_GUARD_ARM: Final = 0.5


@mypyc_attr(allow_interpreted_subclasses=True)
class ClosedLoopInverse(SmoothInverse):
    """Smooth inverse + load-cell model-error estimate (integral action with
    semi-active anti-windup) + short horizon + coil-lag compensation."""

    name = "closed"
    summary = "smooth inverse as feed-forward plus the model error the load cell measures, coil lag compensated"
    params = {
        **SmoothInverse.params,
        "correction_hz": Num(default=40.0, min=0.0, min_exclusive=True, max=200.0,
                             doc="bandwidth of the load-cell correction (Hz) where the model error dominates "
                                 "the load cell's noise: faster follows model error better"),
        "correction_min_hz": Num(default=10.0, min=0.0, min_exclusive=True, max=200.0,
                                 doc="bandwidth of the correction (Hz) where the load cell's noise dominates the "
                                     "model error (≤ correction_hz)"),
        "correction_ramp": Num(default=0.5, min=0.0, max=1.0,
                               doc="slope term of the correction, as a share of the critically damped "
                                   "alpha-beta gain (0: first order)"),
        "correction_max_N": Num(default=25.0, min=0.0, min_exclusive=True, max=1e5,
                                doc="bound of the correction (N), against a broken or miswired load cell"),
        "guard_N": Num(default=0.15, min=0.0, max=1e4,
                       doc="a measured force on the wrong side of the demand, and short of the model's by more "
                           "than this (N), holds the correction and ramps the current down"),
        "horizon_ticks": Num(default=2, integer=True, min=0, max=5,
                             doc="ticks ahead the solve looks, the current held (0 = smooth's one-tick solve)"),
        "reversal_learning": Bool(default=True,
                                  doc="learn, from one velocity reversal to the next, the tracking error "
                                      "after each and where the guard fires, and act on it ahead of time"),
        "reversal_rate": Num(default=0.2, min=0.0, min_exclusive=True, max=1.0,
                             doc="share of a reversal's tracking error added to the reversal table, "
                                 "times the model error's share of what the load cell says"),
        "reversal_lead_ticks": Num(default=3, integer=True, min=0, max=10,
                                   doc="ticks by which the reversal tables act ahead of the force they learned "
                                       "from"),
        "reversal_v_mps": Num(default=0.001, min=0.0, max=1.0,
                              doc="hysteresis of the reversal detector on the velocity (m/s)"),
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
        correction_hz: float = 40.0,
        correction_max_N: float = 25.0,
        guard_N: float = 0.15,
        horizon_ticks: int = 2,
        correction_min_hz: float = 10.0,
        correction_ramp: float = 0.5,
        reversal_learning: bool = True,
        reversal_rate: float = 0.2,
        reversal_lead_ticks: int = 3,
        reversal_v_mps: float = 0.001,
    ) -> None:
        super().__init__(params, I_max, dt, eps_N_per_A, max_slew_A_per_s, lag_s, lag_horizon_s)
        if not (correction_hz > 0.0 and correction_max_N > 0.0 and guard_N >= 0.0):
            raise ValueError("correction_hz and correction_max_N must be > 0, guard_N >= 0")
        if not 0.0 < correction_min_hz <= correction_hz:
            raise ValueError("correction_min_hz must be in (0, correction_hz]")
        if not 0.0 <= correction_ramp <= 1.0:
            raise ValueError("correction_ramp must be in [0, 1]")
        if not 0 <= horizon_ticks <= 5:
            raise ValueError("horizon_ticks must be in 0..5")
        self.gain_max = 1.0 - math.exp(-2.0 * math.pi * correction_hz * self.dt)
        self.gain_min = 1.0 - math.exp(-2.0 * math.pi * correction_min_hz * self.dt)
        self.ramp = float(correction_ramp)
        self._lam = self.dt / _NOISE_S
        self.d_max = float(correction_max_N)
        self.guard_N = float(guard_N)
        self.horizon = int(horizon_ticks)
        if not (0.0 < reversal_rate <= 1.0 and 0 <= reversal_lead_ticks <= 10 and reversal_v_mps >= 0.0):
            raise ValueError("reversal_rate must be in (0, 1], reversal_lead_ticks in 0..10, reversal_v_mps >= 0")
        self.learn = bool(reversal_learning)
        self.rev_rate = float(reversal_rate)
        self.rev_lead = int(reversal_lead_ticks)
        self.rev_v = float(reversal_v_mps)
        #: the reversal table (N): per bin, the tracking error learned; bins 0.._REV_BINS-1 around a
        #: reversal to positive velocity (the first _PRE before it), then the same to negative
        self.table = [0.0] * (2 * _REV_BINS)
        #: the guard table: per bin, the average of "the guard fired" (≥ 0.5: the guard acts ahead)
        self.gtable = [0.0] * (2 * _REV_BINS)
        self._hist = [-1] * _HIST  # the bins of the last commands
        self._slope = 1.0 - math.exp(-self.dt / _SLOPE_S)
        # the model's coefficients at I + ΔI (the horizon's finite difference), and the two
        # force trajectories, reused every tick
        self._probe = LuGreModel(params)
        self._f0, self._f1 = [0.0] * self.horizon, [0.0] * self.horizon
        self.ticks = 0  #: calls since reset
        self.no_force_ticks = 0  #: calls without a finite load-cell force
        self.guard_ticks = 0  #: calls on which the measured force opposed the demand
        self._reset_state(0.0)

    def _reset_state(self, I0: float) -> None:
        self.d = 0.0  #: the model-error estimate d̂ (N)
        self.d_slope = 0.0  #: its slope (N per tick)
        self.gain = self.gain_min  #: the correction's present gain g
        self.noise_var = 0.0  #: load-cell noise variance r̂ (N²)
        self.error_var = 0.0  #: model-error power p̂ (N²)
        self._e1 = math.nan  # the model error of the last update
        self.I_coil = self._I_coil0 = self.I_prev = I0
        self._k = -1
        self._Fb = 0.0  # previous tick's bench terms F_offset + k_x·x
        self._Fd = math.nan  # previous tick's demand (N)
        self._F_seen = math.nan  # previous tick's load-cell reading, as read
        self._dv = self._dF = 0.0  # smoothed per-tick slopes of v and F_des
        tab = self.table
        gt = self.gtable
        for i in range(len(tab)):
            tab[i] = gt[i] = 0.0
        for i in range(_HIST):
            self._hist[i] = -1
        self._hpos = 0
        self._dir = 0  # sign of the motion (hysteresis reversal_v_mps), 0 before the first
        self._n = _REV_BINS  # ticks since the last reversal (≥ _REV_BINS: outside the table)
        self._sat = 0  # previous command held at the top (+1: I_max or slew) or bottom (-1: 0 A or slew)
        self.ff = 0.0  #: the reversal table's feed-forward (N)
        self._ff_w = 1.0  # its weight: fades like d̂ without a load cell
        self.reversals = 0  #: reversals seen
        self._share = 0.0  # p̂/(p̂ + r̂): the model error's share of what the load cell says
        self._lg = False  # the last command was the learned guard's ramp-down

    def reset(self, I0: float = 0.0, z0: float = 0.0, v0: float = 0.0) -> None:
        super().reset(I0, z0, v0)
        self._reset_state(I0)
        self.ticks = self.no_force_ticks = self.guard_ticks = 0

    def applied(self, I: float) -> None:
        """Nothing to do: the next tick reads the command sent from ``m.I_cmd``."""

    def notices(self) -> list[str]:
        n = self.no_force_ticks
        if not n:
            return []
        return [f"inverse law closed: no load-cell force on {n} of {self.ticks} ticks; "
                f"it ran on its feed-forward alone there, without the load-cell correction"]

    def _coil(self, m: Measurement) -> tuple[float, int]:
        """The coil's current over the last interval (the lag model driven by
        the command actually sent, held over skipped ticks), and the ticks
        since the last call."""
        k = m.k
        dk = k - self._k if self._k >= 0 else 1
        self._k = k
        Ic = m.I_cmd
        if not Ic >= 0.0:  # NaN: fall back on what this law sent
            Ic = self.I_prev
        Ia0 = self._I_coil0
        a1 = self._lag_gain(Ic, Ia0)  # the driver's rise or fall: monotone while Ic is held
        if dk <= 1:
            return Ia0 + a1 * (Ic - Ia0), 1
        return Ic + (Ia0 - Ic) * (1.0 - a1) ** dk, dk

    def _correct(self, F: float, Ia: float, dk: int) -> bool:
        """Update d̂ from the load cell's reading F of the previous tick;
        True when that force opposed the demand although the model expected
        it on the demand's side (by more than guard_N): the guard."""
        d = self.d
        if not F - F == 0.0:  # NaN or inf: no load cell this tick
            self.no_force_ticks += 1
            self.d = d - self.gain_max * d
            self.d_slope = 0.0
            self._ff_w -= self.gain_max * self._ff_w
            return False
        if self._ff_w < 1.0:
            self._ff_w += self.gain_max * (1.0 - self._ff_w)
        if not (dk == 1 and self._started) or F == self._F_seen:
            return False  # a gap, or the same reading again (the supervisor holding a sample): nothing new
        mod = self.model  # still at the previous tick: z, v_prev
        Fm = F - self._Fb
        e = Fm - mod.force(mod.v_prev, Ia)
        Fd = self._Fd
        gb = self._hist[self._hpos]
        opp = Fd * Fm < 0.0
        if gb >= 0 and self.learn:
            # the guard table: did the guard fire in this bin? Where the table's guard acted (current
            # ramped down ahead), the force opposing the demand beyond guard_N keeps it armed
            gt = self.gtable
            fired = opp and (e * Fd < -self.guard_N or (self._lg and (Fm - Fd) * Fd < -self.guard_N))
            gt[gb] += _GUARD_RATE * ((1.0 if fired else 0.0) - gt[gb])
        if opp and e * Fd < -self.guard_N:
            self.guard_ticks += 1
            return True  # semi-active: no current can fix this error, hold d̂
        # the gain: slow where the load cell's noise dominates the model error
        lam, e1 = self._lam, self._e1
        self._e1 = e
        r = self.noise_var
        if e1 - e1 == 0.0:  # white noise of variance r gives E[(Δe)²] = 2r; a smooth model error little
            de = e - e1
            r += lam * (0.5 * de * de - r)
            self.noise_var = r
        p = self.error_var
        p += lam * (e * e - r - p)
        self.error_var = p
        g0 = self.gain_min
        g = g0 + (self.gain_max - g0) * p / (p + r + 1e-6) if p > 0.0 else g0
        self.gain = g
        self._share = p / (p + r + 1e-6) if p > 0.0 else 0.0
        # alpha-beta update of d̂ and its slope
        s = self.d_slope
        d += s
        u = e - d
        # the reversal table learns the tracking error into the bin of the command lead ticks before; not
        # where the force opposes the demand (no current helps), nor after the guard table's ramp-down,
        # nor where the command was held at 0 A, I_max or the slew bound with the error asking for more
        # of the same
        b = -1 if (opp or self._lg) else self._hist[(self._hpos - self.rev_lead) % _HIST]
        if b >= 0 and self.learn:
            ee = Fm - Fd
            if not ((self._sat > 0 and ee * Fd < 0.0) or (self._sat < 0 and ee * Fd > 0.0)):
                tab = self.table
                Tb = tab[b] + self.rev_rate * self._share * ee
                dm = self.d_max
                tab[b] = Tb if -dm < Tb < dm else (dm if Tb > 0.0 else -dm)
        d += g * u
        if self.ramp:
            s += self.ramp * (4.0 - 2.0 * g - 4.0 * math.sqrt(1.0 - g)) * u
        if -self.d_max < d < self.d_max:
            self.d, self.d_slope = d, s
        else:
            self.d, self.d_slope = (self.d_max if d > 0.0 else -self.d_max), 0.0
        return False

    def _look_ahead(self, v: float, I0: float, F_t: float) -> tuple[float, float]:
        """Σ D_j·(F_t,j − B_j) and Σ D_j² over the horizon: the model's force
        j ticks ahead, F_j ≈ B_j + D_j·I, from the law's state at this tick
        carried ahead with the current held at I0 and at I0 + ΔI."""
        f0, f1, dF = self._f0, self._f1, self._dF
        # the law's model is at I0 already (its coefficients cached): the probe only at I0 + ΔI
        self.model.look_ahead(v, self._dv, I0, _DI, self.dt, self._probe, f0, f1)
        num = den = 0.0
        for j in range(self.horizon):
            D = (f1[j] - f0[j]) / _DI
            num += D * (F_t + (j + 1) * dF - f0[j] + D * I0)
            den += D * D
        return num, den

    def current(self, m: Measurement, F_des: float) -> float:
        v = m.v
        self.ticks += 1
        Ia, dk = self._coil(m)
        F = m.F
        guard = self._correct(F, Ia, dk)
        self._F_seen = F
        Fb = self._bench(Ia, m.x)
        if self._started:
            s = self._slope
            self._dv += s * (v - self.model.v_prev - self._dv)
            if F_des - self._Fd == F_des - self._Fd:  # both finite
                self._dF += s * (F_des - self._Fd - self._dF)
            z = self.model.advance(v, Ia, self.dt * dk)
        else:
            z = self._first(v)
        zdot = self.model.zdot(v, Ia)
        (s0A, s1A, s2A), (s0B, s1B, s2B) = self._slopes(Ia)
        D = s0A * z + s1A * zdot + s2A * v
        # the reversal detector and the table's feed-forward for the coming ticks
        n = self._n + dk
        dr = self._dir
        if dr >= 0 and v < -self.rev_v:
            if dr:
                n = 0
                self.reversals += 1
            dr = self._dir = -1
        elif dr <= 0 and v > self.rev_v:
            if dr:
                n = 0
                self.reversals += 1
            dr = self._dir = 1
        self._n = n
        ff = 0.0
        b = -1
        lg = False
        if dr:
            if n < _REV_BINS - _PRE:
                b = (0 if dr > 0 else _REV_BINS) + _PRE + n
            else:  # before the next reversal? ticks until the detector sees it, from the velocity's slope
                dvv = self._dv
                if dr * dvv < 0.0:
                    tt = (v + dr * self.rev_v) / -dvv
                    if tt < _PRE:
                        b = (_REV_BINS if dr > 0 else 0) + _PRE - 1 - int(tt if tt > 0.0 else 0.0)
        hp = self._hpos + 1
        if hp == _HIST:
            hp = 0
        self._hpos = hp
        self._hist[hp] = b
        if b >= 0 and self.learn:
            w = self._ff_w
            ff = self.table[b] * w
            bl = b + self.rev_lead
            gt = self.gtable
            if (0 < bl < _REV_BINS if b < _REV_BINS else _REV_BINS < bl < 2 * _REV_BINS) \
                    and gt[bl] * w >= _GUARD_ARM and gt[bl - 1] * w >= _GUARD_ARM:
                guard = lg = True  # the guard fired here on earlier reversals: ramp down ahead of it
        self._lg = lg
        self.ff = ff
        F_t = F_des - Fb - self.d - ff
        F_t -= self.model.hys_force(v)  # the hysteretic stiffness's force at this tick, held over the horizon
        num = D * (F_t - (s0B * z + s1B * zdot + s2B * v))
        den = D * D
        if self.horizon:
            n2, d2 = self._look_ahead(v, Ia, F_t)
            num += n2
            den += d2
        eps2 = self.eps2
        It = (num + eps2 * Ia) / (den + eps2) if den + eps2 > 0.0 else Ia
        I = Ia + (It - Ia) * (self._inv_ah if It >= Ia else self._inv_ahf)
        Ip = m.I_cmd if m.I_cmd >= 0.0 else self.I_prev
        step = self.max_step_A
        sat = 0
        if guard:
            I = Ip - step  # ramp down: the damper opposes the demand
            sat = -1
        elif I > Ip + step:
            I = Ip + step
            sat = 1
        elif I < Ip - step:
            I = Ip - step
            sat = -1
        if I >= self.I_max:
            I, sat = self.I_max, 1
        elif not I > 0.0:  # NaN → 0 A
            I, sat = 0.0, -1
        self._sat = sat
        self.I_prev = I
        self._I_coil0 = Ia
        self.I_coil = Ia + self._lag_gain(I, Ia) * (I - Ia)
        self._Fb, self._Fd = Fb, F_des
        return I
