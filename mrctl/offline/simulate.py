"""Offline closed loop of the paper's Fig 4, as fast as CPython allows.

No pacing, no threads: excitation → (sensors) → demand → inverse law →
clamp → plant, once per tick, with the same objects the daemon uses. The
tick order is the daemon's: sample at t_k, command I_k, the plant's force
at t_k is with I_k applied (a driver lag, if configured, delays that).
"""

from __future__ import annotations

import math
import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mrctl.config import ConfigError
from mrctl.experiment import Experiment
from mrctl.runlog.metrics import tracking_summary
from mrctl.laws.base import Measurement, clamp_current

CSV_COLUMNS = ("t", "x", "v", "F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas")
CSV_UNITS = ("s", "m", "m/s", "N", "N", "A", "A", "m", "m", "m/s", "N")


@dataclass
class SimResult:
    columns: dict[str, np.ndarray]
    wall_s: float
    summary: dict[str, float] = field(default_factory=dict)
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
    controller does before its laws."""
    n = int(round(duration_s / exp.dt)) + 1
    I_max = exp.I_max
    plant = exp.make_plant()
    sensors = exp.make_sensors()
    observe = exp.make_observer()
    has_F, has_v = exp.config.plant.sensors.load_cell, exp.config.plant.sensors.velocity
    law = exp.law
    law.reset()
    t_arr = np.arange(n) * exp.dt
    x_arr, v_arr = exp.excitation.trajectory(t_arr)
    ts, xs, vs = t_arr.tolist(), np.asarray(x_arr, float).tolist(), np.asarray(v_arr, float).tolist()
    cols = {c: array("d", bytes(8 * n)) for c in ("F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas")}
    cfd, cf, ci, cia, cz = cols["F_des"], cols["F"], cols["I"], cols["I_applied"], cols["z"]
    cxm, cvm, cfm = cols["x_meas"], cols["v_meas"], cols["F_meas"]
    # local bindings: attribute lookups cost as much as the physics here
    demand = exp.demand.force if exp.demand is not None else None
    current, applied = law.current, law.applied
    ptick = plant.tick
    m = Measurement()
    F_prev = 0.0  # the plant's force before the first tick (SimBench starts there too)
    I = 0.0
    t0 = time.perf_counter()
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
        if not has_v:
            vm = math.nan
        if observe is not None:
            vm = observe.update(xm, vm)
        m.k, m.t, m.x, m.v, m.F, m.I_applied, m.I_cmd = k, ts[k], xm, vm, Fm, plant.I_applied, I
        Fd = demand(m) if demand is not None else math.nan
        I = current(m, Fd)
        Ic = clamp_current(I, I_max)
        if Ic != I:  # tell the law only when the guard changed its output
            I = Ic
            applied(I)
        F_prev = cf[k] = ptick(v, I, x)
        cxm[k], cvm[k] = xm, vm
        cfd[k] = Fd
        ci[k] = I
        cia[k] = plant.I_applied
        cz[k] = plant.z
    cfm[n - 1] = (F_prev if sensors is None else sensors.F(F_prev)) if has_F else math.nan
    wall = time.perf_counter() - t0
    out = {"t": t_arr, "x": np.asarray(x_arr, float), "v": np.asarray(v_arr, float)}
    out.update({c: np.frombuffer(a, dtype=float) for c, a in cols.items()})
    summary = tracking_summary(out["t"], out["F_des"], out["F"], out["I"], I_max, exp.excitation.settle_s)
    summary["ticks"] = float(n)
    summary["simulated_s"] = (n - 1) * exp.dt
    summary["wall_s"] = wall
    summary["realtime_factor"] = ((n - 1) * exp.dt / wall) if wall > 0 else math.inf
    return SimResult(out, wall, summary, law.notices())


def write_csv(result: SimResult, path: str | Path, comment: str | None = None) -> None:
    """CSV with a header row; optional leading '# ' comment lines (metadata)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    data = np.column_stack([result.columns[c] for c in CSV_COLUMNS])
    header = ",".join(CSV_COLUMNS)
    with p.open("w") as fh:
        if comment:
            for line in comment.splitlines():
                fh.write(f"# {line}\n")
        fh.write(header + "\n")
        np.savetxt(fh, data, delimiter=",", fmt="%.10g")
