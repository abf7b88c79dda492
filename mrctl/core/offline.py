"""The offline tick loop: ``mrctl simulate`` on any simulated bench.

One loop for every bench (the shaker's :class:`mrctl.model.bench.SimBench`,
the quarter car): each tick ``begin_tick`` → ``sample`` → the observer → the
guarded laws (:class:`mrctl.laws.guard.LawCall`) → clamp → ``command``,
the daemon's sim-link order, with the bench's channels handed to the laws
in place. Compiled with the tick (mrctl/build.py): the built-in laws, the
observer, the plant and the shaker bench are native calls.

Columns (``cols``, preallocated ``array('d')`` by name): t, x, v (the
damper's true stroke and rate), F_des, F (the plant's true force), I,
I_applied, z, x_meas, v_meas, F_meas (the load cell's reading of F[k]),
F_rx (the reading the laws received at tick k), and every channel of the
bench (the value the laws saw; ``a_sprung`` the body's true acceleration).
"""

from __future__ import annotations

from typing import Any

from mrctl.estimation.observer import KinematicObserver
from mrctl.laws.base import CurrentLaw, DemandLaw, LawFault, Measurement, clamp_current
from mrctl.laws.guard import LawCall, law_fault, law_name


def run_ticks(bench: Any, law: CurrentLaw, demand: DemandLaw | None, observer: KinematicObserver | None,
              m: Measurement, I_max: float, dt: float, cols: dict[str, Any], n: int) -> tuple[LawFault | None, int]:
    """Run ``n`` ticks; (the law fault that ended the run or None, ticks done).
    A law that fails ends the run at its tick, at 0 A (docs/laws.md)."""
    ct, cx, cv, cfd, cf, ci = cols["t"], cols["x"], cols["v"], cols["F_des"], cols["F"], cols["I"]
    cia, cz, cxm, cvm, cfm, cfr = cols["I_applied"], cols["z"], cols["x_meas"], cols["v_meas"], cols["F_meas"], cols["F_rx"]
    ch: dict[str, float] = m.channels
    ch_cols = [(cols[c], c) for c in ch]
    a_sprung = cols["a_sprung"] if "a_sprung" in ch else None
    plant = bench.plant
    call = LawCall()
    I = 0.0
    for k in range(n):
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
            col[k] = ch[name]
        fault: LawFault | None = None
        try:  # the law guard (mrctl/laws/guard.py), as the controller's
            I = call.run(law, demand, m)
            Ic = clamp_current(I, I_max)
            if Ic != I:  # tell the law only when the clamp changed its output
                I = Ic
                law.applied(I)
        except BaseException as exc:  # noqa: BLE001 - a law's failure is a fault, not a crash
            fault = law_fault(exc, law_name(call.who), k, t)
            I = 0.0  # the run ends at this tick, at 0 A
        bench.command(I)
        ct[k] = t
        cx[k] = bench.x
        cv[k] = bench.v
        cfd[k] = call.F_des
        cf[k] = bench.F
        ci[k] = I
        cia[k] = plant.I_applied
        cz[k] = plant.z
        cxm[k] = xm
        cvm[k] = vm
        cfr[k] = Fm  # what the laws received at this tick
        if k:
            cfm[k - 1] = Fm  # the load cell shows the previous tick's force
        cfm[k] = bench.F
        if a_sprung is not None:
            a_sprung[k] = bench.a_s
        if fault is not None:
            return fault, k + 1
    return None, n

