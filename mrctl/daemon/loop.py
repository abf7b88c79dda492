"""Fixed-rate scheduler for the control loop.

Why absolute deadlines: deadline_k = t_start + k·period_ns is computed from
the start time, never by adding a period to "now", so waking late on one tick
never shifts later ticks (no drift). ``period_ns`` is the rate's period
rounded to a whole nanosecond, so the rate is exact to ≤ 0.5 ns per period
(0.5 ppm at 1 kHz).

Why skip instead of catching up: if a tick ends after the next deadline the
loop is already late; running the missed ticks back-to-back would write a
burst of stale commands to the driver. Instead the tick is counted as an
overrun and the schedule jumps to the first deadline at or after the tick's
end; the deadlines jumped over are counted as skipped. Tick functions get the
deadline index ``k`` (not a tick counter), so ``k`` jumps too and the
controller can use ``(k − k_prev)·period`` as its time step.

Wait strategies (trade CPU for wake-up accuracy):

* ``"sleep"``  — ``time.sleep`` until the deadline: ~0 CPU, lateness is the
  OS's timer latency + timer slack (50 µs default for SCHED_OTHER; see
  :mod:`mrctl.daemon.rt`, which can lower it).
* ``"hybrid"`` — sleep until ``spin_margin_s`` before the deadline, then
  busy-spin on the clock: accurate wake-ups for ~margin/period of a core.
* ``"spin"``   — busy-spin: most accurate, burns a whole core.

The hot path is plain ints and floats: no numpy, logging, I/O or avoidable
allocation (CPython still boxes the ns ints it computes).
"""

from __future__ import annotations

import time
from typing import Callable

from mrctl.daemon.timing import TimingStats

WAIT_STRATEGIES = ("sleep", "hybrid", "spin")
_SLEEP, _HYBRID, _SPIN = range(3)

#: tick(k, now_ns) -> bool: k is the deadline index, now_ns the wake-up time
#: (clock ns). Return False to stop; any other value (including None) continues.
Tick = Callable[[int, int], object]
#: Device-paced tick(n, now_ns, sample): n counts samples.
DeviceTick = Callable[[int, int, object], object]


