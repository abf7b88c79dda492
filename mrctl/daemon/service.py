"""``mrctl run``: start-up, the run, and one way out that commands 0 A.

What runs where:

- the **main thread** runs the fixed-rate loop (:class:`mrctl.daemon.loop.FixedRateLoop`)
  with :class:`mrctl.daemon.controller.Controller` as its tick. Signal
  handlers run here too, so they only set flags (``loop.stop()``, a reload
  event);
- the **monitor thread** (:mod:`mrctl.daemon.monitor`): live line, systemd
  status and watchdog, reloads (validated off the loop, handed over at a
  tick boundary);
- the **status thread** (:mod:`mrctl.daemon.status`) answers ``mrctl status``;
- the **recorder's writer thread** (:mod:`mrctl.daemon.recorder`).

Start-up, in this order, once: build the experiment; open the link; command
0 A (the first thing a start does on the wire, so a restart after a crash
never resumes the old current); check that the link sustains the rate, and
with ``link.on_infeasible: reduce_rate`` rebuild the experiment at the rate
that fits; set up device pacing; only then build the safety supervisor and
the controller, at the final rate. Every resource is entered on one
``ExitStack`` whose first callback on the way out commands 0 A, so every
exit (end of experiment, SIGINT, SIGTERM, driver lost, refusal, exception)
passes there first.

Exit codes are carried by the error that ends a start-up
(:mod:`mrctl.errors`): 2 bad config, 3 link failure; a run ends 0, 3 when
the driver was lost, 4 when the log is incomplete, 1 on an internal error.
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
from mrctl.config import ConfigError, Node, load_experiment
from mrctl.daemon.controller import Controller, safe_zero
from mrctl.daemon.feasibility import assess, check_device_pacing, probe, wire_time_s
from mrctl.daemon.loop import FixedRateLoop
from mrctl.daemon.monitor import Monitor
from mrctl.daemon.notify import Notifier
from mrctl.daemon.rt import RtSettings, apply_rt, restore
from mrctl.daemon.safety import SafetyConfig, SafetySupervisor
from mrctl.daemon.status import StatusServer, default_status_socket
from mrctl.daemon.timing import format_summary as format_timing
from mrctl.errors import BadInput, ExitCode, LinkFailure, MrctlError
from mrctl.experiment import Experiment, build
from mrctl.io.base import Link, LinkError
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS, RUN_UNITS
from mrctl.runlog.metrics import format_summary, tracked_force, tracking_summary
from mrctl.util.jsonutil import jsonable

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
    clock_ns: Callable[[], int] = time.monotonic_ns  # injectable for deterministic tests
    sleep: Callable[[float], object] = time.sleep
    stream: TextIO = field(default_factory=lambda: sys.stdout)
    err: TextIO = field(default_factory=lambda: sys.stderr)


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

    # -- output helpers ---------------------------------------------------
    def say(self, msg: str) -> None:
        print(msg, file=self.opts.stream, flush=True)

    def warn(self, msg: str) -> None:
        self.messages.append(msg)
        print(f"mrctl: {msg}", file=self.opts.err, flush=True)

    # -- the run ---------------------------------------------------------------
    def run(self) -> int:
        """The whole run; returns the exit code (README)."""
        code: int = EXIT_OK
        try:
            with contextlib.ExitStack() as stack:
                try:
                    code = self._run(stack)
                except MrctlError as exc:  # a refusal at start-up: the error says how to exit
                    self.warn(str(exc))
                    code = exc.exit_code
                except KeyboardInterrupt:
                    pass  # a second Ctrl-C during start-up: still leave safely (the stack)
                except Exception as exc:  # noqa: BLE001 - report, then leave safely (the stack)
                    self.warn(f"internal error: {type(exc).__name__}: {exc}")
                    code = EXIT_FAILURE
        finally:
            if self.link is not None and self._zero_error is not None:
                self.warn(f"could not command 0 A on exit: {self._zero_error}")
                code = code or EXIT_LINK
        return self._finish(code) if self.ctl is not None and self.loop is not None else code

    def _run(self, stack: contextlib.ExitStack) -> int:
        o = self.opts
        exp = self.exp = build(load_experiment(o.config_path))
        self.loaded = exp.config
        duration = o.duration_s if o.duration_s is not None else exp.config.duration_s
        try:
            link = exp.make_link()
        except ValueError as exc:  # a combination the schema cannot see (e.g. a register map for RTU)
            raise BadInput(f"backend: {exc}") from None
        self.say(f"mrctl {__version__}: {exp.name}, law {exp.config.inverse.law}, {exp.config.rate_hz:g} Hz, "
                 f"{'%.3f s' % duration if duration else 'until stopped'}; backend {link.describe()}")
        try:
            link.open()
        except (LinkError, OSError) as exc:
            raise LinkFailure(f"cannot open backend: {exc}") from None
        self.link = link
        stack.callback(link.close)
        stack.callback(self._zero_on_exit)  # runs before close, also after a refusal below
        err = safe_zero(link)
        if err:
            raise LinkFailure(f"could not command 0 A at start: {err}")
        self._zero_error = None
        if not link.split:
            exp = self.exp = self._check_link(exp, link)
        if exp.config.loop.pacing == "device":
            self._set_device_pacing(exp, link)
        self._build(exp, link, duration)
        self._enter_run(stack)
        ctl, loop = self.ctl, self.loop
        assert ctl is not None and loop is not None
        stack.callback(self._zero_on_exit)  # the first thing on the way out of the loop
        self.notifier.send("READY=1", f"STATUS=running {exp.name}")
        if exp.config.loop.pacing == "device":
            loop.run_device_paced(ctl.acquire, ctl.tick_paced, duration_s=duration)
        else:
            loop.run(ctl.tick, duration_s=duration)
        if ctl.stopped_reason:
            self.warn(ctl.stopped_reason)
            return EXIT_LINK
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

    # -- start-up steps ----------------------------------------------------------
    def _check_link(self, exp: Experiment, link: Link) -> Experiment:
        """Feasibility of the configured rate on this link (docs/design.md):
        the experiment to run, maybe at a reduced rate; LinkFailure to refuse."""
        cfg = exp.config
        rtts, errors = probe(link, cfg.link.probe_exchanges)
        f = assess(cfg.rate_hz, wire_time_s(cfg.backend), rtts, errors, what=cfg.backend.type)
        if f.ok:
            self.say(f.message)
            return exp
        if cfg.link.on_infeasible == "reduce_rate" and f.suggested_rate_hz:
            self.warn(f"{f.message} Running at {f.suggested_rate_hz:g} Hz instead.")
            return exp.at_rate(f.suggested_rate_hz)
        raise LinkFailure(f"refusing to start: {f.message}")

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
        self.sup = SafetySupervisor(SafetyConfig.from_config(cfg.safety, exp.dt))
        ctl = self.ctl = Controller(
            link, exp.law, exp.demand, self.sup, exp.dt, clock_ns=self.opts.clock_ns,
            driver_retries=cfg.safety.driver_retries,
            link_loss_ticks=max(1, round(cfg.safety.link_loss_s * cfg.rate_hz)),
            reconnect_every_ticks=max(1, round(cfg.safety.reconnect_interval_s * cfg.rate_hz)),
            lead=exp.make_lead(link), observer=exp.make_observer())
        ctl.I_last = ctl.I_next = 0.0  # the start-up 0 A went out
        exp.law.reset()
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
            self.rec = Recorder(o.out, RUN_COLUMNS, self._meta(), capacity_ticks=cfg.record.buffer_ticks,
                                flush_interval_s=cfg.record.flush_interval_s, rate_hz=cfg.rate_hz,
                                fmt=RUN_FORMATS, defer_format=host_paced)
            ctl.record = self.rec.record
            if host_paced:
                loop.background = self.rec.format_pending
        status = StatusServer(o.status_socket or cfg.service.status_socket or default_status_socket(), self.snapshot)
        try:
            status.start()
            stack.callback(status.close)
        except OSError as exc:
            self.warn(f"status socket unavailable ({exc}); running without it")
        mon = self.monitor = Monitor(self.notifier, lambda: ctl.ticks, self._live_line, self._reload, o.err, o.live)
        mon.start()
        stack.callback(mon.stop)
        old_handlers = {sig: signal.signal(sig, lambda s, f: loop.stop()) for sig in (signal.SIGINT, signal.SIGTERM)}
        old_handlers[signal.SIGHUP] = signal.signal(signal.SIGHUP, lambda s, f: mon.reload_event.set())
        stack.callback(lambda: [signal.signal(s, h) for s, h in old_handlers.items()])
        old_switch = sys.getswitchinterval()
        stack.callback(sys.setswitchinterval, old_switch)
        stack.callback(restore)
        stack.callback(self.notifier.send, "STOPPING=1")
        # threads above exist before RT setup, so they do not inherit SCHED_FIFO/affinity
        self.rt_results = apply_rt(RtSettings.from_config(cfg.rt))
        for r in self.rt_results:
            self.say(f"rt: {r}")
        sys.setswitchinterval(2e-4)  # a writer thread must not hold the GIL for 5 ms

    def _meta(self) -> dict[str, Any]:
        exp, link = self.exp, self.link
        assert exp is not None and link is not None
        return {
            "mrctl_version": __version__, "python": platform.python_version(), "host": platform.node(),
            "config_file": str(Path(self.opts.config_path).resolve()), "config": jsonable(exp.config),
            "parameters": exp.params.as_dict(), "backend": link.describe(),
            "columns_units": dict(RUN_UNITS),
        }

    # -- status, live line, reload ------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        loop, ctl, sup = self.loop, self.ctl, self.sup
        d: dict[str, Any] = {
            "mrctl_version": __version__, "pid": os.getpid(),
            "experiment": self.exp.name if self.exp else None,
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
            d.update(safety_state=sup.state.name, fault=sup.fault.name if sup.fault else "NONE",
                     fault_reason=sup.reason, safety_counters=sup.counters().as_dict())
        if loop is not None:
            d["timing"] = loop.stats.summary(last_n=5000)
        if self.rec is not None:
            d["recorder"] = self.rec.stats()
        return d

    def _live_line(self) -> str:
        ctl, sup, loop = self.ctl, self.sup, self.loop
        ticks = ctl.ticks if ctl else 0
        total = self._total_ticks
        if total:
            frac = min(1.0, ticks / total)
            bar = "#" * int(frac * 20)
            head = f"[{bar:<20}] {100 * frac:5.1f}% "
        else:
            head = f"{ticks} ticks "
        timing = loop.stats.live_line() if loop else ""
        fault = sup.state.name if sup else "?"
        I = ctl.I_last if ctl else 0.0
        return f"{head}I={I:.3f} A {fault} link_err={ctl.link_errors if ctl else 0} | {timing}"

    def _reload(self) -> None:
        """SIGHUP: validate the config file again (off the loop); if valid,
        hand the new demand and inverse laws to the controller, built at the
        rate the loop actually runs."""
        assert self.exp is not None and self.ctl is not None and self.loaded is not None
        try:
            new = build(load_experiment(self.opts.config_path))
            changed = [k for k in ("backend", "rate_hz", "safety", "plant", "excitation", "parameters", "loop", "rt",
                                   "sensing")
                       if _as_plain(new.config.get(k)) != _as_plain(self.loaded.get(k))]
            if new.config.rate_hz != self.exp.config.rate_hz:
                new = new.at_rate(self.exp.config.rate_hz)
            self.ctl.pending = (new.law, new.demand)
            self.reloads_ok += 1
            msg = "reload: new demand, inverse taken at the next tick"
            if changed:
                msg += f"; changes to {', '.join(changed)} need a restart and were not applied"
            self.warn(msg)
            self.notifier.send(f"STATUS={msg}")
        except Exception as exc:  # noqa: BLE001 - a reload must never take the loop down
            self.reloads_rejected += 1
            self.last_reload_error = str(exc) if isinstance(exc, ConfigError) else f"{type(exc).__name__}: {exc}"
            self.warn(f"reload rejected, keeping the running config: {self.last_reload_error}")

    # -- the end -------------------------------------------------------------------
    def _finish(self, exit_code: int) -> int:
        assert self.loop is not None and self.ctl is not None and self.sup is not None and self.exp is not None
        for note in self.ctl.law.notices():  # what the law flagged in the loop, said once, after it
            self.warn(note)
        timing = self.loop.stats.summary()
        summary: dict[str, Any] = {"timing": timing, "safety": self.sup.counters().as_dict(),
                                   "link_errors": self.ctl.link_errors, "ticks": self.ctl.ticks,
                                   "rt": [str(r) for r in self.rt_results], "exit_code": exit_code,
                                   "exit_current_A": self.exit_current_A,
                                   "messages": self.messages}
        self.say(format_timing(timing))
        if self.rec is not None:
            stats = self.rec.close(summary=summary)
            track = self._tracking(self.opts.out)
            if track:
                summary["tracking"] = track
                self.say(format_summary(track, self.exp.I_max))
                from mrctl.daemon.recorder import _write_json_atomic, read_sidecar, sidecar_path

                side = read_sidecar(self.opts.out)
                side.setdefault("summary", {})["tracking"] = track
                _write_json_atomic(sidecar_path(self.opts.out), side)
            lost = stats.get("dropped_rows", 0)
            if stats.get("error") or lost:
                self.warn(f"run log incomplete: {lost} rows dropped; {stats.get('error') or ''}".strip())
                exit_code = exit_code or EXIT_LOG
            else:
                self.say(f"wrote {self.opts.out} ({stats.get('rows_written')} rows) and its .json sidecar")
        s = self.sup
        self.say(f"safety: {s.state.name}, faults entered {s.counters().faults_entered}, "
                 f"link errors {self.ctl.link_errors}")
        return exit_code

    def _tracking(self, path: str | None) -> dict[str, float] | None:
        if not path:
            return None
        from mrctl.daemon.recorder import read_run

        try:
            cols = read_run(path)
        except Exception:  # noqa: BLE001 - figures are a bonus; the log itself was reported
            return None
        if len(cols.get("t", ())) < 2:
            return None
        F, _ = tracked_force(cols)
        try:
            return tracking_summary(cols["t"], cols["F_des"], F, cols["I"], self.exp.I_max,  # type: ignore[union-attr]
                                    self.exp.excitation.settle_s)  # type: ignore[union-attr]
        except Exception:  # noqa: BLE001
            return None


def _as_plain(v: Any) -> Any:
    return v.to_dict() if isinstance(v, Node) else v


def run(opts: RunOptions) -> int:
    return Service(opts).run()
