"""The in-process simulated bench as a backend: a peer of serial and Modbus.

It wraps :class:`mrctl.model.bench.SimBench` (the same plant ``hil_sim``
serves over real protocols) behind the backend interfaces. It is
*host-clocked*: the control loop tells it which tick it is (``begin_tick``),
so a loop that skips deadlines skips them in the plant too, and a run is
reproducible. It offers separate ``read``/``write`` (zero latency, like
``mrctl simulate``) and ``exchange`` (the one-transaction shape of the real
links, one tick of latency).
"""

from __future__ import annotations

import math

from mrctl.io.base import Disconnected, Sample, Status
from mrctl.model.bench import SimBench


class SimLink:
    """Backend ``sim``: samples from and currents to a :class:`SimBench`."""

    split = True  # read() then write() within one tick is supported
    host_clocked = True

    def __init__(self, bench: SimBench) -> None:
        self.bench = bench
        self._open = False
        self._status = int(Status.OUTPUT_ENABLED) if hasattr(Status, "OUTPUT_ENABLED") else 0
        if not bench.has_load_cell and hasattr(Status, "NO_LOAD_CELL"):
            self._status |= int(Status.NO_LOAD_CELL)

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        if self._open:
            self.bench.command(0.0)  # leave the plant safe, like a real backend
        self._open = False

    def describe(self) -> str:
        b = self.bench
        return f"sim: in-process bench, dt = {b.dt * 1e3:g} ms, driver tau = {b.plant.driver.alpha:.3g} (alpha)"

    def begin_tick(self, k: int) -> None:
        """The host's tick index: the bench moves its shaker there."""
        self.bench.begin_tick(k)

    def read(self) -> Sample:
        if not self._open:
            raise Disconnected("sim backend is not open")
        b = self.bench
        x, v, F = b.sample()
        return Sample(b.k & 0xFFFFFFFF, b.t, x, v, F, self._status, b.I_applied)

    def write(self, current_A: float) -> None:
        if not self._open:
            raise Disconnected("sim backend is not open")
        self.bench.command(current_A)

    def exchange(self, current_A: float) -> Sample:
        s = self.read()
        self.write(current_A)
        return s

    @property
    def true_force_N(self) -> float:
        """Ground truth for logs: the plant's force at this tick (after write)."""
        return self.bench.F if self.bench.kp == self.bench.k else math.nan
