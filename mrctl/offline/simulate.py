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

CSV_COLUMNS = ("t", "x", "v", "F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas")
CSV_UNITS = ("s", "m", "m/s", "N", "N", "A", "A", "m", "m", "m/s", "N")


@dataclass
class SimResult:
    columns: dict[str, np.ndarray]
    wall_s: float
    summary: dict[str, float] = field(default_factory=dict)

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
    code the daemon runs."""
    n = int(round(duration_s / exp.dt)) + 1
    I_max = exp.I_max
    plant = exp.make_plant()
    sensors = exp.make_sensors()
    law = exp.law
    law.reset()
    t_arr = np.arange(n) * exp.dt
    x_arr, v_arr = exp.excitation.trajectory(t_arr)
    ts, xs, vs = t_arr.tolist(), np.asarray(x_arr, float).tolist(), np.asarray(v_arr, float).tolist()
    if sensors is None:
        xms, vms = xs, vs
    else:
        xms = [sensors.x(x) for x in xs]
        vms = [sensors.v(v) for v in vs]
    cols = {c: array("d", bytes(8 * n)) for c in ("F_des", "F", "I", "I_applied", "z")}
    cfd, cf, ci, cia, cz = cols["F_des"], cols["F"], cols["I"], cols["I_applied"], cols["z"]
    # local bindings: attribute lookups cost as much as the physics here
    demand, current, applied = exp.demand.force, law.current, law.applied
    ptick, model = plant.tick, plant.model
    t0 = time.perf_counter()
    for k in range(n):
        vm = vms[k]
        Fd = demand(ts[k], xms[k], vm)
        I = current(vm, Fd)
        # the daemon's current guard: clamp to [0, I_max], NaN → 0 A
        Ic = (I if I < I_max else I_max) if I > 0.0 else 0.0
        if Ic != I:  # tell the law only when the guard changed its output
            I = Ic
            applied(I)
        cf[k] = ptick(vs[k], I)
        cfd[k] = Fd
        ci[k] = I
        cia[k] = plant.I_applied
        cz[k] = model.z
    wall = time.perf_counter() - t0
    out = {"t": t_arr, "x": np.asarray(x_arr, float), "v": np.asarray(v_arr, float)}
    out.update({c: np.frombuffer(a, dtype=float) for c, a in cols.items()})
    out["x_meas"] = np.asarray(xms, float)
    out["v_meas"] = np.asarray(vms, float)
    out["F_meas"] = out["F"].copy() if sensors is None else np.array([sensors.F(F) for F in out["F"].tolist()])
    summary = tracking_summary(out["t"], out["F_des"], out["F"], out["I"], I_max, exp.excitation.settle_s)
    summary["ticks"] = float(n)
    summary["simulated_s"] = (n - 1) * exp.dt
    summary["wall_s"] = wall
    summary["realtime_factor"] = ((n - 1) * exp.dt / wall) if wall > 0 else math.inf
    return SimResult(out, wall, summary)


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
