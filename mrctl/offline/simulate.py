"""Offline closed loop of the paper's Fig 4, on the compiled tick, in blocks.

No pacing, no threads: excitation → (sensors) → demand → inverse law →
clamp → plant, once per tick, with the same objects the daemon uses. The
tick order is the daemon's: sample at t_k, command I_k, the plant's force
at t_k is with I_k applied (a driver lag, if configured, delays that), or,
with ``plant.command_delay_ticks`` d, with I_(k-d): an exchange link's
current goes out with the next tick's request.

The loop runs in blocks of :data:`BLOCK_TICKS` ticks
(:func:`simulate_blocks`): each block goes to whoever consumes it (the run
log, :mod:`mrctl.offline.simulate_log`; the figures,
:mod:`mrctl.runlog.blockmetrics`) and is dropped, so memory does not grow
with the duration. :func:`simulate` keeps every block:
:attr:`SimResult.columns` are the simulation's own arrays (the plant's true
x, v, F and the sensors' readings apart); the run log (:func:`log_block`,
:func:`log_columns`) is ``mrctl run``'s, column for column
(docs/runlog.md).
"""

from __future__ import annotations

import math
import time
from array import array
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mrctl.config import ConfigError
from mrctl.core.offline import OfflineLoop
from mrctl.experiment import Experiment
from mrctl.laws.base import LawFault, Measurement
from mrctl.runlog.blockmetrics import FigureSet, LoadCellFigures, RideFigures, RowFigures, TrackingFigures
from mrctl.runlog.format import RUN_COLUMNS, RUN_UNITS

#: The simulation's own arrays (:attr:`SimResult.columns`): the plant's x, v,
#: F and the sensors' readings apart; ``F_meas[k]`` is the reading of F[k]
#: (which the controller receives at tick k + 1), ``F_rx[k]`` the reading
#: received at tick k.
SIM_COLUMNS = ("t", "x", "v", "F_des", "F", "I", "I_applied", "z", "x_meas", "v_meas", "F_meas", "F_rx")
#: What a block holds (F_meas is the next block's F_rx: :func:`simulate` joins it).
BLOCK_COLUMNS = tuple(c for c in SIM_COLUMNS if c != "F_meas")
#: What the run log holds: the daemon's columns (mrctl/runlog/format.py).
CSV_COLUMNS = RUN_COLUMNS
CSV_UNITS = tuple(RUN_UNITS[c] for c in RUN_COLUMNS)
#: Ticks a block: 16 s at 1 kHz, ~1.6 MB of columns. A multiple of every SIMD
#: width, so the shaker's motion computed a block at a time is the same, value
#: for value, as computed for the whole run at once.
BLOCK_TICKS = 16384
#: the driver's applied current before the first tick (what tick 0's sample reports)
I_APPLIED0 = 0.0

#: on_block(k0, block): the rows of ticks k0 .. k0 + len − 1, BLOCK_COLUMNS
#: and the bench's channels by name; the arrays are reused for the next
#: block, so a consumer copies what it keeps
BlockSink = Callable[[int, dict[str, np.ndarray]], None]


@dataclass
class SimResult:
    #: the simulation's arrays (:data:`SIM_COLUMNS` and the bench's channels); empty when streamed
    columns: dict[str, np.ndarray]
    wall_s: float
    summary: dict[str, float] = field(default_factory=dict)
    #: a law that raised or returned NaN/inf: the run ended at that tick, at 0 A
    fault: LawFault | None = None
    #: the driver's applied current before the first tick (what tick 0's sample reports)
    I_applied0: float = I_APPLIED0
    #: what the law flagged during the run (Law.notices), said once after it
    notices: list[str] = field(default_factory=list)
    #: the verdict's row figures (:class:`mrctl.runlog.blockmetrics.RowFigures`)
    row_figures: dict[str, float] = field(default_factory=dict)
    #: the load cell's reading of the last tick's force, as the next tick would have received it
    F_meas_last: float = math.nan
    #: the bench's channel names (the columns after :data:`SIM_COLUMNS`)
    channels: tuple[str, ...] = ()

    @property
    def ticks(self) -> int:
        return int(self.summary["ticks"])


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


def run_ticks(exp: Experiment, duration_s: float) -> int:
    """Ticks a run of ``duration_s`` has (both ends included)."""
    return int(round(duration_s / exp.dt)) + 1


#: the verdict's row figures (:func:`mrctl.runlog.acceptance.row_figures`): in
#: :attr:`SimResult.row_figures`, not in the summary
ROW_FIGURES = ("fault_share", "longest_zero_stretch_s", "longest_gap_s")


def offline_figures(exp: Experiment, channels: tuple[str, ...]) -> FigureSet:
    """The figures a simulation accumulates block by block, over its own
    columns (:data:`BLOCK_COLUMNS` and the bench's channels): tracking, the
    quarter car's ride, the verdict's row figures. A figure added here is in
    every simulation's summary (:mod:`mrctl.runlog.blockmetrics`)."""
    settle = exp.excitation.settle_s
    return FigureSet([TrackingFigures(settle, exp.I_max), *([RideFigures(settle)] if "a_sprung" in channels else []),
                      RowFigures(exp.dt, x="x_meas", fault=None, k=None), LoadCellFigures()])


