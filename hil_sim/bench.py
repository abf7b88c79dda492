"""The device side of the simulated bench: its own fixed-rate clock.

Each tick k (absolute deadlines on ``time.monotonic_ns``, via
:class:`mrctl.daemon.loop.FixedRateLoop`, hybrid sleep-then-spin by default):

1. ``SimBench.begin_tick(k)`` moves the shaker to t = k·dt;
2. the sensors are read (``sample()``: noisy, quantised; F is the last
   completed tick's force, NaN without a load cell);
3. the latest setpoint is taken from :class:`~hil_sim.state.DeviceState`
   and turned into the driver input: 0 A before the first setpoint, when
   ``enable`` is clear, or when the watchdog has expired (no setpoint for
   ``watchdog_ms``: the host's requested value, or the configured default);
   otherwise the setpoint clamped to [0, I_max_A];
4. ``command(I)``: the plant produces tick k's true force;
5. ``Sample(seq=k mod 2**32, t_dev_s=k·dt, x, v, F, status, I_applied)`` is
   published for the protocol servers, and the truth row is logged.

Scheduled faults (:mod:`hil_sim.faults`): the clock computes the active bits
of tick k, publishes them for the servers (``DeviceState.fault_bits``) and
applies the sample faults itself: ``stale_seq`` freezes the published seq,
``nan`` / ``out_of_range`` replace x (or v), ``ignore_setpoints`` keeps the
setpoint of the fault's first tick. The truth row records the faulted
measurement and the bits (``fault`` column).

Status bits: ``OUTPUT_ENABLED`` while a live, enabled setpoint is applied;
``WATCHDOG_TRIPPED`` latched from the first expiry until a CLEAR_FAULTS
request; ``CURRENT_CLAMPED`` when the last setpoint was out of range or
non-finite; ``NO_LOAD_CELL`` without a load cell.

Late ticks: the loop skips deadlines it overran (k jumps); the plant runs
the skipped ticks on the held command (``SimBench.begin_tick``), so the
physics stays on the k·dt grid and only the skipped rows are missing from
the truth log. The sensor noise of skipped ticks is drawn and discarded, so
the noise at tick k is a function of (seed, k) alone: with the same seed and
the same setpoints, runs agree tick for tick whatever deadlines they missed.
"""

from __future__ import annotations

import math
import threading

from mrctl.io.base import Sample, Status
from mrctl.daemon.loop import FixedRateLoop

from hil_sim.config import BenchConfig
from hil_sim.faults import FaultBit, FaultSchedule, bit_names
from hil_sim.state import DeviceState
from hil_sim.truth import TruthLog

__all__ = ["BenchDevice", "clamp_setpoint"]

_U32 = 0xFFFFFFFF
_OUTPUT_ENABLED = int(Status.OUTPUT_ENABLED)
_WATCHDOG_TRIPPED = int(Status.WATCHDOG_TRIPPED)
_CURRENT_CLAMPED = int(Status.CURRENT_CLAMPED)
_NO_LOAD_CELL = int(Status.NO_LOAD_CELL)
_STALE = int(FaultBit.STALE_SEQ)
_NAN = int(FaultBit.NAN)
_OOR = int(FaultBit.OUT_OF_RANGE)
_IGNORE_SP = int(FaultBit.IGNORE_SETPOINTS)
_ESTOP_F = int(FaultBit.ESTOP)
_ESTOP = int(Status.ESTOP)
#: a gap between ticks longer than this many periods is the emulator's own stall, not the host's silence
_STALL_PERIODS = 4


def clamp_setpoint(I: float, I_max: float) -> tuple[float, bool]:
    """(current the driver accepts, whether it had to be clamped). NaN/inf → 0 A."""
    if not math.isfinite(I):
        return 0.0, True
    if I < 0.0:
        return 0.0, True
    if I > I_max:
        return I_max, True
    return I, False


