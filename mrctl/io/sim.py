"""The in-process simulated bench as a link: a peer of serial and Modbus.

It wraps a simulated bench (:class:`mrctl.model.bench.SimBench`, the same
plant ``hil_sim`` serves over real protocols) behind the :class:`Link`
interface. It is *host-clocked*: the control loop tells it which tick it is
(:meth:`begin_tick`), so a loop that skips deadlines skips them in the plant
too, and a run is reproducible. It is *split*: :meth:`read` then
:meth:`write` within one tick (zero latency, like ``mrctl simulate``);
:meth:`exchange` gives the one-transaction shape of the real links.

The bench is handed in (built by :mod:`mrctl.experiment`): a link knows
samples and currents, not the damper model.
"""

from __future__ import annotations

import math
from typing import Any, Protocol

from mrctl.io.base import Disconnected, Link, Sample, Status


class Bench(Protocol):
    """What the sim link needs of a simulated bench (tick protocol: docs/design.md)."""

    dt: float
    k: int
    kp: int
    t: float
    F: float
    has_load_cell: bool

    def begin_tick(self, k: int) -> None: ...
    def sample(self) -> tuple[float, float, float]: ...
    def command(self, I_A: float) -> None: ...

    @property
    def I_applied(self) -> float: ...


class SimLink(Link):
    """Backend ``sim``: samples from and currents to a simulated bench."""

    kinds = ("sim",)
    split = True
    host_clocked = True

    def __init__(self, bench: Bench) -> None:
        super().__init__(timeout_s=1.0)
        self.bench = bench
        # the bench's own dict, updated in place at every begin_tick: no copy per tick
        self.channels = getattr(bench, "channels", {})
        self._open = False
        self._status = int(Status.OUTPUT_ENABLED)
        if not bench.has_load_cell:
            self._status |= int(Status.NO_LOAD_CELL)

    @classmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "SimLink":
        if context is None:
            raise ValueError("the sim link needs the experiment to build its bench")
        return cls(context.make_bench())

    @property
    def is_open(self) -> bool:
        return self._open

    def _open_transport(self) -> None:
        self._open = True

    def _send_safe(self) -> None:
        self.bench.command(0.0)  # leave the plant safe, like a real link

    def _close_transport(self) -> None:
        self._open = False

    def describe(self) -> str:
        b = self.bench
        return f"sim: in-process bench, dt = {b.dt * 1e3:g} ms"

    def begin_tick(self, k: int) -> None:
        """The host's tick index: the bench moves its shaker there."""
        self.bench.begin_tick(k)

    def read(self) -> Sample:
        if not self._open:
            raise Disconnected("sim link is not open")
        b = self.bench
        x, v, F = b.sample()
        return Sample(b.k & 0xFFFFFFFF, b.t, x, v, F, self._status, b.I_applied)

    def write(self, current_A: float) -> None:
        if not self._open:
            raise Disconnected("sim link is not open")
        self.bench.command(current_A)

    def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Sample:
        s = self.read()
        self.write(current_A)
        return s

    @property
    def true_force_N(self) -> float:
        """Ground truth for logs: the plant's force at this tick (after write)."""
        b = self.bench
        return b.F if b.kp == b.k else math.nan
