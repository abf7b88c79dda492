"""Offline closed loop on a bench whose motion depends on the damper: the quarter car.

On the shaker the damper's motion is an open-loop input, computed up front
(:func:`mrctl.offline.simulate.simulate`). In a quarter car the body and the
wheel move with the damper's force, so this loop steps the bench exactly
as the daemon's sim link does (``begin_tick`` → ``sample`` → laws →
``command``), with the bench's channels handed to the laws in place.

Columns: those of ``mrctl simulate`` (x, v the damper's true stroke and
rate), then every channel of the bench (the values the laws saw at the
tick; ``a_sprung`` with that tick's force, the body's true acceleration).
"""

from __future__ import annotations

import math
import time
from array import array
from typing import TYPE_CHECKING

import numpy as np

from mrctl.laws.base import LawFault, Measurement, NonFiniteOutput, clamp_current
from mrctl.laws.guard import law_fault
from mrctl.runlog.metrics import tracking_summary
from mrctl.runlog.ride import ride_summary

if TYPE_CHECKING:
    from mrctl.experiment import Experiment
    from mrctl.offline.simulate import SimResult

_BASE = ("F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas", "F_rx")


def simulate_bench(exp: Experiment, duration_s: float) -> SimResult:
    """Run ``duration_s`` of simulated time on ``exp.make_bench()``; a law
    fault ends the run at its tick, at 0 A (``summary['law_fault']``)."""
    from mrctl.offline.simulate import SimResult

    n = int(round(duration_s / exp.dt)) + 1
    bench = exp.make_bench()
    channels: dict[str, float] = getattr(bench, "channels", {})
    cols = {c: array("d", bytes(8 * n)) for c in ("t", "x", "v", *_BASE, *channels)}
    law, dem = exp.law, exp.demand
    law.reset()
    if dem is not None:
        dem.reset()
    m = Measurement(channels=channels)
    fault, done, t0 = _loop(exp, bench, m, cols, n)
    wall = time.perf_counter() - t0
    out = {c: np.frombuffer(a, dtype=float)[:done] for c, a in cols.items()}
    s = tracking_summary(out["t"], out["F_des"], out["F"], out["I"], exp.I_max, exp.excitation.settle_s)
    if "a_sprung" in out:
        s.update(ride_summary(out, exp.excitation.settle_s))
    s["ticks"] = float(done)
    s["simulated_s"] = (done - 1) * exp.dt
    s["wall_s"] = wall
    s["realtime_factor"] = ((done - 1) * exp.dt / wall) if wall > 0 else math.inf
    return SimResult(out, wall, s, fault, notices=law.notices())


def _loop(exp: Experiment, bench, m: Measurement, cols: dict[str, array], n: int
          ) -> tuple[LawFault | None, int, float]:
    """The per-tick loop; returns (law fault or None, ticks done, start time)."""
    I_max, dt = exp.I_max, exp.dt
    demand = exp.demand.force if exp.demand is not None else None
    current, applied = exp.law.current, exp.law.applied
    sample, command, plant = bench.sample, bench.command, bench.plant
    ch_cols = [(cols[c], c) for c in m.channels]
    ct, cx, cv, cfd, cf, ci, cia, cz = (cols[c] for c in ("t", "x", "v", "F_des", "F", "I", "I_applied", "z"))
    cxm, cvm, cfm, cfr = cols["x_meas"], cols["v_meas"], cols["F_meas"], cols["F_rx"]
    ch = m.channels
    observe = exp.make_observer()  # sensing.velocity: observer, as the controller applies it
    dname = exp.config.demand.type if exp.demand is not None else ""
    lname = exp.config.inverse.law
    I = 0.0
    fault = None
    t0 = time.perf_counter()
    for k in range(n):
        bench.begin_tick(k)
        xm, vm, Fm = sample()
        if observe is not None:
            vm = observe.update(xm, vm)
        m.k, m.t, m.x, m.v, m.F, m.I_applied, m.I_cmd = k, k * dt, xm, vm, Fm, plant.I_applied, I
        for col, name in ch_cols:
            col[k] = ch[name]
        Fd = math.nan
        who = dname
        try:  # the law guard (docs/laws.md, mrctl/laws/guard.py)
            if demand is not None:
                Fd = demand(m)
                if Fd - Fd != 0.0:
                    raise NonFiniteOutput(f"F_des = {Fd!r}")
            who = lname
            I = current(m, Fd)
            if I - I != 0.0:
                raise NonFiniteOutput(f"I = {I!r}")
            Ic = clamp_current(I, I_max)
            if Ic != I:
                I = Ic
                applied(I)
        except Exception as exc:  # noqa: BLE001 - a law's failure is a fault, not a crash
            fault = law_fault(exc, who, k, k * dt)
            I = 0.0
        command(I)
        ct[k], cx[k], cv[k], cfd[k], cf[k], ci[k] = k * dt, bench.x, bench.v, Fd, bench.F, I
        cia[k], cz[k], cxm[k], cvm[k] = plant.I_applied, plant.z, xm, vm
        cfr[k] = Fm  # what the controller received at this tick
        if k:
            cfm[k - 1] = Fm  # the load cell shows the previous tick's force
        cfm[k] = bench.F
        if "a_sprung" in ch:
            cols["a_sprung"][k] = bench.a_s
        if fault is not None:
            return fault, k + 1, t0
    return None, n, t0