def simulate_blocks(exp: Experiment, duration_s: float, on_block: BlockSink | None = None, *,
                    block_ticks: int = BLOCK_TICKS, progress: Callable[[int], None] | None = None) -> SimResult:
    """Run the closed loop for ``duration_s`` of simulated time, a block of
    ``block_ticks`` ticks at a time, each block handed to ``on_block`` and
    to the figures; the result without columns.

    One loop for every bench (:class:`mrctl.core.offline.OfflineLoop`, the
    compiled tick): the laws see what the daemon's sim link gives them: x
    and v at tick k, the load cell's reading of the force of tick k − 1,
    sensor noise drawn in the same order (x, v, F per tick), NaN in a
    channel the bench lacks (``plant.sensors.load_cell``/``velocity``), and
    the velocity the observer makes of them (``sensing``), as the controller
    does before its laws. On the shaker the motion is an open-loop input,
    computed a block ahead (numpy); a bench whose motion depends on the
    damper (``plant.bench: quarter_car``) is stepped as the sim link steps
    it. A law that raises or returns NaN/inf ends the run at that tick with
    0 A (``SimResult.fault``). ``progress(ticks done)`` after each block."""
    n = run_ticks(exp, duration_s)
    shaker = exp.config.plant.get("bench", "shaker") == "shaker"
    bench = exp.make_bench(trajectory=([], [])) if shaker else exp.make_bench()
    channels: dict[str, float] = getattr(bench, "channels", {})
    law, dem = exp.law, exp.demand
    law.reset()
    if dem is not None:
        dem.reset()
    loop = OfflineLoop(bench, law, dem, exp.make_observer(), Measurement(channels=channels), exp.I_max, exp.dt,
                       exp.command_delay_ticks)
    size = max(1, min(int(block_ticks), n))
    cols = {c: array("d", bytes(8 * size)) for c in (*BLOCK_COLUMNS, *channels)}
    views = {c: np.frombuffer(a, dtype=float) for c, a in cols.items()}
    figures = offline_figures(exp, tuple(channels))
    wall = 0.0
    k0 = 0
    while k0 < n and loop.fault is None:
        nb = min(size, n - k0)
        if shaker:
            x_arr, v_arr = exp.excitation.trajectory(np.arange(k0, k0 + nb) * exp.dt)
            bench.set_trajectory(np.asarray(x_arr, float).tolist(), np.asarray(v_arr, float).tolist(), k0)
        t0 = time.perf_counter()
        done = loop.run(cols, nb)
        wall += time.perf_counter() - t0
        block = {c: v[:done] for c, v in views.items()}
        figures.add(block)
        if on_block is not None:
            on_block(k0, block)
        k0 += done
        if progress is not None:
            progress(k0)
    if shaker:  # the load cell's reading of the last force, as the next tick would have received it
        F_last = bench.sensors.F(bench.F) if bench.sensors is not None else bench.F
        F_last = F_last if bench.has_load_cell else math.nan
    else:
        F_last = bench.F
    s = figures.result()
    row_figs = {key: s.pop(key) for key in ROW_FIGURES if key in s}
    s["ticks"] = float(k0)
    s["simulated_s"] = (k0 - 1) * exp.dt
    s["wall_s"] = wall
    s["realtime_factor"] = ((k0 - 1) * exp.dt / wall) if wall > 0 else math.inf
    return SimResult({}, wall, s, loop.fault, notices=law.notices(), row_figures=row_figs,
                     F_meas_last=float(F_last), channels=tuple(channels))


def simulate(exp: Experiment, duration_s: float, block_ticks: int = BLOCK_TICKS) -> SimResult:
    """:func:`simulate_blocks` keeping every block: :attr:`SimResult.columns`
    holds the whole run (for short runs and studies: sweeps, tests)."""
    kept: dict[str, list[np.ndarray]] = {}

    def keep(k0: int, block: dict[str, np.ndarray]) -> None:
        for c, v in block.items():
            kept.setdefault(c, []).append(v.copy())

    res = simulate_blocks(exp, duration_s, keep, block_ticks=block_ticks)
    out = {c: np.concatenate(kept[c]) if c in kept else np.zeros(0) for c in BLOCK_COLUMNS}
    if len(out["F_rx"]):  # the reading of F[k] is what tick k + 1 received
        out["F_meas"] = np.concatenate((out["F_rx"][1:], [res.F_meas_last]))
    else:
        out["F_meas"] = np.zeros(0)
    res.columns = {c: out[c] for c in SIM_COLUMNS} | {c: np.concatenate(kept[c]) for c in res.channels}
    return res


def log_block(block: dict[str, np.ndarray], k0: int, I_applied_before: float) -> dict[str, np.ndarray]:
    """The run log's columns of the block of ticks ``k0`` … of a simulation:
    :data:`RUN_COLUMNS` with ``mrctl run``'s meaning per column
    (docs/runlog.md): x, v, F as the controller received them (F: the
    reading of the previous tick's force), F_true the plant's force of the
    tick, I_applied what the driver reported at the sample
    (``I_applied_before``: the applied current of tick k0 − 1); no clock,
    supervisor or link offline (late_us, compute_us NaN; fault, link_errors 0)."""
    n = len(block["t"])
    k = np.arange(k0, k0 + n, dtype=float)
    nan = np.full(n, math.nan)
    zero = np.zeros(n)
    I_seen = np.concatenate(([I_applied_before], block["I_applied"][:-1])) if n else zero
    return {"t": block["t"], "x": block["x_meas"], "v": block["v_meas"], "F_des": block["F_des"], "F": block["F_rx"],
            "I": block["I"], "k": k, "seq": k, "t_dev": block["t"], "I_applied": I_seen, "F_true": block["F"],
            "late_us": nan, "compute_us": nan, "fault": zero, "link_errors": zero}


def log_columns(result: SimResult) -> dict[str, np.ndarray]:
    """The run log of a whole simulation kept by :func:`simulate`."""
    return log_block(result.columns, 0, result.I_applied0)
