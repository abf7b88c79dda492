"""The simulated test bench: shaker + damper plant + current driver + sensors.

Pure numerics on a tick grid, no clock and no I/O: the in-process ``sim``
backend (:mod:`mrctl.io.sim`) steps it from the control loop, ``hil_sim``
steps it from its own 1 kHz clock behind real protocols. Both therefore
simulate the same bench.

Tick protocol, the same as ``mrctl simulate`` so that the in-process bench
reproduces it exactly: ``begin_tick(k)`` moves the shaker to tick k;
``sample()`` is what the sensors read then (the load cell shows the force of
the last completed tick); ``command(I)`` applies the driver input at tick k
and the plant produces that tick's force, the ground truth (``F``,
``I_applied``). A tick with no command keeps the last one (the driver holds
its input), so a host that misses ticks still gets a physical plant.
"""

from __future__ import annotations

import math

from typing import Any

from mrctl.model.params import LuGreParams
from mrctl.model.plant import DamperPlant, Sensors


class SimBench:
    """One damper on one shaker, advanced tick by tick.

    The damper is a :class:`DamperPlant` built from ``params`` unless
    ``plant`` gives another with its interface (``tick(v, I_cmd, x)``,
    ``I_applied``, ``F``): e.g. :class:`mrctl.model.boucwen.BoucWenPlant`.
    ``has_velocity`` false: the DAQ measures displacement only, the velocity
    channel reads NaN (as the force does without a load cell).
    ``trajectory`` (x, v lists by tick, from ``excitation.trajectory``):
    the shaker's motion computed up front (``mrctl simulate``: a block of
    ticks at a time, :meth:`set_trajectory`), else
    ``excitation.position``/``velocity`` at each tick's time."""

    __slots__ = ("excitation", "plant", "sensors", "dt", "k", "kp", "I_cmd", "t", "x", "v", "F",
                 "has_load_cell", "has_velocity", "_xs", "_vs", "_k0")

    def __init__(
        self,
        params: LuGreParams,
        excitation,
        dt: float,
        driver_tau_s: float | None = None,
        sensors: Sensors | None = None,
        has_load_cell: bool = True,
        plant: Any = None,
        has_velocity: bool = True,
        trajectory: tuple[list[float], list[float]] | None = None,
    ) -> None:
        self.excitation = excitation
        self.plant = DamperPlant(params, dt, driver_tau_s) if plant is None else plant
        self.sensors = sensors
        self.dt = dt
        self.has_load_cell = has_load_cell
        self.has_velocity = has_velocity
        self.I_cmd = 0.0
        self.k = -1  # present tick
        self.kp = -1  # last tick the plant has produced a force for
        self.t = self.x = self.v = self.F = 0.0
        self._xs: list[float] | None = None if trajectory is None else trajectory[0]
        self._vs: list[float] = [] if trajectory is None else trajectory[1]
        self._k0 = 0

    def set_trajectory(self, xs: list[float], vs: list[float], k0: int) -> None:
        """The shaker's motion for ticks k0, k0 + 1, … (the next block of an
        offline run); the ticks it moves to next must lie in it."""
        self._xs = xs
        self._vs = vs
        self._k0 = k0

    def begin_tick(self, k: int) -> None:
        """Move to tick k; ticks skipped since the last command run on the held command."""
        while self.kp < k - 1:
            self._plant_tick(self.kp + 1)
        self.k = k
        t = self.t = k * self.dt
        self.x, self.v = self._motion(k, t)

    def _motion(self, k: int, t: float) -> tuple[float, float]:
        xs = self._xs
        if xs is not None:
            return xs[k - self._k0], self._vs[k - self._k0]
        return float(self.excitation.position(t)), float(self.excitation.velocity(t))

    def command(self, I_A: float) -> None:
        """Apply the driver input (A) at the present tick. Non-finite or
        negative values read as 0 A, as a real driver's input stage clamps them."""
        self.I_cmd = I_A if I_A > 0.0 and I_A < math.inf else 0.0
        if self.kp < self.k:
            self._plant_tick(self.k)

    def finish_tick(self) -> None:
        """Make sure the present tick's force exists (no command came: hold)."""
        if self.kp < self.k:
            self._plant_tick(self.k)

    def _plant_tick(self, j: int) -> None:
        if j == self.k:
            x, v = self.x, self.v
        else:
            x, v = self._motion(j, j * self.dt)
        self.F = self.plant.tick(v, self.I_cmd, x)
        self.kp = j

    @property
    def I_applied(self) -> float:
        return self.plant.I_applied

    def sample(self) -> tuple[float, float, float]:
        """Measured (x m, v m/s, F N) at the present tick; F is the last
        completed tick's force, NaN without a load cell; v is NaN without a
        velocity channel. Noise is drawn for every channel either way (the
        noise sequence depends on the seed and the tick alone)."""
        s = self.sensors
        if s is None:
            x, v, F = self.x, self.v, self.F
        else:
            x, v, F = s.x(self.x), s.v(self.v), s.F(self.F)
        return x, (v if self.has_velocity else math.nan), (F if self.has_load_cell else math.nan)
