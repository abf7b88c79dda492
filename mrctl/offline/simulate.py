"""Offline closed loop of the paper's Fig 4, as fast as CPython allows.

No pacing, no threads: excitation → (sensors) → demand → inverse law →
clamp → plant, once per tick, with the same objects the daemon uses. The
tick order is the daemon's: sample at t_k, command I_k, the plant's force
at t_k is with I_k applied (a driver lag, if configured, delays that).

:attr:`SimResult.columns` are the simulation's own arrays (the plant's true
x, v, F and the sensors' readings apart); the run log it writes
(:func:`write_csv`, :func:`log_columns`) is ``mrctl run``'s, column for
column (docs/runlog.md).
"""

from __future__ import annotations

import io
import math
import os
import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from mrctl.config import ConfigError
from mrctl.experiment import Experiment
from mrctl.laws.base import LawFault, Measurement, NonFiniteOutput, clamp_current
from mrctl.laws.guard import law_fault
from mrctl.runlog import files
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS, RUN_UNITS
from mrctl.runlog.metrics import tracking_summary

#: The simulation's own arrays (:attr:`SimResult.columns`): the plant's x, v,
#: F and the sensors' readings apart; ``F_meas[k]`` is the reading of F[k]
#: (which the controller receives at tick k + 1), ``F_rx[k]`` the reading
#: received at tick k.
SIM_COLUMNS = ("t", "x", "v", "F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas", "F_rx")
#: What the run log holds: the daemon's columns (mrctl/runlog/format.py).
CSV_COLUMNS = RUN_COLUMNS
CSV_UNITS = tuple(RUN_UNITS[c] for c in RUN_COLUMNS)


@dataclass
class SimResult:
    columns: dict[str, np.ndarray]
    wall_s: float
    summary: dict[str, float] = field(default_factory=dict)
    #: a law that raised or returned NaN/inf: the run ended at that tick, at 0 A
    fault: LawFault | None = None
    #: the driver's applied current before the first tick (what tick 0's sample reports)
    I_applied0: float = 0.0
    #: what the law flagged during the run (Law.notices), said once after it
    notices: list[str] = field(default_factory=list)

    @property
    def ticks(self) -> int:
        return len(self.columns["t"])


def run_duration(exp: Experiment, override_s: float | None = None) -> float:
    """How long to simulate: CLI override, else config, else the excitation file's length."""
    if override_s is not None:
        return override_s
    if exp.config.duration_s is not None:
        return exp.config.duration_s
    length = getattr(exp.excitation, "duration_s", None)
    if length is None:
        raise ConfigError(["duration_s: required for an offline simulation (or pass --duration)"])
    return length


def simulate(exp: Experiment, duration_s: float) -> SimResult:
    """Run the closed loop for ``duration_s`` of simulated time.

    The shaker's motion is an open-loop input, so it is computed for the
    whole run up front (numpy); the loop itself is the per-tick plain-float
    code the daemon runs. The laws see what the daemon's sim link gives
    them: x and v at tick k, the load cell's reading of the force of tick
    k − 1, sensor noise drawn in the same order (x, v, F per tick), NaN in
    a channel the bench lacks (``plant.sensors.load_cell``/``velocity``),
    and the velocity the observer makes of them (``sensing``), as the
    controller does before its laws.

    A bench whose motion depends on the damper (``plant.bench:
    quarter_car``) is stepped tick by tick instead (:mod:`.bench_sim`). A law
    that raises or returns NaN/inf ends the run at that tick with 0 A
    (``SimResult.fault``)."""
    if exp.config.plant.get("bench", "shaker") != "shaker":
        from mrctl.offline.bench_sim import simulate_bench

        return simulate_bench(exp, duration_s)
    n = int(round(duration_s / exp.dt)) + 1
    exp.law.reset()
    if exp.demand is not None:
        exp.demand.reset()
    t_arr = np.arange(n) * exp.dt
    x_arr, v_arr = exp.excitation.trajectory(t_arr)
    cols = {c: array("d", bytes(8 * n)) for c in SIM_COLUMNS[3:]}
    t0 = time.perf_counter()
    n, fault = _loop(exp, t_arr.tolist(), np.asarray(x_arr, float).tolist(), np.asarray(v_arr, float).tolist(), cols)
    wall = time.perf_counter() - t0
    out = {"t": t_arr[:n], "x": np.asarray(x_arr, float)[:n], "v": np.asarray(v_arr, float)[:n]}
    out.update({c: np.frombuffer(a, dtype=float)[:n] for c, a in cols.items()})
    summary = tracking_summary(out["t"], out["F_des"], out["F"], out["I"], exp.I_max, exp.excitation.settle_s)
    summary["ticks"] = float(n)
    summary["simulated_s"] = (n - 1) * exp.dt
    summary["wall_s"] = wall
    summary["realtime_factor"] = ((n - 1) * exp.dt / wall) if wall > 0 else math.inf
    return SimResult(out, wall, summary, fault, notices=exp.law.notices())


