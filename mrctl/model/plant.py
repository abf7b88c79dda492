"""The simulated damper plant: forward LuGre + current-driver lag + sensors.

This is what stands behind the driver interface in simulation: in-process
(:mod:`mrctl.io.sim`, ``mrctl simulate``) and in the separate ``hil_sim``
process. Pure numerics, no I/O; the shaker's motion comes from
:mod:`mrctl.model.excitation`.
"""

from __future__ import annotations

import math
import random

from mrctl.model.lugre import LuGreModel
from mrctl.model.params import LuGreParams, ThetaTable


class DriverLag:
    """First-order current driver: I_applied follows the command with time constant τ.

    Discretised exactly for a command held over one tick:
    I ← I + (I_cmd − I)·(1 − e^{−dt/τ}). τ = 0 is an ideal driver.
    ``tau_fall_s`` (None: τ) is the time constant while the command is below
    the applied input: a driver that forces the current up and lets it decay.
    """

    __slots__ = ("alpha", "alpha_fall", "I")

    def __init__(self, tau_s: float, dt: float, tau_fall_s: float | None = None) -> None:
        if tau_s < 0.0 or not math.isfinite(tau_s):
            raise ValueError("driver time constant must be finite and >= 0")
        self.alpha = 1.0 if tau_s == 0.0 else 1.0 - math.exp(-dt / tau_s)
        tf = tau_s if tau_fall_s is None else tau_fall_s
        if tf < 0.0 or not math.isfinite(tf):
            raise ValueError("driver fall time constant must be finite and >= 0")
        self.alpha_fall = 1.0 if tf == 0.0 else (self.alpha if tf == tau_s else 1.0 - math.exp(-dt / tf))
        self.I = 0.0

    def update(self, I_cmd: float) -> float:
        self.I += (I_cmd - self.I) * (self.alpha if I_cmd >= self.I else self.alpha_fall)
        return self.I

    def tau_s(self, dt: float) -> float:
        """The time constant (s) back from ``alpha`` at tick ``dt``."""
        a = self.alpha
        return 0.0 if a >= 1.0 else -dt / math.log(1.0 - a)


class DamperPlant:
    """The damper as the driver sees it: command in, true force out, once per tick.

    ``tick(v, I_cmd, x)`` advances the LuGre state over the last interval
    with the current applied then, updates the driver, and returns the force
    at this tick with the newly applied current, plus the bench terms
    F_offset + k_x·x. With no lag this is exactly the tick protocol the
    inverse laws assume (see :class:`LuGreModel`).

    The input lag is ``driver_tau_s`` when given (the same rising and
    falling), else the parameter set's ``tau_input`` and ``tau_input_fall``:
    a bench key may impose a lag on a set that has none. The set's
    ``tau_field`` lags the field behind the driver's current (``I_applied``,
    what a current monitor reads): the damper feels ``I_field``."""

    __slots__ = ("model", "driver", "dt", "I_applied", "F", "_started", "_Fo", "_kx", "_table", "field", "I_field")

    def __init__(self, params: LuGreParams, dt: float, driver_tau_s: float | None = None) -> None:
        self.model = LuGreModel(params)
        self.driver = (DriverLag(params.tau_input, dt, params.tau_fall()) if driver_tau_s is None
                       else DriverLag(driver_tau_s, dt))
        self.dt = dt
        self.I_applied = 0.0
        self.I_field = 0.0  # the current the field follows, as the damper feels it
        self.field: DriverLag | None = DriverLag(params.tau_field, dt) if params.tau_field > 0.0 else None
        self.F = 0.0
        self._started = False
        self._Fo = params.F_offset
        self._kx = params.k_x
        table = params.table
        self._table: ThetaTable | None = table if table is not None and table.has_bench() else None

    @property
    def z(self) -> float:
        """The LuGre state z (m), for the logs (every plant has one state to show)."""
        return self.model.z

    @property
    def tau_s(self) -> float:
        """The input lag in effect (s)."""
        return self.driver.tau_s(self.dt)

    def tick(self, v: float, I_cmd: float, x: float = 0.0) -> float:
        if self._started:
            self.model.advance(v, self.I_field, self.dt)
        else:
            self._started = True
            self.model.v_prev = v
        driver = self.driver
        I = I_cmd if driver.alpha == 1.0 and driver.alpha_fall == 1.0 else driver.update(I_cmd)
        driver.I = I
        self.I_applied = I
        field = self.field
        if field is not None:  # the damper's own lag behind the driver's current
            I = field.update(I)
        self.I_field = I
        F = self.model.force(v, I)
        table = self._table
        if table is not None:  # laws: table with per-level F_offset and k_x
            F += table.bench_force(I, x)
        elif self._kx != 0.0:
            F += self._Fo + self._kx * x
        elif self._Fo != 0.0:
            F += self._Fo
        self.F = F
        return F


class Sensors:
    """Seeded Gaussian noise and quantisation of x (m), v (m/s) and F (N).

    Zero noise and zero LSB give exact readings. Uses :mod:`random` (plain
    floats, reproducible per seed) rather than numpy, because it runs per tick."""

    __slots__ = ("rng", "x_noise_m", "v_noise_mps", "F_noise_N", "x_lsb_m", "v_lsb_mps", "F_lsb_N", "F_offset_N")

    def __init__(
        self,
        seed: int = 0,
        x_noise_m: float = 0.0,
        v_noise_mps: float = 0.0,
        F_noise_N: float = 0.0,
        x_lsb_m: float = 0.0,
        v_lsb_mps: float = 0.0,
        F_lsb_N: float = 0.0,
        F_offset_N: float = 0.0,
    ) -> None:
        self.rng = random.Random(seed)
        self.x_noise_m = x_noise_m
        self.v_noise_mps = v_noise_mps
        self.F_noise_N = F_noise_N
        self.x_lsb_m = x_lsb_m
        self.v_lsb_mps = v_lsb_mps
        self.F_lsb_N = F_lsb_N
        #: the load cell's zero error (N): what its amplifier reads at no force (an uncalibrated cell)
        self.F_offset_N = F_offset_N

    def _read(self, value: float, sigma: float, lsb: float) -> float:
        if sigma > 0.0:
            value += self.rng.gauss(0.0, sigma)
        if lsb > 0.0:
            value = round(value / lsb) * lsb
        return value

    def x(self, x: float) -> float:
        return self._read(x, self.x_noise_m, self.x_lsb_m)

    def v(self, v: float) -> float:
        return self._read(v, self.v_noise_mps, self.v_lsb_mps)

    def F(self, F: float) -> float:
        if self.F_offset_N != 0.0:  # no addition at all when there is none: -0.0 stays -0.0
            F += self.F_offset_N
        return self._read(F, self.F_noise_N, self.F_lsb_N)
