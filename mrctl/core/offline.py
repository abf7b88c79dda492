"""The offline tick loop: ``mrctl simulate`` on any simulated bench.

One loop for every bench (the shaker's :class:`mrctl.model.bench.SimBench`,
the quarter car): each tick ``begin_tick`` → ``sample`` → the observer → the
guarded laws (:class:`mrctl.laws.guard.LawCall`) → clamp → ``command``,
the daemon's sim-link order, with the bench's channels handed to the laws
in place. ``delay_ticks``: the current computed from tick k's sample reaches
the bench at tick k + delay_ticks (0: at once, as the sim link does; 1: as
an exchange link sends it, with the next tick's request); the bench holds
0 A before the first one arrives. Compiled with the tick (mrctl/build.py): the built-in laws, the
observer, the plant and the shaker bench are native calls.

Columns (``cols``, preallocated ``array('d')`` by name, one block's rows):
t, x, v (the damper's true stroke and rate), F_des, F (the plant's true
force), I, I_applied, z, x_meas, v_meas, F_rx (the reading the laws
received at tick k), and every channel of the bench (the value the laws
saw; ``a_sprung`` the body's true acceleration).
"""

from __future__ import annotations

from typing import Any

from mrctl.estimation.observer import KinematicObserver
from mrctl.laws.base import CurrentLaw, DemandLaw, LawFault, Measurement, clamp_current
from mrctl.laws.guard import LawCall, law_fault, law_name
from mrctl.util.interrupt import user_stopped


class OfflineLoop:
    """The offline closed loop, run in blocks of ticks (``mrctl simulate``
    streams: a block's rows are logged and dropped before the next block).

    The state a tick hands the next (the law guard, the last command, the
    tick index) lives here between blocks, so a run cut into blocks is the
    same run, bit for bit, as one block. ``fault``: the law fault that ended
    the run (None while it goes on)."""

    def __init__(self, bench: Any, law: CurrentLaw, demand: DemandLaw | None,
                 observer: KinematicObserver | None, m: Measurement, I_max: float, dt: float,
                 delay_ticks: int = 0) -> None:
        if delay_ticks < 0:
            raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
        self.bench = bench
        self.law = law
        self.demand = demand
        self.observer = observer
        self.m = m
        self.I_max = I_max
        self.dt = dt
        self.call = LawCall()
        self.I = 0.0
        self.k = 0
        self.fault: LawFault | None = None
        #: the currents computed but not yet at the bench, oldest first (delay_ticks of them)
        self.pending: list[float] = [0.0] * delay_ticks

    def run(self, cols: dict[str, Any], n: int) -> int:
        """Run up to ``n`` more ticks into rows 0 .. n − 1 of ``cols``; the rows
        written (fewer after a law fault: the run ends at its tick, at 0 A,
        docs/laws.md). ``F_meas`` is not written here: it is the next tick's
        ``F_rx`` (:func:`mrctl.offline.simulate.simulate`)."""
        if self.fault is not None:
            return 0
        ct, cx, cv, cfd, cf, ci = cols["t"], cols["x"], cols["v"], cols["F_des"], cols["F"], cols["I"]
        cia, cz, cxm, cvm, cfr = cols["I_applied"], cols["z"], cols["x_meas"], cols["v_meas"], cols["F_rx"]
        bench = self.bench
        law = self.law
        demand = self.demand
        observer = self.observer
        m = self.m
        I_max = self.I_max
        dt = self.dt
        call = self.call
        ch: dict[str, float] = m.channels
        ch_cols = [(cols[c], c) for c in ch]
        a_sprung = cols["a_sprung"] if "a_sprung" in ch else None
        plant = bench.plant
        pending = self.pending
        delayed = len(pending) > 0
        I = self.I
        k0 = self.k
        for i in range(n):
            k = k0 + i
            t = k * dt
            bench.begin_tick(k)
            xm, vm, Fm = bench.sample()
            xm = float(xm)
            vm = float(vm)
            Fm = float(Fm)
            if observer is not None:
                vm = observer.update(xm, vm, 1)
            m.k = k
            m.t = t
            m.x = xm
            m.v = vm
            m.F = Fm
            m.I_applied = float(plant.I_applied)
            m.I_cmd = I
            for col, name in ch_cols:
                col[i] = ch[name]
            fault: LawFault | None = None
            try:  # the law guard (mrctl/laws/guard.py), as the controller's
                I = call.run(law, demand, m)
                Ic = clamp_current(I, I_max)
                if Ic != I:  # tell the law only when the clamp changed its output
                    I = Ic
                    law.applied(I)
            except BaseException as exc:  # noqa: BLE001 - a law's failure is a fault, not a crash
                if isinstance(exc, KeyboardInterrupt) and user_stopped():
                    raise  # the user's Ctrl-C that landed inside the law: not the law's (mrctl/util/interrupt.py)
                fault = law_fault(exc, law_name(call.who), k, t)
                I = 0.0  # the run ends at this tick, at 0 A
            if delayed:
                pending.append(I)
                bench.command(pending.pop(0))
            else:
                bench.command(I)
            ct[i] = t
            cx[i] = bench.x
            cv[i] = bench.v
            cfd[i] = call.F_des
            cf[i] = bench.F
            ci[i] = I
            cia[i] = plant.I_applied
            cz[i] = plant.z
            cxm[i] = xm
            cvm[i] = vm
            cfr[i] = Fm  # what the laws received at this tick
            if a_sprung is not None:
                a_sprung[i] = bench.a_s
            if fault is not None:
                self.fault = fault
                self.I = I
                self.k = k + 1
                return i + 1
        self.I = I
        self.k = k0 + n
        return n
