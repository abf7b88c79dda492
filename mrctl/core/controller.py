"""One control tick: read → demand law → inverse law → safety → write → record.

The loop (:mod:`mrctl.daemon.loop`) knows timing, not physics; the backends know
bytes, not physics; this module joins them and nothing else. The tick is
called at 1 kHz, so it allocates nothing it can avoid, does no I/O but the
backend's, and hands its row to the recorder's bounded buffer.

Two backend shapes:

- *split* (``backend.split`` is true: the in-process sim): read the sample,
  compute, write the current, all within the tick. Zero latency, the same
  tick order as ``mrctl simulate``.
- *exchange* (serial, Modbus): one transaction per tick writes the current
  computed on the previous tick and returns the latest sample; the current
  for it goes out on the next tick (one tick of latency, inherent to a single
  request/reply per tick).

A driver write that fails is retried within the tick budget; if it still
fails, the supervisor latches a DRIVER fault and the run ends: the service
then commands 0 A where it still can and exits non-zero. On exchange links
the setpoint shares the link with the samples, so ``link_loss_ticks``
consecutive failed exchanges mean the driver is lost too; a ``Disconnected``
link is reopened at most every ``reconnect_every_ticks`` before that.

The whole good path of a tick (sample checks, observer, demand, built-in
law, clamp and slew, the log row) is compiled with mypyc (mrctl/build.py):
one call per tick from the loop, native calls inside. Rare paths (faults,
reloads, reconnects) are the same code, and a plugin law is called back as
ordinary Python.

The law guard judges a law's time on the loop thread's CPU clock (time the
thread actually computed), not on the wall clock: a tick preempted by
another process is an overrun the loop counts, not the law's fault.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Final

from mrctl.core.safety import SafetySupervisor
from mrctl.estimation.lead import VelocityLead
from mrctl.estimation.observer import KinematicObserver
from mrctl.io.base import Disconnected, Link, LinkError, Sample
from mrctl.laws.base import CurrentLaw, DemandLaw, Law, LawFault, Measurement
from mrctl.laws.guard import LawCall, law_fault, law_name
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS  # noqa: F401 - re-exported for callers

NAN: Final = math.nan
#: a device-time step further than this share of a tick from a whole number of ticks is a real
#: fraction (a sample taken between the host's ticks), not float rounding of k·dt
_OFF_GRID: Final = 1e-3


class Controller:
    """Holds the per-run objects and implements ``tick(k, now_ns)``."""

    def __init__(
        self,
        backend: Link,
        law: CurrentLaw,
        demand: DemandLaw | None,
        supervisor: SafetySupervisor,
        dt: float,
        record: Callable[..., None] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        driver_retries: int = 2,
        link_loss_ticks: int = 100,
        reconnect_every_ticks: int = 50,
        lead: VelocityLead | None = None,
        law_budget_s: float | None = None,
        law_overrun_ticks: int = 3,
        observer: KinematicObserver | None = None,
        cpu_clock_ns: Callable[[], int] = time.thread_time_ns,
    ) -> None:
        self.backend = backend
        self.law = law
        self.demand = demand
        self.sup = supervisor
        self.dt = dt
        self.record = record
        self.clock_ns = clock_ns
        #: the loop thread's CPU clock: the law guard's budget is CPU time, not wall time
        self.cpu_clock_ns = cpu_clock_ns
        self.driver_retries = driver_retries
        self.link_loss_ticks = link_loss_ticks
        self.reconnect_every_ticks = max(1, reconnect_every_ticks)
        self.consecutive_failures = 0
        self.reconnects = 0
        #: latency compensation (mrctl/estimation/lead.py); None when off
        self.lead = lead
        self._k_prev = -1
        #: velocity observer (sensing.velocity: observer): replaces the sample's
        #: v before the safety checks, so they judge the velocity the laws see
        self.observer = observer
        self._t_obs = NAN
        self.split: bool = backend.split
        self._host_clocked: bool = backend.host_clocked
        #: what the laws see, rewritten in place every tick; the link's
        #: extra channels are its own dict, updated in place by the link
        self.meas = Measurement(channels=getattr(backend, "channels", None))
        #: the law guard (docs/laws.md): a law whose calls take more CPU time than
        #: the budget (default one period) on this many ticks in a row is a fault
        self.law_budget_ns = round((dt if law_budget_s is None else law_budget_s) * 1e9)
        self.law_overrun_ticks = max(1, law_overrun_ticks)
        self._law_slow = 0
        self._call = LawCall()  # the guarded call of the demand and current laws
        #: the law fault that ended the run (reported after it), or None
        self.law_fault: LawFault | None = None
        self.I_next = 0.0  # exchange shape: the current to send on the next tick
        self.I_last = 0.0  # last current actually commanded (A)
        self.link_errors = 0
        self.ticks = 0
        self.stopped_reason: str | None = None
        #: the loop (its ``t_start_ns`` and ``period_ns`` give each row's lateness); None offline
        self.loop: Any = None
        self.pending: tuple[CurrentLaw, DemandLaw | None] | None = None  # (law, demand) from a reload
        #: ``mrctl arm`` (the status thread sets it): taken at the next tick boundary
        self.arm_request = False
        #: the link's output enable as last set: off while the supervisor is in FAULT
        self._enabled = True
        # live values for the status socket (plain attribute stores per tick)
        self.last_x = self.last_v = self.last_F_des = NAN
        # this tick's sample (None: none), set by _acquire
        self._sample: Sample | None = None
        self._go_on = True
        # device pacing state (acquire / tick_paced)
        self._seq0 = 0
        self._have_seq0 = False
        self._k0 = 0
        self._k_paced = -1
        self._prev_now = 0
        self._period_ns = round(dt * 1e9)

    # ------------------------------------------------------------------
    def set_rate(self, dt: float, link_loss_ticks: int, reconnect_every_ticks: int,
                 lead: VelocityLead | None) -> None:
        """Everything in the controller that counts ticks or integrates over
        ``dt`` (``link.on_infeasible: reduce_rate`` changes the period
        before the loop starts)."""
        self.dt = dt
        self._period_ns = round(dt * 1e9)
        self.link_loss_ticks = link_loss_ticks
        self.reconnect_every_ticks = max(1, reconnect_every_ticks)
        self.lead = lead

    def swap_laws(self, law: CurrentLaw, demand: DemandLaw | None) -> None:
        """Take new laws at a tick boundary (SIGHUP reload). The new inverse
        law starts from the current actually commanded, so no step appears."""
        law.reset(I0=self.I_last)
        if demand is not None:
            demand.reset()
        self.law = law
        self.demand = demand

    def _take_requests(self) -> None:
        """At the tick boundary (called when either is pending): a reload
        (SIGHUP), then ``mrctl arm``."""
        if self.pending is not None:
            law, demand = self.pending
            self.pending = None
            try:
                self.swap_laws(law, demand)
            except BaseException as exc:  # noqa: BLE001 - a plugin's reset may raise anything
                self.law = law  # the new law failed: it is the one to blame, 0 A follows
                self._law_failed("raised", law.name, self.ticks, NAN, f"in reset(): {type(exc).__name__}: {exc}")
        if self.arm_request:
            self._take_arm()

    def _take_arm(self) -> None:
        """``mrctl arm`` at the tick boundary: the device is asked to clear its
        latched status (an E-stop once closed, its watchdog's trip) and the
        supervisor waits for a good sample without the cause (SIGHUP never
        re-arms)."""
        self.arm_request = False
        try:
            self.backend.request_clear_faults()
        except Exception:  # noqa: BLE001 - a link that cannot: the supervisor still judges the samples
            pass
        self.sup.request_arm()

    def tick(self, k: int, now_ns: int) -> bool:
        """One control period; returns False to end the run (driver lost)."""
        if self.pending is not None or self.arm_request:
            self._take_requests()
        if self._host_clocked:
            self.backend.begin_tick(k)
        t0 = self.clock_ns()
        self._acquire()
        t1 = self.clock_ns()
        lp = self.loop  # lateness: wake-up minus deadline
        late_us = (now_ns - lp.t_start_ns - k * lp.period_ns) * 1e-3 if lp is not None else NAN
        return self._finish(k, now_ns, (t1 - t0) * 1e-9, late_us)

    # -- device pacing (FixedRateLoop.run_device_paced) -------------------------
    def acquire(self) -> Controller:
        """Device pacing, the blocking half of a tick: the exchange, which
        returns at the device's next tick (the SYNC flag). Never None: a
        failed exchange is a tick too, for the safety hold and link loss,
        and comes no sooner than one period after the previous tick."""
        if self.pending is not None or self.arm_request:
            self._take_requests()
        self._acquire()
        if self._sample is None and self._prev_now and self.loop is not None:
            # No reply, so no device clock: a link that fails at once (closed,
            # refused) must not run ticks back to back, or link_loss_s, held
            # in ticks, would pass in a fraction of its time. Pace by the host.
            self.loop.sleep_until(self._prev_now + self._period_ns)
        return self

    def tick_paced(self, n: int, now_ns: int, _token: object) -> bool:
        """Device pacing, the rest of the tick. ``k`` (time t = k·dt) follows
        the device's sample counter, so device ticks with no reply leave a gap
        as host-paced skipped deadlines do. The sample's age is not checked
        (the wait is the pacing); lateness is the jitter of reply arrivals."""
        sample = self._sample
        k = self._k_paced + 1 if n else 0  # k always advances (a stale seq too)
        if sample is not None:
            seq = int(sample[0])
            d = (seq - self._seq0) & 0xFFFFFFFF if self._have_seq0 else 0x80000000
            if d >= 0x80000000:  # first sample, or the device's counter went back (a restart)
                self._seq0, self._k0, self._have_seq0 = seq, k, True
            elif self._k0 + d > k:  # device ticks with no reply: leave the gap
                k = self._k0 + d
        prev, self._prev_now = self._prev_now, now_ns
        late_us = (now_ns - prev - self._period_ns) * 1e-3 if n else 0.0
        self._k_paced = k
        return self._finish(k, now_ns, 0.0, late_us)

    def _acquire(self) -> None:
        """Read (split) or exchange: ``_sample`` (None on a failure), ``_go_on``."""
        backend = self.backend
        self._sample = None
        try:
            if self.split:
                self._sample = backend.read()
            else:
                self._sample = backend.exchange(self.I_next)
                self.I_last = self.I_next
            self.consecutive_failures = 0
        except Disconnected:
            self.link_errors += 1
            self.consecutive_failures += 1
            if self.consecutive_failures % self.reconnect_every_ticks == 1:
                self._reconnect()
        except LinkError:
            self.link_errors += 1
            self.consecutive_failures += 1
        self._go_on = True
        if not self.split and self.consecutive_failures > self.link_loss_ticks:
            # the setpoint travels on the same link: the driver is unreachable
            self.sup.driver_failed()
            self.stopped_reason = (f"link lost: no successful exchange for {self.consecutive_failures} ticks "
                                   f"(the device's own watchdog applies 0 A)")
            self._go_on = False

    def _finish(self, k: int, now_ns: int, age_s: float, late_us: float) -> bool:
        """Safety check, laws, command, record: the non-blocking part of a tick."""
        c1 = self.cpu_clock_ns()  # the sample is in hand: the law's CPU budget runs from here
        sup = self.sup
        sample = self._sample
        go_on = self._go_on
        t = k * self.dt
        if sample is not None:
            seq = int(sample[0])
            t_dev = float(sample[1])
            x = float(sample[2])
            v = float(sample[3])
            F = float(sample[4])
            I_app = float(sample[6])
            if self.observer is not None:
                v = self._observe(t_dev, x, v)
            ok = sup.check(k, seq, x, v, F, int(sample[5]), I_app, age_s)
        else:
            ok = sup.check_missing(k)
            seq = -1
            t_dev = F = I_app = NAN
        if sup.in_fault == self._enabled:  # FAULT: the output disabled too (driver enable low), until it ends
            self._enabled = not self._enabled
            self.backend.enabled = self._enabled
        if ok:
            x = sup.x
            v = sup.v
            lead = self.lead
            if lead is not None:  # the state when this current will act
                v = lead.update(v, k - self._k_prev if self._k_prev >= 0 else 1)
                self._k_prev = k
            m = self.meas
            m.k = k
            m.t = t
            m.x = x
            m.v = v
            m.F = sup.F
            m.I_applied = sup.I_applied
            m.I_cmd = self.I_last
            m.status = sup.status
            I_law = self._laws(m, k, t, c1)
            F_des = self.last_F_des
        else:
            x = v = F_des = NAN
            I_law = 0.0
        I = sup.limit(I_law)
        if I != I_law and self.law_fault is None:
            try:
                self.law.applied(I)  # the law's state follows what is commanded
            except BaseException as exc:  # noqa: BLE001
                I = I_law = self._law_raised(exc, self.law, k, t)
        if self.law_fault is not None:
            go_on = False
        if not go_on:
            I = 0.0  # the run ends: the service's way out commands 0 A
        elif self.split:
            if self._write(I):
                self.I_last = I
            else:
                go_on = False
        else:
            self.I_next = I
        self.ticks += 1
        self.last_x = x
        self.last_v = v
        self.last_F_des = F_des
        rec = self.record
        if rec is not None:
            end = self.clock_ns()
            rec(t, x, v, F_des, F, I, k, NAN if seq < 0 else float(seq), t_dev, I_app,
                self.backend.true_force_N, late_us, (end - now_ns) * 1e-3, float(sup.fault_bits),
                float(self.link_errors))
        return go_on  # even the tick that ends the run is logged

    def _laws(self, m: Measurement, k: int, t: float, c1: int) -> float:
        """The demand and current laws on this tick's measurement, guarded:
        an exception (any, ``SystemExit`` too), a result that is not a real
        number, a NaN/inf, or ``law_overrun_ticks`` ticks in a row over the
        CPU budget is a law fault (docs/laws.md). Sets ``last_F_des``."""
        call = self._call
        try:  # zero cost on the good path (3.11); a law's failure is a fault, never a crash
            I_law = call.run(self.law, self.demand, m)
        except BaseException as exc:  # noqa: BLE001 - SystemExit, KeyboardInterrupt from a law too
            I_law = self._law_raised(exc, call.who, k, t)
        else:
            if self.cpu_clock_ns() - c1 > self.law_budget_ns:
                self._law_slow_tick(k, t, c1)  # the fault sets the supervisor's 0 A
            elif self._law_slow:
                self._law_slow = 0
        self.last_F_des = call.F_des
        return I_law

    # -- the law guard: the fault path only ----------------------------------------
    def _law_raised(self, exc: BaseException, who: Law | None, k: int, t: float) -> float:
        f = law_fault(exc, law_name(who), k, t)
        self._law_failed(f.kind, f.law, k, t, f.detail)
        return 0.0

    def _law_slow_tick(self, k: int, t: float, c1: int) -> None:
        """One more tick over the budget; the fault (0 A) after ``law_overrun_ticks``."""
        self._law_slow += 1
        if self._law_slow >= self.law_overrun_ticks:
            us = (self.cpu_clock_ns() - c1) * 1e-3
            self._law_failed("slow", self.law.name, k, t, f"its calls took {us:.0f} us of CPU time, over the "
                             f"budget of {self.law_budget_ns * 1e-3:.0f} us, on {self._law_slow} ticks in a row")

    def _law_failed(self, kind: str, name: str, k: int, t: float, detail: str) -> None:
        if self.law_fault is None:
            self.law_fault = LawFault(kind, name or type(self.law).__name__, k, t, detail)
            self.stopped_reason = str(self.law_fault)
            self.sup.law_failed(f"{self.law_fault.law} {kind}", k)

    def _observe(self, t_dev: float, x: float, v: float) -> float:
        """v from the observer. Its time step is the device's (t_dev), so
        skipped ticks and a reduced rate keep it on the right clock, and a
        sample stamped off the tick grid (a device clock: the reading was taken
        earlier or later than the host's tick) is predicted over its real step,
        with the gains of the nearest whole number of ticks; a
        repeated sample (stale) does not update it, a device clock that
        went back (a restart) starts it over."""
        obs = self.observer
        assert obs is not None
        d = t_dev - self._t_obs
        if d == 0.0:
            return obs.v
        if d < 0.0:
            obs.reset()
        self._t_obs = t_dev
        dt = self.dt
        n = int(d / dt + 0.5) if d > 0.0 else 1  # NaN (first sample, or no device time): one tick
        if n < 1:
            n = 1
        if d > 0.0 and abs(d - n * dt) > _OFF_GRID * dt:  # stamped between ticks: predict over the real step
            return obs.update(x, v, n, d)
        return obs.update(x, v, n)

    def _write(self, I: float) -> bool:
        for _ in range(self.driver_retries + 1):
            try:
                self.backend.write(I)
                return True
            except LinkError:
                self.link_errors += 1
        self.sup.driver_failed()
        self.stopped_reason = "current driver lost: write failed after retries"
        return False

    def _reconnect(self) -> None:
        """Reopen a vanished link (USB-serial unplugged, TCP reset), at most once
        per ``reconnect_every_ticks``; a failure just counts as another bad tick."""
        try:
            self.backend.close()
            self.backend.open()
            self.reconnects += 1
        except (LinkError, OSError):
            pass

    def safe_stop(self, budget_s: float = 0.25, min_attempts: int = 3) -> str | None:
        """Command 0 A on the way out (:func:`safe_zero`, reopening a vanished
        link); None on success, else what went wrong."""
        err = safe_zero(self.backend, budget_s, min_attempts, self._reconnect)
        if err is None:
            self.I_last = 0.0
            self.I_next = 0.0
        return err


def safe_zero(link: Link, budget_s: float = 0.25, min_attempts: int = 3,
              reconnect: Callable[[], None] | None = None) -> str | None:
    """Command 0 A, at start and on the way out, whatever the reason; returns
    what went wrong if even that failed (the caller reports it, saying
    when), None on success.

    Retried for ``budget_s`` (at least ``min_attempts`` times): a link that
    stalls at that moment must not leave the coil energised or the start
    refused (the device's own watchdog is the last resort). A vanished link
    is reopened between attempts."""
    last = ""
    n = 0
    deadline = time.monotonic() + budget_s
    while n < min_attempts or time.monotonic() < deadline:
        n += 1
        try:
            if link.split:
                link.write(0.0)
            else:
                link.exchange(0.0)
            return None
        except Disconnected as exc:
            last = str(exc)
            if reconnect is not None:
                reconnect()
            else:
                try:
                    link.close()
                    link.open()
                except (LinkError, OSError):
                    pass
        except LinkError as exc:
            last = str(exc)
        except Exception as exc:  # noqa: BLE001 - the last line of defence must not raise
            return f"{type(exc).__name__}: {exc}"
        # a link that fails at once (unplugged) is retried every ~1 ms, not
        # thousands of times: each retry reopens the port
        pause = min(1e-3, deadline - time.monotonic())
        if pause > 0:
            time.sleep(pause)
    return f"{last} ({n} attempts in {budget_s:g} s)"