class FixedRateLoop:
    """Runs a tick function at a fixed rate on absolute deadlines.

    ``clock`` (→ int ns, monotonic) and ``sleep`` (seconds) are injectable so
    tests can drive the loop with a fake clock. Timing of every tick goes into
    ``self.stats``.
    """

    def __init__(
        self,
        rate_hz: float,
        wait: str = "hybrid",
        spin_margin_s: float = 3e-4,
        clock: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], object] = time.sleep,
        stats: TimingStats | None = None,
        idle: Callable[[], object] | None = None,
        background: Callable[[int], object] | None = None,
        background_guard_s: float = 2e-4,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        if wait not in WAIT_STRATEGIES:
            raise ValueError(f"wait must be one of {WAIT_STRATEGIES}, got {wait!r}")
        if not spin_margin_s >= 0:
            raise ValueError(f"spin_margin_s must be >= 0, got {spin_margin_s!r}")
        self.rate_hz = float(rate_hz)
        self.period_ns = max(1, round(1e9 / self.rate_hz))
        self.wait = wait
        self.spin_margin_ns = round(spin_margin_s * 1e9)
        self.stats = stats if stats is not None else TimingStats()
        #: clock value of deadline 0 of the last run (ns), for tests/diagnostics.
        self.t_start_ns: int | None = None
        self._clock = clock
        self._sleep = sleep
        self._mode = WAIT_STRATEGIES.index(wait)
        self._stop = False
        #: called on every pass of the spin phase (spin, and hybrid's last part):
        #: lets a single-threaded device serve its link while it waits, with no
        #: thread wake-up in between (hil_sim's inline serving).
        self._idle = idle
        #: background(until_ns): bounded work done in the loop thread after a
        #: tick, to be finished by until_ns = the moment the wait must begin
        #: (hybrid: deadline − spin margin) minus ``background_guard_s``.
        #: Used to format the run log here rather than in a second thread
        #: that would take the GIL from the loop (see mrctl/daemon/recorder.py).
        self.background = background
        self.background_guard_ns = round(background_guard_s * 1e9)

    def stop(self) -> None:
        """Ask the loop to end after the current tick.

        Safe from another thread or a signal handler (a plain attribute store).
        Sticky: a stopped loop's ``run`` returns at once; make a new loop to
        run again. Checked once per tick, so it takes effect within a period.
        """
        self._stop = True

    @property
    def stopped(self) -> bool:
        """True once :meth:`stop` was called."""
        return self._stop

    def run(
        self,
        tick: Tick,
        max_ticks: int | None = None,
        duration_s: float | None = None,
    ) -> int:
        """Host-paced loop; returns the number of ticks run.

        Ends on ``stop()``, ``tick`` returning False, after ``max_ticks``
        ticks, or once the next deadline is ``duration_s`` or more after the
        start (so at 1 kHz, ``duration_s=1`` runs deadlines 0…999).
        """
        if max_ticks is not None and max_ticks <= 0:
            return 0
        clock = self._clock
        wait = self._wait
        record = self.stats.record
        period = self.period_ns
        margin = self.spin_margin_ns
        mode = self._mode
        limit = -1 if max_ticks is None else max_ticks
        if duration_s is None:
            k_end = -1
        else:
            # First deadline index at or past the duration: ceil(duration / period).
            k_end = -(-round(duration_s * 1e9) // period)

        bg = self.background
        bg_lead = self.background_guard_ns + (margin if mode == _HYBRID else 0)
        t0 = clock()
        self.t_start_ns = t0
        k = 0
        n = 0
        prev_wake = t0
        while not self._stop:
            if 0 <= k_end <= k:
                break
            deadline = t0 + k * period
            now = clock()
            if bg is not None and now < deadline - bg_lead:
                bg(deadline - bg_lead)
                now = clock()
            if now < deadline:
                now = wait(deadline, now)
            go_on = tick(k, now)
            end = clock()

            nxt = k + 1
            if end > t0 + nxt * period:
                # Overrun: jump to the first deadline at or after `end`.
                m = -((t0 - end) // period)  # ceil((end - t0) / period)
                record(now - deadline, end - now, now - prev_wake if n else 0, True, m - nxt)
                nxt = m
            else:
                record(now - deadline, end - now, now - prev_wake if n else 0, False, 0)
            prev_wake = now
            n += 1
            k = nxt
            if go_on is False or n == limit:
                break
        return n

    def _wait(self, deadline: int, now: int) -> int:
        """Wait by the configured strategy until ``deadline`` (clock ns);
        returns the clock reading at wake-up."""
        clock, idle = self._clock, self._idle
        mode = self._mode
        if mode == _SPIN:
            while now < deadline:
                if idle is not None:
                    idle()
                now = clock()
            return now
        if mode == _HYBRID:
            margin = self.spin_margin_ns
            if deadline - now > margin:
                self._sleep((deadline - margin - now) * 1e-9)
                now = clock()
            while now < deadline:
                if idle is not None:
                    idle()
                now = clock()
            return now
        sleep = self._sleep
        while now < deadline:
            sleep((deadline - now) * 1e-9)
            now = clock()
        return now

    def sleep_until(self, t_ns: int) -> None:
        """Sleep until this loop's clock reads ``t_ns`` (no-op if it has)."""
        clock, sleep = self._clock, self._sleep
        now = clock()
        while now < t_ns:
            sleep((t_ns - now) * 1e-9)
            now = clock()

    def run_device_paced(
        self,
        wait_sample: Callable[[], object | None],
        tick: DeviceTick,
        max_ticks: int | None = None,
        duration_s: float | None = None,
    ) -> int:
        """Loop paced by the backend's blocking read; returns the ticks run.

        ``wait_sample()`` blocks until the device delivers a sample and returns
        it, or None to end the run (give it a timeout so ``stop()`` is seen).
        Lateness is measured against the previous sample + period (so it is
        jitter and can be negative); a tick is an overrun if its compute time
        exceeds the period or the gap since the previous sample rounds to two
        or more periods, and ``round(gap / period) − 1`` samples count as
        skipped.
        """
        if max_ticks is not None and max_ticks <= 0:
            return 0
        clock = self._clock
        record = self.stats.record
        period = self.period_ns
        half = period // 2
        limit = -1 if max_ticks is None else max_ticks
        dur_ns = -1 if duration_s is None else round(duration_s * 1e9)

        t0 = clock()
        self.t_start_ns = t0
        n = 0
        prev_wake = t0
        while not self._stop:
            sample = wait_sample()
            if sample is None:
                break
            now = clock()
            if dur_ns >= 0 and now - t0 >= dur_ns:
                break
            go_on = tick(n, now, sample)
            end = clock()
            if n:
                gap = now - prev_wake
                skipped = (gap + half) // period - 1
                if skipped < 0:
                    skipped = 0
                record(gap - period, end - now, gap, skipped > 0 or end - now > period, skipped)
            else:
                record(0, end - now, 0, end - now > period, 0)
            prev_wake = now
            n += 1
            if go_on is False or n == limit:
                break
        return n
