"""The one object shared by the bench's clock thread and the protocol servers.

The clock thread publishes a sample per tick and reads the latest setpoint;
protocol servers (serial, Modbus TCP/RTU) do the opposite, from their own
threads. Both sides only swap references to immutable values under a lock,
so neither ever waits on the other for more than a few instructions.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

from mrctl.io.base import Sample

#: a setpoint after this much silence marks a host start (a host (re)start,
#: a reconnect): the first setpoint of each is kept, to show what a restarted
#: host commands first (docs/hil_sim.md)
START_GAP_NS = 20_000_000
MAX_STARTS = 1000


class OwedReply:
    """A SYNC (device-paced) reply whose sender is known only after the
    setpoint is in: the clock calls it after the tick that applied the
    setpoint, the transport gives the sender with :meth:`attach` once it has parsed
    the request; whichever comes second sends (the clock is normally later,
    by most of a period)."""

    __slots__ = ("_send", "_due", "_lock")

    def __init__(self) -> None:
        self._send: Callable[[], object] | None = None
        self._due = False
        self._lock = threading.Lock()

    def __call__(self) -> None:
        with self._lock:
            send = self._send
            if send is None:
                self._due = True
                return
        send()

    def attach(self, send: Callable[[], object]) -> None:
        with self._lock:
            self._send = send
            due = self._due
        if due:
            send()


class DeviceState:
    """Latest sample out, latest setpoint in; plus link bookkeeping."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        #: the E-stop input is open this tick (the clock's ``estop`` fault window): what a device
        #: that shows the raw input (the emulated T7's E-stop DIO) reads
        self.estop_input = False
        #: the device latches its E-stop (holds 0 A, reports ESTOP) until a CLEAR_FAULTS once the
        #: input closed (firmware-like devices); False: the latch is the host's (the emulated T7)
        self.estop_latches = True
        self._sample = Sample(seq=0, t_dev_s=0.0, x_m=0.0, v_mps=0.0, F_N=float("nan"), status=0)
        #: monotonic ns the latest sample stands for (0 = none yet): its tick's deadline, when
        #: its inputs were "converted" (the bench's time k·dt), for a device that stamps its samples
        #: (the emulated T7's CORE_TIMER); not when a late clock thread got round to publishing it
        self.sample_ns = 0
        #: the bench's extra channels (names fixed at start) and their values,
        #: published with each sample (docs/protocol.md §2.5, docs/registers.md)
        self.channel_names: tuple[str, ...] = ()
        self._channels: tuple[float, ...] = ()
        self._setpoint_A = 0.0
        self._enable = False
        self._setpoint_ns = 0  # monotonic time of the last setpoint (0 = never)
        self._watchdog_ms = 0  # watchdog the host asked for with it (0 = device default)
        self._clear_requests = 0  # CLEAR_FAULTS requests so far (the clock acts on changes)
        self.setpoints_received = 0
        self.requests_served = 0
        #: fault bits of the latest device tick (hil_sim.faults.FaultBit); written by
        #: the clock only, read by the servers (a plain int attribute: atomic)
        self.fault_bits = 0
        #: the FaultSchedule (parameters of the active faults), or None
        self.faults = None
        #: replies owed to SYNC (device-paced) requests: callables the clock runs
        #: right after it publishes the sample of the tick that applied them
        self._owed: list = []
        #: clock side: the owed replies taken with this tick's setpoint
        self.owed_now: list = []
        #: "host starts": (monotonic ns, current A, enable) of every setpoint that
        #: arrived after START_GAP_NS of silence (or the very first); bounded
        self.starts: list[tuple[int, float, bool]] = []

    # -- clock side -------------------------------------------------------
    def publish(self, sample: Sample, channels: tuple[float, ...] = (), at_ns: int = 0) -> None:
        """The clock's sample of its tick; ``at_ns``: the monotonic ns it stands for (the tick's
        deadline; 0: now)."""
        if at_ns <= 0:
            at_ns = time.monotonic_ns()
        with self._lock:
            self._sample = sample
            self._channels = channels
            self.sample_ns = at_ns

    def latest_sample_ns(self) -> tuple[Sample, int]:
        """The latest sample and the monotonic ns it was published at, in one step."""
        with self._lock:
            self.requests_served += 1
            return self._sample, self.sample_ns

    def setpoint(self) -> tuple[float, bool, int]:
        """(current A, enable, monotonic ns of arrival or 0 if none yet)."""
        with self._lock:
            return self._setpoint_A, self._enable, self._setpoint_ns

    def setpoint_ex(self) -> tuple[float, bool, int, int, int]:
        """:meth:`setpoint` plus (requested watchdog ms or 0, CLEAR_FAULTS request count).

        Also moves the replies owed so far to :attr:`owed_now`, in the same
        locked step: a SYNC request whose setpoint this tick applies is
        answered with this tick's sample, one that arrives later with the
        next tick's."""
        with self._lock:
            if self._owed:
                self.owed_now, self._owed = self._owed, self.owed_now
            return (self._setpoint_A, self._enable, self._setpoint_ns,
                    self._watchdog_ms, self._clear_requests)

    def run_owed(self) -> None:
        """Clock side, after :meth:`publish`: send the replies taken with this
        tick's setpoint (each builds its reply from the sample just published)."""
        owed = self.owed_now
        while owed:
            owed.pop(0)()

    # -- protocol side ----------------------------------------------------
    def latest_sample(self) -> Sample:
        with self._lock:
            self.requests_served += 1
            return self._sample

    def latest_sample_ex(self) -> tuple[Sample, tuple[float, ...]]:
        """The latest sample and the channel values published with it (same
        order as :attr:`channel_names`), in one step."""
        with self._lock:
            self.requests_served += 1
            return self._sample, self._channels

    def set_setpoint(
        self, current_A: float, enable: bool = True, watchdog_ms: int = 0, clear_faults: bool = False,
        owe: Callable[[], object] | None = None,
    ) -> None:
        """Accept a setpoint (restarts the device watchdog). ``watchdog_ms``:
        the host's requested watchdog, 0 = device default; ``clear_faults``:
        also clear latched status bits (serial CLEAR_FAULTS flag); ``owe``:
        a SYNC request's reply, run by the clock after the tick that applies
        this setpoint (taken in the same locked step, so never earlier)."""
        now = time.monotonic_ns()
        with self._lock:
            if (self._setpoint_ns == 0 or now - self._setpoint_ns > START_GAP_NS) \
                    and len(self.starts) < MAX_STARTS:
                self.starts.append((now, float(current_A), bool(enable)))
            self._setpoint_A = current_A
            self._enable = enable
            self._setpoint_ns = now
            self._watchdog_ms = watchdog_ms
            if clear_faults:
                self._clear_requests += 1
            self.setpoints_received += 1
            if owe is not None:
                self._owed.append(owe)

    def request_clear_faults(self) -> None:
        """Clear latched status bits (WATCHDOG_TRIPPED) at the next tick."""
        with self._lock:
            self._clear_requests += 1