class BenchDevice:
    """The simulated bench (shaker or quarter car) + device logic (setpoint, watchdog, status) on a fixed-rate clock."""

    def __init__(self, cfg: BenchConfig, state: DeviceState, truth: TruthLog | None = None,
                 wait: str = "hybrid", spin_margin_s: float = 2e-4, idle=None) -> None:
        self.cfg = cfg
        self.state = state
        self.truth = truth
        # the same bench as the in-process sim link, built the same way (plant.bench, plant.model)
        self.bench = cfg.make_bench()
        #: the bench's extra channels (a dict it updates in place), published with each sample
        self._channels = getattr(self.bench, "channels", {})
        state.channel_names = tuple(self._channels)
        self._sensors = self.bench.sensors
        self.loop = FixedRateLoop(cfg.rate_hz, wait=wait, spin_margin_s=spin_margin_s, idle=idle)
        self.I_max = cfg.I_max_A
        self.default_watchdog_ns = cfg.watchdog_ms * 1_000_000
        self._base_status = 0 if cfg.load_cell else _NO_LOAD_CELL
        self._tripped = False  # WATCHDOG_TRIPPED latch
        self._estop = False  # the device's E-stop latch (status ESTOP, 0 A) until CLEAR_FAULTS
        #: ticks held at 0 A by the E-stop (the input open, or the device's latch)
        self.estop_ticks = 0
        self._expired = False  # watchdog expired now (setpoints absent)
        self._prev_now_ns = 0  # the previous tick's time: a longer gap is this process's own stall
        self._stall_ns = _STALL_PERIODS * self.loop.period_ns
        self._clears_seen = 0
        self.k_last = -1
        self.ticks = 0
        #: times the watchdog expired (one per stretch of absent setpoints)
        self.watchdog_trips = 0
        self.first_trip_k: int | None = None
        self.clamped_ticks = 0
        # scheduled faults (hil_sim/faults.py): None = none, no per-tick cost
        self.faults = FaultSchedule(cfg.faults, cfg.rate_hz) if cfg.faults else None
        state.faults = self.faults
        self._fbits = 0
        self._frozen_seq = 0
        self._frozen_sp: tuple[float, bool] = (0.0, False)
        self._prev_sp: tuple[float, bool] = (0.0, False)
        #: fault windows as they opened/closed: [{k, start|end}]
        self.fault_events: list[dict] = []
        #: every watchdog expiry: {k, last_setpoint_age_ms, last_setpoint_k}
        self.watchdog_events: list[dict] = []
        #: host starts (first setpoint after silence) with the tick that applied it
        self.starts: list[dict] = []
        self._starts_seen = 0
        #: set once the first sample is published (the process may say READY)
        self.first_tick = threading.Event()

    # -- the tick -------------------------------------------------------------
    def tick(self, k: int, now_ns: int) -> None:
        b = self.bench
        if k != self.k_last + 1 and self._sensors is not None:
            self._skip_noise(k - self.k_last - 1)
        b.begin_tick(k)
        x_m, v_m, F_m = b.sample()
        state = self.state
        I_req, enable, sp_ns, wd_ms, clears = state.setpoint_ex()
        fbits = 0
        seq = k & _U32
        sched = self.faults
        if sched is not None:
            fbits = sched.active(k)
            if fbits != self._fbits:
                self._fault_change(fbits, k)
            if fbits:
                if fbits & _STALE:
                    seq = self._frozen_seq
                if fbits & _NAN:
                    if sched.param(_NAN, "field") == "v":
                        v_m = math.nan
                    else:
                        x_m = math.nan
                if fbits & _OOR:
                    x_m = sched.param(_OOR, "x_m")
                if fbits & _IGNORE_SP:
                    I_req, enable = self._frozen_sp
            self._prev_sp = (I_req, enable)
        if len(state.starts) != self._starts_seen:
            self._tag_starts(k)
        estop_in = bool(fbits & _ESTOP_F)
        state.estop_input = estop_in
        if clears != self._clears_seen:
            self._clears_seen = clears
            self._tripped = False
            self._estop = False
        if estop_in and state.estop_latches:
            self._estop = True
        status = self._base_status
        if sp_ns == 0:
            # Watchdog from power-up: 0 A until the first setpoint (not a trip).
            I = 0.0
        elif self._silence_ns(now_ns, sp_ns) > (wd_ms * 1_000_000 if wd_ms > 0 else self.default_watchdog_ns):
            I = 0.0
            if not self._expired:
                self._expired = True
                self.watchdog_trips += 1
                if self.first_trip_k is None:
                    self.first_trip_k = k
                if len(self.watchdog_events) < 1000:
                    # the device tick the last setpoint arrived in, from its age
                    age = now_ns - sp_ns
                    self.watchdog_events.append({"k": k, "last_setpoint_age_ms": round(age / 1e6, 3),
                                                 "last_setpoint_k": k - int(age // self.loop.period_ns)})
            self._tripped = True
        else:
            self._expired = False
            I, clamped = clamp_setpoint(I_req, self.I_max)
            if clamped:
                status |= _CURRENT_CLAMPED
                self.clamped_ticks += 1
            if enable:
                status |= _OUTPUT_ENABLED
            else:
                I = 0.0
        if self._tripped:
            status |= _WATCHDOG_TRIPPED
        if estop_in or self._estop:  # the hard-wired chain (and a device's latch) hold the driver off
            I = 0.0
            status = (status & ~_OUTPUT_ENABLED) | _ESTOP
            self.estop_ticks += 1
        b.command(I)
        t = b.t
        I_app = b.I_applied
        t0 = self.loop.t_start_ns  # the sample is the bench at its deadline, however late this tick runs
        state.publish(Sample(seq, t, x_m, v_m, F_m, status, I_app),
                      tuple(self._channels.values()) if self._channels else (),
                      0 if t0 is None else t0 + k * self.loop.period_ns)
        if state.owed_now:  # device pacing: answer SYNC requests with this sample
            state.run_owed()
        if self.truth is not None:
            self.truth.record((k, t, b.x, b.v, b.F, b.I_cmd, I_app, x_m, v_m, F_m, status, fbits))
        self.k_last = k
        self._prev_now_ns = now_ns
        self.ticks += 1
        if not self.first_tick.is_set():
            self.first_tick.set()

    def _silence_ns(self, now_ns: int, sp_ns: int) -> int:
        """How long the host has been silent, as the device saw it. A real
        device never stalls; this process can (a loaded machine), and the
        setpoints sent meanwhile wait unread in its socket. After a gap of more
        than _STALL_PERIODS periods the silence counts only up to a period past
        the tick before it; the next tick, a period later, counts it whole, the
        server thread having had that period to read what waited."""
        prev = self._prev_now_ns
        if now_ns - prev > self._stall_ns:  # then now_ns is past prev + one period
            return prev + self.loop.period_ns - sp_ns
        return now_ns - sp_ns

    def _fault_change(self, fbits: int, k: int) -> None:
        """A fault window opened or closed at this tick (rare: not the hot path)."""
        started = fbits & ~self._fbits
        if started & _STALE:
            self._frozen_seq = self.k_last & _U32 if self.k_last >= 0 else 0
        if started & _IGNORE_SP:
            self._frozen_sp = self._prev_sp  # what the driver had before this tick
        for bit in FaultBit:
            if started & bit:
                self.fault_events.append({"k": k, "start": bit_names(int(bit))})
            elif self._fbits & ~fbits & bit:
                self.fault_events.append({"k": k, "end": bit_names(int(bit))})
        self._fbits = fbits
        self.state.fault_bits = fbits

    def _tag_starts(self, k: int) -> None:
        """Give the host starts that began since the last tick their tick k."""
        new = self.state.starts[self._starts_seen:]
        self._starts_seen += len(new)
        for ns, I, en in new:
            self.starts.append({"k": k, "first_setpoint_A": I, "enable": en, "t_mono_ns": ns})

    def _skip_noise(self, n: int) -> None:
        """Draw the noise of ``n`` skipped ticks, so tick k's noise depends on
        (seed, k) only, not on which deadlines the clock happened to miss."""
        s = self._sensors
        for _ in range(n):
            s.x(0.0)
            s.v(0.0)
            s.F(0.0)

    def safe_tick(self) -> None:
        """One last tick at 0 A with the output disabled (on stop)."""
        k = self.k_last + 1
        b = self.bench
        b.begin_tick(k)
        x_m, v_m, F_m = b.sample()
        b.command(0.0)
        status = (self._base_status | (_WATCHDOG_TRIPPED if self._tripped else 0)
                  | (_ESTOP if self._estop else 0))
        self.state.publish(Sample(k & _U32, b.t, x_m, v_m, F_m, status, b.I_applied))
        if self.truth is not None:
            self.truth.record((k, b.t, b.x, b.v, b.F, b.I_cmd, b.I_applied, x_m, v_m, F_m, status, 0))
        self.k_last = k
        self.ticks += 1

    # -- running ----------------------------------------------------------------
    def run(self, duration_s: float | None = None) -> int:
        """Run the clock until :meth:`stop` or ``duration_s``; then one 0 A tick."""
        try:
            return self.loop.run(self.tick, duration_s=duration_s)
        finally:
            self.safe_tick()
            self.first_tick.set()

    def stop(self) -> None:
        """Stop after the current tick (thread- and signal-safe)."""
        self.loop.stop()

    def summary(self) -> dict:
        timing = self.loop.stats.summary()
        return {
            "ticks": self.ticks,
            "last_k": self.k_last,
            "rate_hz": self.cfg.rate_hz,
            "watchdog_ms": self.cfg.watchdog_ms,
            "watchdog_trips": self.watchdog_trips,
            "first_watchdog_trip_k": self.first_trip_k,
            "clamped_ticks": self.clamped_ticks,
            "estop_ticks": self.estop_ticks,
            "setpoints_received": self.state.setpoints_received,
            "requests_served": self.state.requests_served,
            "timing": timing,
            "faults": self.faults.describe() if self.faults is not None else [],
            "fault_events": self.fault_events,
            "watchdog_events": self.watchdog_events,
            "setpoint_starts": self.starts,
        }