def _loop(exp: Experiment, ts: list[float], xs: list[float], vs: list[float], cols: dict[str, array]
          ) -> tuple[int, LawFault | None]:
    """The per-tick loop on the shaker; (ticks done, law fault or None)."""
    n, I_max = len(ts), exp.I_max
    plant, sensors = exp.make_plant(), exp.make_sensors()
    cfd, cf, ci, cia, cz = cols["F_des"], cols["F"], cols["I"], cols["I_applied"], cols["z"]
    cxm, cvm, cfm, cfr = cols["x_meas"], cols["v_meas"], cols["F_meas"], cols["F_rx"]
    # local bindings: attribute lookups cost as much as the physics here
    demand = exp.demand.force if exp.demand is not None else None
    current, applied = exp.law.current, exp.law.applied
    dname, lname = (exp.config.demand.type if demand is not None else ""), exp.config.inverse.law
    ptick = plant.tick
    observe = exp.make_observer()
    has_F, has_v = exp.config.plant.sensors.load_cell, exp.config.plant.sensors.velocity
    m = Measurement()
    F_prev = 0.0  # the plant's force before the first tick (SimBench starts there too)
    I, nan = 0.0, math.nan
    fault: LawFault | None = None
    for k in range(n):
        x, v = xs[k], vs[k]
        if sensors is None:
            xm, vm, Fm = x, v, F_prev
        else:
            xm, vm, Fm = sensors.x(x), sensors.v(v), sensors.F(F_prev)
        if not has_F:
            Fm = math.nan
        if k:
            cfm[k - 1] = Fm
        cfr[k] = Fm
        if not has_v:
            vm = math.nan
        if observe is not None:
            vm = observe.update(xm, vm)
        m.k, m.t, m.x, m.v, m.F, m.I_applied, m.I_cmd = k, ts[k], xm, vm, Fm, plant.I_applied, I
        Fd = nan
        who = dname
        try:  # the law guard (docs/laws.md, mrctl/laws/guard.py): zero cost on the good path
            if demand is not None:
                Fd = demand(m)
                if Fd - Fd != 0.0:  # NaN or inf
                    raise NonFiniteOutput(f"F_des = {Fd!r}")
            who = lname
            I = current(m, Fd)
            if I - I != 0.0:
                raise NonFiniteOutput(f"I = {I!r}")
            Ic = clamp_current(I, I_max)
            if Ic != I:  # tell the law only when the clamp changed its output
                I = Ic
                applied(I)
        except Exception as exc:  # noqa: BLE001 - a law's failure is a fault, not a crash
            fault = law_fault(exc, who, k, ts[k])
            I = 0.0  # the run ends at this tick, at 0 A
        F_prev = cf[k] = ptick(v, I, x)
        cxm[k], cvm[k], cfd[k], ci[k], cia[k], cz[k] = xm, vm, Fd, I, plant.I_applied, plant.z
        if fault is not None:
            n = k + 1
            break
    cfm[n - 1] = (F_prev if sensors is None else sensors.F(F_prev)) if has_F else math.nan
    return n, fault


def log_columns(result: SimResult) -> dict[str, np.ndarray]:
    """The run log of a simulation: :data:`RUN_COLUMNS` with ``mrctl run``'s
    meaning per column (docs/runlog.md): x, v, F as the controller received
    them (F: the reading of the previous tick's force), F_true the plant's
    force of the tick, I_applied what the driver reported at the sample; no
    clock, supervisor or link offline (late_us, compute_us NaN; fault,
    link_errors 0)."""
    c = result.columns
    n = len(c["t"])
    k = np.arange(n, dtype=float)
    nan = np.full(n, math.nan)
    zero = np.zeros(n)
    I_seen = np.concatenate(([result.I_applied0], np.asarray(c["I_applied"])[:-1])) if n else zero
    return {"t": c["t"], "x": c["x_meas"], "v": c["v_meas"], "F_des": c["F_des"], "F": c["F_rx"], "I": c["I"],
            "k": k, "seq": k, "t_dev": c["t"], "I_applied": I_seen, "F_true": c["F"], "late_us": nan,
            "compute_us": nan, "fault": zero, "link_errors": zero}


def write_csv(result: SimResult, path: str | Path, force: bool = False, fh: BinaryIO | None = None) -> None:
    """The run log's CSV (plain: the header first; provenance goes in the
    sidecar). Created without following a symlink; an existing file is
    refused unless ``force`` (:func:`mrctl.runlog.files.create_log`).
    ``fh``: the log already created (``mrctl simulate`` takes its names
    before simulating), written and closed here."""
    cols = log_columns(result)
    extra = tuple(c for c in result.columns if c not in SIM_COLUMNS)  # a bench's channels (quarter car)
    names = CSV_COLUMNS + extra
    data = np.column_stack([np.asarray(cols[c] if c in cols else result.columns[c], float) for c in names])
    text = io.StringIO()
    text.write(",".join(names) + "\n")
    np.savetxt(text, data, delimiter=",", fmt=[RUN_FORMATS.get(c, "%.9g") for c in names])
    with (fh if fh is not None else files.create_log(path, force)) as out:
        out.write(text.getvalue().encode("ascii"))
        os.fsync(out.fileno())
