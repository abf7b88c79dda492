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
from mrctl.laws.base import LawFault, Measurement, clamp_current

CSV_COLUMNS = ("t", "x", "v", "F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas")
CSV_UNITS = ("s", "m", "m/s", "N", "N", "A", "A", "m", "m", "m/s", "N")


@dataclass
class SimResult:
    columns: dict[str, np.ndarray]
    wall_s: float
    summary: dict[str, float] = field(default_factory=dict)
    #: a law that raised or returned NaN/inf: the run ended at that tick, at 0 A
    fault: LawFault | None = None

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
    k − 1, sensor noise drawn in the same order (x, v, F per tick).

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
    cols = {c: array("d", bytes(8 * n)) for c in ("F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas")}
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
    return SimResult(out, wall, summary, fault)


def _loop(exp: Experiment, ts: list[float], xs: list[float], vs: list[float], cols: dict[str, array]
          ) -> tuple[int, LawFault | None]:
    """The per-tick loop on the shaker; (ticks done, law fault or None)."""
    n, I_max = len(ts), exp.I_max
    plant, sensors = exp.make_plant(), exp.make_sensors()
    cfd, cf, ci, cia, cz = cols["F_des"], cols["F"], cols["I"], cols["I_applied"], cols["z"]
    cxm, cvm, cfm = cols["x_meas"], cols["v_meas"], cols["F_meas"]
    # local bindings: attribute lookups cost as much as the physics here
    demand = exp.demand.force if exp.demand is not None else None
    current, applied = exp.law.current, exp.law.applied
    ptick, model = plant.tick, plant.model
    dname, lname = (exp.config.demand.type if demand is not None else ""), exp.config.inverse.law
    m = Measurement()
    F_prev = 0.0  # the plant's force before the first tick (SimBench starts there too)
    I, Fd = 0.0, math.nan
    fault: LawFault | None = None
    for k in range(n):
        x, v = xs[k], vs[k]
        if sensors is None:
            xm, vm, Fm = x, v, F_prev
        else:
            xm, vm, Fm = sensors.x(x), sensors.v(v), sensors.F(F_prev)
        if k:
            cfm[k - 1] = Fm
        m.k, m.t, m.x, m.v, m.F, m.I_applied, m.I_cmd = k, ts[k], xm, vm, Fm, plant.I_applied, I
        who = dname
        try:  # the law guard (docs/laws.md): zero cost on the good path
            Fd = demand(m) if demand is not None else math.nan
            who = lname
            I = current(m, Fd)
            if I - I != 0.0 or (demand is not None and Fd - Fd != 0.0):  # NaN or inf
                fault = LawFault("non-finite", lname if I - I != 0.0 else dname, k, ts[k], f"F_des = {Fd!r}, I = {I!r}")
        except Exception as exc:  # noqa: BLE001 - a law's failure is a fault, not a crash
            fault = LawFault("raised", who, k, ts[k], f"{type(exc).__name__}: {exc}")
        if fault is not None:
            I = 0.0  # the run ends at this tick, at 0 A
        else:
            Ic = clamp_current(I, I_max)
            if Ic != I:  # tell the law only when the guard changed its output
                I = Ic
                applied(I)
        F_prev = cf[k] = ptick(v, I, x)
        cxm[k], cvm[k], cfd[k], ci[k], cia[k], cz[k] = xm, vm, Fd, I, plant.I_applied, model.z
        if fault is not None:
            n = k + 1
            break
    cfm[n - 1] = F_prev if sensors is None else sensors.F(F_prev)
    return n, fault


def write_csv(result: SimResult, path: str | Path, comment: str | None = None) -> None:
    """CSV with a header row; optional leading '# ' comment lines (metadata)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    names = CSV_COLUMNS + tuple(c for c in result.columns if c not in CSV_COLUMNS)  # + a bench's channels
    data = np.column_stack([result.columns[c] for c in names])
    header = ",".join(names)
    with p.open("w") as fh:
        if comment:
            for line in comment.splitlines():
                fh.write(f"# {line}\n")
        fh.write(header + "\n")
        np.savetxt(fh, data, delimiter=",", fmt="%.10g")
