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
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Callable

from mrctl.daemon.safety import SafetySupervisor
from mrctl.estimation import KinematicObserver, VelocityLead
from mrctl.io.base import Disconnected, Link, LinkError, Sample
from mrctl.laws.base import CurrentLaw, DemandLaw, Law, LawFault, Measurement, NonFiniteOutput
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS  # noqa: F401 - re-exported for callers

if TYPE_CHECKING:
    from mrctl.daemon.loop import FixedRateLoop

NAN = math.nan


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
    ) -> None:
        self.backend = backend
        self.law = law
        self.demand = demand
        self.sup = supervisor
        self.dt = dt
        self.record = record
        self.clock_ns = clock_ns
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
        self.split = backend.split
        self._begin = backend.begin_tick if backend.host_clocked else None
        #: what the laws see, rewritten in place every tick; the link's
        #: extra channels are its own dict, updated in place by the link
        self.meas = Measurement(channels=getattr(backend, "channels", None))
        #: the law guard (docs/laws.md): a law whose calls take longer than
        #: the budget (default one period) on this many ticks in a row is a fault
        self.law_budget_ns = round((dt if law_budget_s is None else law_budget_s) * 1e9)
        self.law_overrun_ticks = max(1, law_overrun_ticks)
        self._law_slow = 0
        #: the law fault that ended the run (reported after it), or None
        self.law_fault: LawFault | None = None
        self.I_next = 0.0  # exchange shape: the current to send on the next tick
        self.I_last = 0.0  # last current actually commanded (A)
        self.link_errors = 0
        self.ticks = 0
        self.stopped_reason: str | None = None
        self.loop: FixedRateLoop | None = None  # for the per-row lateness column
        self.pending: tuple[CurrentLaw, DemandLaw | None] | None = None  # (law, demand) from a reload
        # live values for the status socket (plain attribute stores per tick)
        self.last_x = self.last_v = self.last_F_des = NAN
        # device pacing state (acquire / tick_paced)
        self._acq: tuple[Sample | None, bool] = (None, True)
        self._seq0: int | None = None
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

    def _take_reload(self) -> None:
        """A reload (SIGHUP) is taken at the tick boundary."""
        if self.pending is not None:
            law, demand = self.pending
            self.pending = None
            try:
                self.swap_laws(law, demand)
            except Exception as exc:  # noqa: BLE001 - a plugin's reset may raise
                self.law = law  # the new law failed: it is the one to blame, 0 A follows
                self._law_failed("raised", law.name, self.ticks, NAN, f"in reset(): {type(exc).__name__}: {exc}")

    def tick(self, k: int, now_ns: int) -> bool:
        """One control period; returns False to end the run (driver lost)."""
        self._take_reload()
        if self._begin is not None:
            self._begin(k)
        t0 = self.clock_ns()
        sample, go_on = self._acquire()
        t1 = self.clock_ns()
        lp = self.loop  # lateness: wake-up minus deadline
        late_us = (now_ns - lp.t_start_ns - k * lp.period_ns) * 1e-3 if lp is not None else NAN
        return self._finish(k, now_ns, sample, (t1 - t0) * 1e-9, go_on, late_us, t1)

    # -- device pacing (FixedRateLoop.run_device_paced) -------------------------
    def acquire(self) -> Controller:
        """Device pacing, the blocking half of a tick: the exchange, which
        returns at the device's next tick (the SYNC flag). Never None: a
        failed exchange is a tick too, for the safety hold and link loss,
        and comes no sooner than one period after the previous tick."""
        self._take_reload()
        self._acq = self._acquire()
        if self._acq[0] is None and self._prev_now and self.loop is not None:
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
        sample, go_on = self._acq
        k = self._k_paced + 1 if n else 0  # k always advances (a stale seq too)
        if sample is not None:
            d = (sample.seq - self._seq0) & 0xFFFFFFFF if self._seq0 is not None else 0x80000000
            if d >= 0x80000000:  # first sample, or the device's counter went back (a restart)
                self._seq0, self._k0 = sample.seq, k
            elif self._k0 + d > k:  # device ticks with no reply: leave the gap
                k = self._k0 + d
        prev, self._prev_now = self._prev_now, now_ns
        late_us = (now_ns - prev - self._period_ns) * 1e-3 if n else 0.0
        self._k_paced = k
        return self._finish(k, now_ns, sample, 0.0, go_on, late_us, self.clock_ns())

    def _acquire(self) -> tuple[Sample | None, bool]:
        """Read (split) or exchange; (sample or None, go on)."""
        backend = self.backend
        sample = None
        try:
            if self.split:
                sample = backend.read()
            else:
                sample = backend.exchange(self.I_next)
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
        go_on = True
        if not self.split and self.consecutive_failures > self.link_loss_ticks:
            # the setpoint travels on the same link: the driver is unreachable
            self.sup.driver_failed()
            self.stopped_reason = (f"link lost: no successful exchange for {self.consecutive_failures} ticks "
                                   f"(the device's own watchdog applies 0 A)")
            go_on = False
        return sample, go_on

    def _finish(self, k: int, now_ns: int, sample: Sample | None, age_s: float, go_on: bool, late_us: float,
                t1: int) -> bool:
        """Safety check, laws, command, record: the non-blocking part of a tick.
        ``t1`` is the clock when the sample was in hand (the law's budget runs from it)."""
        sup = self.sup
        if self.observer is not None and sample is not None:
            sample = self._observe(sample)
        s = sup.check_sample(sample, age_s)
        t = k * self.dt
        if s is not None:
            x = s.x_m
            v = s.v_mps
            lead = self.lead
            if lead is not None:  # the state when this current will act
                v = lead.update(v, k - self._k_prev if self._k_prev >= 0 else 1)
                self._k_prev = k
            m = self.meas
            m.k = k
            m.t = t
            m.x = x
            m.v = v
            m.F = s.F_N
            m.I_applied = s.current_A
            m.I_cmd = self.I_last
            m.status = s.status
            I_law = self._laws(m, k, t, t1)
            F_des = self.last_F_des
        else:
            x = v = F_des = NAN
            I_law = 0.0
        I = sup.limit(I_law)
        if I != I_law and self.law_fault is None:
            try:
                self.law.applied(I)  # the law's state follows what is commanded
            except Exception as exc:  # noqa: BLE001
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
        self.last_x, self.last_v, self.last_F_des = x, v, F_des
        rec = self.record
        if rec is not None:
            if sample is not None:
                seq, t_dev, F, I_app = sample.seq, sample.t_dev_s, sample.F_N, sample.current_A
            else:
                seq = t_dev = F = I_app = NAN
            end = self.clock_ns()
            rec(t, x, v, F_des, F, I, k, seq, t_dev, I_app, self.backend.true_force_N, late_us,
                (end - now_ns) * 1e-3, sup.fault_bits, self.link_errors)
        return go_on  # even the tick that ends the run is logged

    def _laws(self, m: Measurement, k: int, t: float, t1: int) -> float:
        """The demand and current laws on this tick's measurement, guarded:
        an exception, a NaN/inf, or ``law_overrun_ticks`` ticks in a row over
        the budget is a law fault (docs/laws.md). Sets ``last_F_des``."""
        F_des = NAN
        who: Law | None = self.demand
        try:  # zero cost on the good path (3.11); a law's failure is a fault, never a crash
            if who is not None:
                F_des = who.force(m)  # type: ignore[union-attr]
                if F_des - F_des != 0.0:  # NaN or inf
                    raise NonFiniteOutput(f"F_des = {F_des!r}")
            who = law = self.law
            I_law = law.current(m, F_des)
            if I_law - I_law != 0.0:
                raise NonFiniteOutput(f"I = {I_law!r}")
        except Exception as exc:  # noqa: BLE001
            I_law = self._law_raised(exc, who, k, t)
        else:
            if self.clock_ns() - t1 > self.law_budget_ns:
                self._law_slow_tick(k, t, t1)  # the fault sets the supervisor's 0 A
            elif self._law_slow:
                self._law_slow = 0
        self.last_F_des = F_des
        return I_law

    # -- the law guard: the fault path only ----------------------------------------
    def _law_raised(self, exc: Exception, who: Law | None, k: int, t: float) -> float:
        name = (who.name or type(who).__name__) if who is not None else ""
        if isinstance(exc, NonFiniteOutput):
            self._law_failed("non-finite", name, k, t, str(exc))
        else:
            self._law_failed("raised", name, k, t, f"{type(exc).__name__}: {exc}")
        return 0.0

    def _law_slow_tick(self, k: int, t: float, t1: int) -> None:
        """One more tick over the budget; the fault (0 A) after ``law_overrun_ticks``."""
        self._law_slow += 1
        if self._law_slow >= self.law_overrun_ticks:
            us = (self.clock_ns() - t1) * 1e-3
            self._law_failed("slow", self.law.name, k, t, f"its calls took {us:.0f} us, over the budget of "
                             f"{self.law_budget_ns * 1e-3:.0f} us, on {self._law_slow} ticks in a row")

    def _law_failed(self, kind: str, name: str, k: int, t: float, detail: str) -> None:
        if self.law_fault is None:
            self.law_fault = LawFault(kind, name or type(self.law).__name__, k, t, detail)
            self.stopped_reason = str(self.law_fault)
            self.sup.law_failed(f"{self.law_fault.law} {kind}")

    def _observe(self, sample: Sample) -> Sample:
        """The sample with v from the observer. Its time step is the device's
        (t_dev), so skipped ticks and a reduced rate keep it on the right
        clock; a repeated sample (stale) does not update it, a device clock
        that went back (a restart) starts it over."""
        obs = self.observer
        assert obs is not None
        seq, t_dev, x, v, F, status, I_app = sample
        d = t_dev - self._t_obs
        if d == 0.0:
            v = obs.v
        else:
            if d < 0.0:
                obs.reset()
            self._t_obs = t_dev
            n = int(d / self.dt + 0.5) if d > 0.0 else 1  # NaN (first sample, or no device time): one tick
            v = obs.update(x, v, n if n > 0 else 1)
        # the constructor, not _replace(), which builds a dict and a map per call: one more
        # small object per tick, as the link's own Sample
        return Sample(seq, t_dev, x, v, F, status, I_app)

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
