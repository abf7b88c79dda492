"""``mrctl run``: start-up, the run, and one way out that commands 0 A.

What runs where:

- the **main thread** runs the fixed-rate loop (:class:`mrctl.daemon.loop.FixedRateLoop`)
  with :class:`mrctl.core.controller.Controller` as its tick. Signal
  handlers run here too, so they only set flags (``loop.stop()``, a reload
  event);
- the **monitor thread** (:mod:`mrctl.daemon.monitor`): live line, systemd
  status and watchdog, reloads (validated off the loop, handed over at a
  tick boundary);
- the **status thread** (:mod:`mrctl.daemon.status`) answers ``mrctl status``;
- the **recorder's writer thread** (:mod:`mrctl.daemon.recorder`).

Start-up, in this order, once: check ``--duration``, the config and
``--out`` (exit 2 before anything is touched); take the device's lock (a
second daemon is refused here, exit 3, before it sends anything); create
the run log; open the link; command 0 A (the first thing a start does on
the wire, so a restart after a crash never resumes the old current); check
that the link sustains the rate, and with ``link.on_infeasible:
reduce_rate`` rebuild the experiment at the rate that fits; set up device
pacing; only then build the safety supervisor and the controller, at the
final rate. Every resource is entered on one ``ExitStack`` whose first
callback on the way out commands 0 A, so every exit (end of experiment,
SIGINT, SIGTERM, driver lost, refusal, exception) passes there first; the
device's lock is released last.

Exit codes are carried by the error that ends a start-up
(:mod:`mrctl.errors`): 2 bad input, 3 link failure or device owned; a run
ends 0, 3 when the driver was lost, 4 when the log is incomplete
(:mod:`mrctl.daemon.logcheck`), 5 when it completed but broke an
``acceptance`` bound (:meth:`Service.acceptance`), 1 on an internal error.
"""

from __future__ import annotations

import contextlib
import math
import os
import platform
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, TextIO

from mrctl import __version__
from mrctl.build import tick_build
from mrctl.config import ConfigError, Node, load_experiment
from mrctl.core.controller import Controller, safe_zero
from mrctl.daemon import ownership
from mrctl.daemon.arm import ArmServer
from mrctl.daemon import signals
from mrctl.daemon.faultwatch import FaultWatch
from mrctl.daemon.interlocks import read_until_clean, start_refusal
from mrctl.daemon.feasibility import assess, check_device_pacing, probe, wire_time_s, wire_words
from mrctl.config.acceptance import bounds as acceptance_bounds
from mrctl.config.saved import saved_config
from mrctl.daemon.logcheck import LogWatch, close_log, verdict_exit
from mrctl.daemon.loop import FixedRateLoop
from mrctl.daemon.monitor import Monitor, live_line
from mrctl.daemon.notify import Notifier
from mrctl.daemon.reload import validate_in_child
from mrctl.daemon.observe import Observe, stream_settings
from mrctl.daemon.rt import RtSettings, apply_rt, restore
from mrctl.core.safety import SafetyConfig, SafetySupervisor
from mrctl.core.safety_config import LATCH_STATUS
from mrctl.daemon.instances import server_socket
from mrctl.daemon.status import StatusServer
from mrctl.daemon.timing import format_summary as format_timing
from mrctl.errors import BadInput, ExitCode, LinkFailure, LogIncomplete, MrctlError
from mrctl.experiment import Experiment, build, check_channels, link_channels
from mrctl.io.base import Link, LinkError, Status
from mrctl.runlog import files
from mrctl.runlog.acceptance import format_verdict, judge, row_figures, tracking_judged
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS, sidecar_header
from mrctl.runlog.metrics import format_summary, load_cell_offset
from mrctl.util.journal import CRIT, ERR, NOTICE, WARNING, Journal
from mrctl.util.files import Fence
from mrctl.util.options import check_duration

# kept as names: tests and hil_sim compare against them
EXIT_OK, EXIT_FAILURE, EXIT_CONFIG, EXIT_LINK, EXIT_LOG = (
    ExitCode.OK, ExitCode.FAILURE, ExitCode.BAD_INPUT, ExitCode.LINK, ExitCode.LOG)


