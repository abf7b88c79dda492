"""Offline closed loop of the paper's Fig 4, on the compiled tick.

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
from mrctl.core.offline import run_ticks
from mrctl.laws.base import LawFault, Measurement
from mrctl.runlog import files
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS, RUN_UNITS
from mrctl.runlog.metrics import tracking_summary
from mrctl.runlog.ride import ride_summary

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

    One loop for every bench (:func:`mrctl.core.offline.run_ticks`, the
    compiled tick): the laws see what the daemon's sim link gives them: x
    and v at tick k, the load cell's reading of the force of tick k − 1,
    sensor noise drawn in the same order (x, v, F per tick), NaN in a
    channel the bench lacks (``plant.sensors.load_cell``/``velocity``), and
    the velocity the observer makes of them (``sensing``), as the controller
    does before its laws. On the shaker the motion is an open-loop input,
    computed for the whole run up front (numpy); a bench whose motion
    depends on the damper (``plant.bench: quarter_car``) is stepped as the
    sim link steps it. A law that raises or returns NaN/inf ends the run at
    that tick with 0 A (``SimResult.fault``)."""
    n = int(round(duration_s / exp.dt)) + 1
    shaker = exp.config.plant.get("bench", "shaker") == "shaker"
    if shaker:
        t_arr = np.arange(n) * exp.dt
        x_arr, v_arr = exp.excitation.trajectory(t_arr)
        bench = exp.make_bench(trajectory=(np.asarray(x_arr, float).tolist(), np.asarray(v_arr, float).tolist()))
    else:
        bench = exp.make_bench()
    channels: dict[str, float] = getattr(bench, "channels", {})
    cols = {c: array("d", bytes(8 * n)) for c in (*SIM_COLUMNS, *channels)}
    law, dem = exp.law, exp.demand
    law.reset()
    if dem is not None:
        dem.reset()
    m = Measurement(channels=channels)
    t0 = time.perf_counter()
    fault, done = run_ticks(bench, law, dem, exp.make_observer(), m, exp.I_max, exp.dt, cols, n)
    wall = time.perf_counter() - t0
    if shaker:  # the load cell's reading of the last force, as the next tick would have received it
        cols["F_meas"][done - 1] = bench.sensors.F(bench.F) if bench.sensors is not None else bench.F
        if not bench.has_load_cell:
            cols["F_meas"][done - 1] = math.nan
    out = {c: np.frombuffer(a, dtype=float)[:done] for c, a in cols.items()}
    s = tracking_summary(out["t"], out["F_des"], out["F"], out["I"], exp.I_max, exp.excitation.settle_s)
    if "a_sprung" in out:
        s.update(ride_summary(out, exp.excitation.settle_s))
    s["ticks"] = float(done)
    s["simulated_s"] = (done - 1) * exp.dt
    s["wall_s"] = wall
    s["realtime_factor"] = ((done - 1) * exp.dt / wall) if wall > 0 else math.inf
    return SimResult(out, wall, s, fault, notices=law.notices())


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