@dataclass
class RunOptions:
    config_path: str
    out: str | None = None
    duration_s: float | None = None
    status_socket: str | None = None
    live: bool = True  # progress / live line on stderr (foreground)
    force: bool = False  # replace an existing run log (--force)
    mkdir: bool = False  # create a missing directory of the run log (--mkdir)
    instance: str | None = None  # --instance NAME: its status socket and the name mrctl ls shows
    clock_ns: Callable[[], int] = time.monotonic_ns  # injectable for deterministic tests
    sleep: Callable[[float], object] = time.sleep
    stream: TextIO = field(default_factory=lambda: sys.stdout)
    err: TextIO = field(default_factory=lambda: sys.stderr)
    # live observers (docs/observe.md): over the config's stream section
    stream_url: str | None = None
    stream_every: int | None = None
    stream_columns: tuple[str, ...] | None = None
    log_priorities: bool | None = None  # <N> prefixes on stderr; None: when stderr is the journal
    allow_outside_paths: bool = False  # data files outside the config's directory (--allow-outside-paths)


class Service:
    """One run of ``mrctl run``: owns every thread and resource of it."""

    def __init__(self, opts: RunOptions) -> None:
        self.opts = opts
        self.notifier = Notifier()
        self.exp: Experiment | None = None
        self.loaded: Node | None = None  # the config as the file says it (before any rate reduction)
        self.link: Link | None = None
        self.loop: FixedRateLoop | None = None
        self.ctl: Controller | None = None
        self.sup: SafetySupervisor | None = None
        self.rec: Any = None
        self._ran = False  #: the loop was entered: what follows is a run, with its log and verdict
        self.obs: Observe | None = None
        self.faults: FaultWatch | None = None
        self._stream: tuple[str, int, tuple[str, ...] | None] | None = None
        self.monitor: Monitor | None = None
        self.rt_results: list[Any] = []
        self.messages: list[str] = []
        self.started_mono = time.monotonic()
        self.reloads_ok = 0
        self.reloads_rejected = 0
        self.last_reload_error: str | None = None
        self.exit_current_A = math.nan  # what the way out commanded (0.0 unless it failed)
        self._zero_error: str | None = "not attempted"
        self._total_ticks: int | None = None
        self.requested_s: float | None = None  # --duration, else the config's; None: until stopped
        self.interrupted: str | None = None  # SIGINT/SIGTERM that stopped the loop
        self._at_stop: tuple[int, int] | None = None  # (ticks, skipped deadlines) when it came
        self.verdict: dict[str, Any] | None = None  # the run's acceptance verdict, once it ended
        self._log_fh: Any = None  # the run log, created before the link opens, until the recorder takes it
        self.journal = Journal(opts.err, opts.log_priorities)
        self.log_watch = LogWatch(bool(opts.out), self.warn, self.notifier.send)

    # -- output helpers ---------------------------------------------------
    def say(self, msg: str) -> None:
        print(msg, file=self.opts.stream, flush=True)

    def warn(self, msg: str, priority: int = WARNING) -> None:
        """Every warning, error and fault goes out here, with its journal priority."""
        self.messages.append(msg)
        self.journal.log(priority, msg)

    # -- the run ---------------------------------------------------------------
    def run(self) -> int:
        """The whole run; returns the exit code (README). A SIGINT/SIGTERM
        during start-up (:mod:`mrctl.daemon.signals`) leaves through the same
        stack (0 A if the link is open), removes the run log it created, and
        exits 0."""
        code: int = EXIT_OK
        old_handlers = signals.install_startup()
        stopped: signals.StopSignal | None = None
        try:
            try:
                with contextlib.ExitStack() as stack:
                    try:
                        code = self._run(stack)
                    except MrctlError as exc:  # a refusal at start-up: the error says how to exit
                        self.warn(str(exc), ERR)
                        code = exc.exit_code
                    except signals.StopSignal as exc:
                        stopped = exc
                    except KeyboardInterrupt:
                        pass  # a second Ctrl-C during start-up: still leave safely (the stack)
                    except Exception as exc:  # noqa: BLE001 - report, then leave safely (the stack)
                        self.warn(f"internal error: {type(exc).__name__}: {exc}", ERR)
                        code = EXIT_FAILURE
            except signals.StopSignal as exc:  # while the stack unwound a refusal
                stopped = stopped or exc
            finally:
                signals.install_late()
                if self.link is not None and self._zero_error is not None:
                    self.warn(f"could not command 0 A on exit: {self._zero_error}", CRIT)
                    code = code or EXIT_LINK
            if stopped is None and self.interrupted is not None and self.ctl is not None and self.ctl.ticks == 0:
                # SIGINT/SIGTERM after the handlers moved to the loop but before its first tick
                stopped = signals.StopSignal(signal.Signals[self.interrupted].value)
            if stopped is not None:
                return self._stopped_at_startup(stopped, code)
            if not self._ran:  # refused before the first tick (after the recorder was built, too)
                self._drop_run_log()
                return code
            return self._finish(code)
        finally:
            signals.restore(old_handlers)

    def _stopped_at_startup(self, stop: signals.StopSignal, code: int) -> int:
        """A stop before the first tick: nothing ran, so no run log is left
        (the recorder's CSV and "incomplete" sidecar are removed); exit 0
        unless 0 A could not be commanded."""
        self._drop_run_log()
        self.warn(f"stopped by {stop.name} during start-up: nothing ran"
                  + ("; 0 A commanded" if self.link is not None and code == EXIT_OK else ""), NOTICE)
        return code

    def _drop_run_log(self) -> None:
        """Nothing ran: the recorder's CSV and "incomplete" sidecar, if it
        was built, are removed (a refusal leaves no run log to mistake for one)."""
        if self.obs is not None:  # its stream and taps end with the run that did not start
            with contextlib.suppress(Exception):
                self.obs.close(self.rec)
        if self.rec is not None:
            with contextlib.suppress(Exception):
                self.rec.close(write_sidecar=False, timeout=5.0)
            for q in (self.opts.out, files.sidecar_path(self.opts.out or "x")):
                with contextlib.suppress(OSError):
                    if self.opts.out:
                        os.unlink(q)

    def _run(self, stack: contextlib.ExitStack) -> int:
        o = self.opts
        # everything the user gave is checked before the device is touched
        override = check_duration(o.duration_s, "--duration")
        exp = self.exp = build(load_experiment(o.config_path, allow_outside=o.allow_outside_paths))
        self.loaded = exp.config
        duration = self.requested_s = override if override is not None else exp.config.duration_s
        if o.out:
            files.check_log_path(o.out, o.force, o.mkdir)
        self._stream = stream_settings(exp.config, o.stream_url, o.stream_every, o.stream_columns)
        try:
            link = exp.make_link()
        except ValueError as exc:  # a combination the schema cannot see (e.g. a register map for RTU)
            raise BadInput(f"backend: {exc}") from None
        self.say(f"mrctl {__version__}: {exp.name}, law {exp.config.inverse.law}, {exp.config.rate_hz:g} Hz, "
                 f"{'%.3f s' % duration if duration else 'until stopped'}; backend {link.describe()}")
        if exp.config.get("calibration"):
            from mrctl.config.calibration import describe_calibration

            self.say(describe_calibration(exp.config.calibration, Path(o.config_path).parent,
                                          Fence.around(Path(o.config_path).parent, o.allow_outside_paths)))
        with signals.deferred():  # a stop waits until the lock's release is registered
            self._own_device(stack, link)  # before a byte goes out: a second daemon is refused here
        if o.out:
            with signals.deferred():  # the file and its removal, as one step
                self._log_fh = files.create_log(o.out, o.force, o.mkdir)
                stack.callback(self._drop_unused_log)
        with signals.deferred():  # an open link always has its 0 A registered
            try:
                link.open()
            except (LinkError, OSError) as exc:
                raise LinkFailure(f"cannot open backend: {exc}") from None
            self.link = link
            stack.callback(link.close)
            stack.callback(self._zero_on_exit)  # runs before close, also after a refusal below
        if getattr(link, "setup_report", None):  # a device preset: what open chose and read back
            self.say(f"opened: {link.describe()}")
        link.request_clear_faults()  # a new run starts clean: what is still tripped is refused below
        err = safe_zero(link)
        if err:
            raise LinkFailure(f"could not command 0 A at start: {err}")
        self._zero_error = None
        checked = not link.split or ownership.device_key_of(link) is not None  # every link but the in-process bench
        if checked:
            exp = self.exp = self._check_link(exp, link)
            self._check_interlocks(exp, link)
        if exp.config.loop.pacing == "device":
            self._set_device_pacing(exp, link)
        link_channels(exp, link)  # the laws' extra channels: asked for, checked (exit 2)
        with signals.deferred():  # recorder, threads and handlers: all or none registered
            self._build(exp, link, duration)
            self._enter_run(stack)
        ctl, loop = self.ctl, self.loop
        assert ctl is not None and loop is not None
        stack.callback(self._zero_on_exit)  # the first thing on the way out of the loop
        if checked:
            # the device was at 0 A through start-up; its watchdog may have expired meanwhile (no
            # setpoint since the probe): that is cleared, an E-stop latched meanwhile refuses the start
            self._check_interlocks(exp, link, since_check=True)
        else:
            link.request_clear_faults()  # the in-process bench: no E-stop between check and tick
        self.notifier.send("READY=1", f"STATUS=running {exp.name}")
        self._ran = True
        if exp.config.loop.pacing == "device":
            loop.run_device_paced(ctl.acquire, ctl.tick_paced, duration_s=duration)
        else:
            loop.run(ctl.tick, duration_s=duration)
        if ctl.stopped_reason:
            self.warn(ctl.stopped_reason, ERR)
            return EXIT_FAILURE if ctl.law_fault is not None else EXIT_LINK  # a law is software: exit 1
        return EXIT_OK

    def _zero_on_exit(self) -> None:
        """0 A on the way out, whatever happened. Idempotent: once it worked,
        later calls (the stack holds it twice) do nothing."""
        if self._zero_error is None and self.exit_current_A == 0.0:
            return
        link, ctl = self.link, self.ctl
        if link is None:
            return
        err = ctl.safe_stop() if ctl is not None else safe_zero(link)
        self._zero_error = err
        self.exit_current_A = 0.0 if err is None else math.nan

    def _own_device(self, stack: contextlib.ExitStack, link: Link) -> None:
        """The device's lock, held until the very end: released after the 0 A
        on the way out and the link's close (the stack unwinds in reverse)."""
        lock = ownership.own(link, f"mrctl run {Path(self.opts.config_path).resolve()}", self.warn)
        if lock is not None:
            stack.callback(lock.release)

    def _drop_unused_log(self) -> None:
        """A start refused before the recorder took the run log: remove the
        empty file this run created (never anything else)."""
        fh, self._log_fh = self._log_fh, None
        if fh is not None and self.opts.out:
            fh.close()
            files.drop_log(self.opts.out)

    # -- start-up steps ----------------------------------------------------------
    def _check_link(self, exp: Experiment, link: Link) -> Experiment:
        """Feasibility of the configured rate on this link (docs/design.md):
        the experiment to run, maybe at a reduced rate; LinkFailure to refuse."""
        cfg = exp.config
        timeouts: list[int] = []
        rtts, errors = probe(link, cfg.link.probe_exchanges, clock=lambda: self.opts.clock_ns() * 1e-9,
                             timeouts=timeouts)
        _what, advice = wire_words(cfg.backend)
        f = assess(cfg.rate_hz, wire_time_s(cfg.backend), rtts, errors, what=cfg.backend.type,
                   timeouts=timeouts[0], advice=advice)
        if f.ok:
            self.say(f.message)
            return exp
        if cfg.link.on_infeasible == "reduce_rate" and f.suggested_rate_hz:
            self.warn(f"{f.message} Running at {f.suggested_rate_hz:g} Hz instead.")
            return exp.at_rate(f.suggested_rate_hz)
        if f.suggested_rate_hz and "reduce_rate" not in f.message:
            raise LinkFailure(f"refusing to start: {f.message}; or set link.on_infeasible: reduce_rate")
        raise LinkFailure(f"refusing to start: {f.message}")

    def _check_interlocks(self, exp: Experiment, link: Link, since_check: bool = False) -> None:
        """A real link's E-stop and device watchdog before the first tick: an
        open E-stop refuses the start (exit 3: the run would begin latched);
        a bench without a software E-stop input is said once.

        Run twice: after the probe, where a latch left by an earlier run is
        cleared, and again just before the first tick (``since_check``),
        where what latched during the start-up's own pauses is cleared (a
        watchdog that expired, a driver fault or a receive error that came and
        went) but not an E-stop: one pressed and released in between is still
        latched in the device and refuses the start, where a blind
        CLEAR_FAULTS would have erased the operator's stop."""
        estop = exp.config.safety.estop
        where = f" (safety.estop.input: {estop.input})" if estop.input is not None else ""
        if estop.input is None and not since_check:
            self.warn("safety.estop: no E-stop input configured: only the hard-wired E-stop protects this bench "
                      "(docs/hardware.md)", NOTICE)
        # what is cleared until the answer is clean: every latch after the probe; past the first
        # check all but the E-stop
        mask = _CLEARED_BEFORE_FIRST_TICK if since_check else LATCH_STATUS
        found = read_until_clean(link, mask, keep_mask=int(Status.ESTOP) if since_check else 0)
        if since_check and found.status is not None and found.status & int(Status.ESTOP):
            raise LinkFailure(f"refusing to start: the E-stop was pressed during start-up{where}; the device "
                              "reports it: reset the E-stop and start again")
        # past the first check a driver fault still there at the deadline is the supervisor's: only a
        # watchdog trip that does not clear refuses (the first check's own mask has no driver fault)
        why = start_refusal(found, int(Status.WATCHDOG_TRIPPED), "the first tick", where)
        if why:
            raise LinkFailure(why)

    def _set_device_pacing(self, exp: Experiment, link: Link) -> None:
        try:
            link.set_device_paced(True, exp.dt, exp.config.loop.spin_margin_s)
        except ValueError as exc:  # e.g. a Modbus map without an enable register
            raise ConfigError([f"loop.pacing: {exc}"]) from None
        why = check_device_pacing(link, exp.dt)
        if why:
            raise LinkFailure(f"refusing to start: {why}")
        self.say(f"device pacing: the loop runs on the device's clock ({exp.config.rate_hz:g} Hz)")

    def _build(self, exp: Experiment, link: Link, duration: float | None) -> None:
        """The supervisor, controller and loop, once, at the final rate."""
        cfg = exp.config
        self._total_ticks = int(round(duration * cfg.rate_hz)) if duration else None
        self.sup = SafetySupervisor(SafetyConfig.from_config(cfg.safety, exp.dt, real_link=cfg.backend.type != "sim"))
        ctl = self.ctl = Controller(
            link, exp.law, exp.demand, self.sup, exp.dt, clock_ns=self.opts.clock_ns,
            driver_retries=cfg.safety.driver_retries,
            link_loss_ticks=max(1, round(cfg.safety.link_loss_s * cfg.rate_hz)),
            reconnect_every_ticks=max(1, round(cfg.safety.reconnect_interval_s * cfg.rate_hz)),
            lead=exp.make_lead(link), observer=exp.make_observer(), law_budget_s=cfg.safety.law_budget_s,
            law_overrun_ticks=cfg.safety.law_overrun_ticks)
        ctl.I_last = ctl.I_next = 0.0  # the start-up 0 A went out
        exp.law.reset()
        if exp.demand is not None:
            exp.demand.reset()
        self.loop = ctl.loop = FixedRateLoop(cfg.rate_hz, wait=cfg.loop.wait, spin_margin_s=cfg.loop.spin_margin_s,
                                             clock=self.opts.clock_ns, sleep=self.opts.sleep)

    def _enter_run(self, stack: contextlib.ExitStack) -> None:
        """Recorder, status socket, monitor, signals, RT: each undone by the stack."""
        o, exp, ctl, loop = self.opts, self.exp, self.ctl, self.loop
        assert exp is not None and ctl is not None and loop is not None
        cfg = exp.config
        if o.out:
            from mrctl.daemon.recorder import Recorder

            # host pacing: the loop formats the log in its idle time; device
            # pacing has no idle time between compute and send, but sleeps
            # in the exchange, when the writer thread can format
            host_paced = cfg.loop.pacing == "host"
            fh, self._log_fh = self._log_fh, None
            try:
                self.rec = Recorder(o.out, RUN_COLUMNS, {"backend": self.link.describe() if self.link else None},
                                    capacity_ticks=cfg.record.buffer_ticks,
                                    flush_interval_s=cfg.record.flush_interval_s, rate_hz=cfg.rate_hz,
                                    fmt=RUN_FORMATS, defer_format=host_paced, opener=lambda _p: fh,
                                    header=sidecar_header("run", Path(o.out).name, self._provenance()))
            except OSError as exc:
                files.drop_log(o.out)
                raise LogIncomplete(f"{o.out}: cannot write the run log: {exc.strerror or exc}") from None
            ctl.record = self.rec.record
            if host_paced:
                loop.background = self.rec.format_pending
        obs = self.obs = Observe.for_run(cfg, ctl, loop, self.rec, self._stream, o.clock_ns, exp.name, self.warn)
        where, notice = server_socket(o.status_socket or cfg.service.status_socket, o.instance)
        arm = ArmServer(ctl, self.sup, self.warn)
        status = StatusServer(where, self.snapshot, lambda c, r: arm.handle(c, r) or obs.handle_request(c, r))
        try:
            status.start()
            if notice:
                self.warn(notice, NOTICE)
            stack.callback(status.close)
        except OSError as exc:
            self.warn(f"status socket unavailable ({exc}); running without it")
        faults = self.faults = FaultWatch(self.sup, self.warn, lambda: ctl.ticks)
        mon = self.monitor = Monitor(self.notifier, lambda: ctl.ticks, self._live_line, self._reload, o.err, o.live,
                                     watch=lambda: (self.log_watch.check(self.rec), faults.check()))
        mon.start()
        stack.callback(mon.stop)
        for sig in signals.STOP_SIGNALS:
            signal.signal(sig, lambda s, f: self._stop_by(s, loop))
        signal.signal(signal.SIGHUP, lambda s, f: mon.reload_event.set())
        if signals.take_hup():  # a SIGHUP during start-up, maybe after the config was read
            mon.reload_event.set()
        stack.callback(signals.install_late)  # the way out is not cut short by a second signal
        old_switch = sys.getswitchinterval()
        stack.callback(sys.setswitchinterval, old_switch)
        stack.callback(restore)
        stack.callback(self.notifier.send, "STOPPING=1")
        # threads above exist before RT setup, so they do not inherit SCHED_FIFO/affinity
        self.rt_results = apply_rt(RtSettings.from_config(cfg.rt))
        for r in self.rt_results:
            self.say(str(r))  # "rt gc_freeze=True: applied (...)": the prefix is its own
        sys.setswitchinterval(2e-4)  # a writer thread must not hold the GIL for 5 ms

    def _provenance(self) -> dict[str, Any]:
        """What ran, with what: the sidecar's provenance (docs/runlog.md)."""
        exp, link = self.exp, self.link
        assert exp is not None and link is not None
        return {
            "mrctl_version": __version__, "build": tick_build(), "python": platform.python_version(),
            "host": platform.node(), "config_file": str(Path(self.opts.config_path).resolve()), "config": saved_config(exp.config),
            "parameters": exp.params.as_dict(), "backend": link.describe(), "law": exp.config.inverse.law,
            "I_max_A": exp.I_max, "rate_hz": exp.config.rate_hz, "settle_s": exp.excitation.settle_s,
            # the in-process bench's load cell reads the previous tick's force; hardware: taken as simultaneous
            "load_cell_delay_ticks": 1 if exp.config.backend.type == "sim" else 0,
        }

    def _stop_by(self, signum: int, loop: FixedRateLoop) -> None:
        """SIGINT/SIGTERM in the loop: stop after this tick, and remember which
        and where (the verdict judges the ticks before it: a deadline missed
        while the process was being stopped is not the run's)."""
        if self.interrupted is None:
            self.interrupted = signal.Signals(signum).name
            self._at_stop = (loop.stats.ticks, loop.stats.skipped_deadlines)
        loop.stop()

    def _duration(self) -> dict[str, Any]:
        """The sidecar's duration: asked (``--duration``, else the config's;
        None: until stopped), run (ticks and skipped deadlines on the loop's
        clock) and the signal that stopped it (None: it ran its course)."""
        assert self.loop is not None
        st = self.loop.stats
        return {"requested_duration_s": self.requested_s,
                "actual_duration_s": (st.ticks + st.skipped_deadlines) / self.loop.rate_hz if self.loop.rate_hz
                else None,
                "interrupted": self.interrupted}

    # -- acceptance (docs/config.md: acceptance) ------------------------------------
    def acceptance(self, cols: dict[str, Any] | None = None, track: dict[str, float] | None = None) -> dict[str, Any]:
        """The run judged against its ``acceptance`` bounds, from the counters
        the loop and the supervisor keep (ticks in fault, skipped deadlines,
        the longest gap) and, once the run has ended, from its rows (the
        longest forced-0 A stretch) and tracking figures. Without rows the
        stretch is estimated from the longest run of bad samples."""
        assert self.exp is not None and self.loop is not None and self.ctl is not None and self.sup is not None
        dt = 1.0 / self.loop.rate_hz
        c = self.sup.counters()
        st = self.loop.stats
        ticks, skipped = st.ticks, st.skipped_deadlines
        if self._at_stop is not None:  # stopped by the user: judged up to the signal
            skipped = min(skipped, self._at_stop[1])
        figs: dict[str, Any] = {
            "ticks": ticks,
            "fault_share": c.ticks_in_fault / ticks if ticks else 0.0,
            "skipped_share": skipped / (ticks + skipped) if ticks + skipped else 0.0,
            "longest_gap_s": st.max_gap_ns / 1e9,
        }
        lc: dict[str, float] = {}  # the load cell's zero error, from the rows
        if cols is not None and len(cols.get("t", ())):
            figs["longest_zero_stretch_s"] = row_figures(cols, dt)["longest_zero_stretch_s"]
            lc = load_cell_offset(cols, dt, 1 if self.exp.config.backend.type == "sim" else 0,
                                  float(self.exp.params.F_offset))
        else:
            cfg = self.sup.config
            bad = max(0, c.longest_bad_run - cfg.hold_ticks)
            figs["longest_zero_stretch_s"] = (bad + (cfg.resume_good_ticks if c.faults_entered else 0)) * dt
            figs["zero_stretch_estimated"] = True
        figs["latched_s"] = c.ticks_latched * dt
        figs.update(tracking_judged({**(track or {}), **lc}, self.exp.excitation.settle_s, dt))
        v = judge({k: v for k, v in figs.items() if k not in ("ticks", "zero_stretch_estimated")},
                  acceptance_bounds(self.exp.config), dt)
        v["figures"]["ticks"] = ticks
        if figs.get("zero_stretch_estimated"):
            v["figures"]["zero_stretch_estimated"] = True
        return v

    def _final_verdict(self, cols: dict[str, Any] | None, track: dict[str, float] | None) -> dict[str, Any]:
        """The verdict at the end of the run, said once: stdout if ok, stderr
        (and the sidecar's messages) if degraded."""
        v = self.verdict = self.acceptance(cols, track)
        if v["verdict"] == "degraded":
            self.warn(format_verdict(v) + " (exit 5 unless the run failed otherwise)", ERR)
        else:
            self.say(format_verdict(v))
        return v

    # -- status, live line, reload ------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        loop, ctl, sup = self.loop, self.ctl, self.sup
        d: dict[str, Any] = {
            "mrctl_version": __version__, "pid": os.getpid(),
            "experiment": self.exp.name if self.exp else None,
            "instance": self.opts.instance, "config_file": str(Path(self.opts.config_path).resolve()),
            "uptime_s": round(time.monotonic() - self.started_mono, 3),
            "rate_hz": loop.rate_hz if loop else None,
            "ticks": ctl.ticks if ctl else 0,
            "reloads": {"ok": self.reloads_ok, "rejected": self.reloads_rejected,
                        "last_error": self.last_reload_error},
        }
        if ctl is not None:
            d.update(current_A=ctl.I_last, x_m=ctl.last_x, v_mps=ctl.last_v, F_des_N=ctl.last_F_des,
                     link_errors=ctl.link_errors, law=ctl.law.name)
        if sup is not None:
            d.update(safety_state=sup.shown_state.name, latch_cause=sup.latch_cause or None,
                     fault=sup.fault.name if sup.fault else "NONE",
                     fault_reason=sup.reason, safety_counters=sup.counters().as_dict())
        if loop is not None:
            d["timing"] = loop.stats.summary(last_n=5000)
        if self.rec is not None:
            self.log_watch.check(self.rec)
            d["recorder"] = self.rec.stats()
        if self.obs is not None:
            d.update(self.obs.stats())
        d["log"] = self.log_watch.state
        if self.verdict is not None:
            d["acceptance"] = self.verdict
        elif ctl is not None and loop is not None and sup is not None:
            try:
                d["acceptance"] = self.acceptance()  # so far, from the counters
            except Exception:  # noqa: BLE001 - status must answer
                pass
        d["warnings"] = self.messages[-5:]
        return d

    def _live_line(self) -> str:
        ctl, loop = self.ctl, self.loop
        # progress on the loop's clock: a skipped deadline (a late tick) is time gone too, so a
        # run that ends on time ends at 100 %
        done = (ctl.ticks if ctl else 0) + (loop.stats.skipped_deadlines if loop else 0)
        return live_line(done, self._total_ticks, loop.rate_hz if loop else 0.0,
                         ctl.I_last if ctl else 0.0, _state_text(self.sup) if self.sup else "?",
                         ctl.link_errors if ctl else 0, self.log_watch.warned,
                         loop.stats.live_line() if loop else "")

    def _reload(self) -> None:
        """SIGHUP, in the monitor's reload thread: validate the config file
        again in a child process (:mod:`mrctl.daemon.reload`: bounded in time
        and memory, never in the loop's interpreter); if valid, build the new
        demand and inverse laws from the validated data at the rate the loop
        actually runs and hand them to the controller."""
        assert self.exp is not None and self.ctl is not None and self.loaded is not None
        try:
            new = build(validate_in_child(self.opts.config_path, allow_outside=self.opts.allow_outside_paths))
            changed = [k for k in ("backend", "rate_hz", "safety", "plant", "excitation", "parameters", "loop", "rt",
                                   "sensing", "stream")
                       if _as_plain(new.config.get(k)) != _as_plain(self.loaded.get(k))]
            if new.config.rate_hz != self.exp.config.rate_hz:
                new = new.at_rate(self.exp.config.rate_hz)
            assert self.link is not None
            check_channels((new.demand, new.law), getattr(self.link, "channels", {}), self.link.describe())
            new.law.reset(I0=self.ctl.I_last)  # a plugin whose reset raises is rejected here, off the loop
            if new.demand is not None:
                new.demand.reset()
            self.ctl.pending = (new.law, new.demand)
            self.reloads_ok += 1
            msg = "reload: new demand, inverse taken at the next tick"
            if changed:
                msg += f"; changes to {', '.join(changed)} need a restart and were not applied"
            self.warn(msg, NOTICE)
            self.notifier.send(f"STATUS={msg}")
        except BaseException as exc:  # noqa: BLE001 - a reload (a plugin's SystemExit too) never takes anything down
            self.reloads_rejected += 1
            self.last_reload_error = str(exc) if isinstance(exc, ConfigError) else f"{type(exc).__name__}: {exc}"
            self.warn(f"reload rejected, keeping the running config: {self.last_reload_error}")

    # -- the end -------------------------------------------------------------------
    def _finish(self, exit_code: int) -> int:
        """Figures, the log's fate, the final sidecar (with the exit code).
        Never raises: a run that ends here has already commanded 0 A."""
        assert self.loop is not None and self.ctl is not None and self.sup is not None and self.exp is not None
        try:  # what the law flagged in the loop, said once, after it (a plugin's notices() may raise)
            for note in self.ctl.law.notices():
                self.warn(note)
        except Exception as exc:  # noqa: BLE001
            self.warn(f"{self.ctl.law.name}: notices() raised {type(exc).__name__}: {exc}")
        try:
            timing = self.loop.stats.summary()
            self.say(format_timing(timing))
        except Exception as exc:  # noqa: BLE001
            timing = {"error": f"{type(exc).__name__}: {exc}"}
        summary: dict[str, Any] = {"timing": timing, "safety": self.sup.counters().as_dict(),
                                   "link_errors": self.ctl.link_errors, "ticks": self.ctl.ticks,
                                   "rt": [str(r) for r in self.rt_results],
                                   "exit_current_A": self.exit_current_A,
                                   "law_fault": str(self.ctl.law_fault) if self.ctl.law_fault else None}
        try:  # the link's failures by kind (timeouts, frame and device errors, ...): protocol health
            summary["link"] = self.link.counters() if self.link is not None else None
        except Exception:  # noqa: BLE001 - a plugin link may not have them
            summary["link"] = None
        if self.obs is not None:
            summary.update(self.obs.close(self.rec))  # the last rows to the stream and taps, before the log closes
        if self.rec is not None:
            exit_code = close_log(self.rec, self.opts.out or "", summary, exit_code, self.messages,
                                  I_max=self.exp.I_max, settle_s=self.exp.excitation.settle_s, say=self.say,
                                  warn=lambda m: self.warn(m, ERR),
                                  format_tracking=lambda t: format_summary(t, self.exp.I_max, self.exp.dt,
                                                                               self.exp.excitation.settle_s),
                                  verdict=self._final_verdict, extra=self._duration())
        else:
            exit_code = verdict_exit(self._final_verdict(None, None), exit_code)
        if self.faults is not None:
            self.faults.check()  # a fault in the last 50 ms, after the monitor's last look
        s = self.sup
        self.say(f"safety: {_state_text(s)}, faults entered {s.counters().faults_entered}, "
                 f"link errors {self.ctl.link_errors}")
        return exit_code


#: what the check just before the first tick clears (all the device latches but the E-stop's)
_CLEARED_BEFORE_FIRST_TICK = int(Status.WATCHDOG_TRIPPED | Status.DRIVER_FAULT | Status.RX_ERROR)


def _state_text(sup: SafetySupervisor) -> str:
    """The supervisor's state as people read it: ``LATCHED (estop)``, ``OK``."""
    cause = sup.latch_cause
    return f"{sup.shown_state.name} ({cause})" if cause else sup.shown_state.name


def _as_plain(v: Any) -> Any:
    return v.to_dict() if isinstance(v, Node) else v


def run(opts: RunOptions) -> int:
    return Service(opts).run()
