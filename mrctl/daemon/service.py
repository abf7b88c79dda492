"""Daemon lifecycle around the loop: start-up, signals, systemd, status, shut-down.

What runs where:

- the **main thread** runs the fixed-rate loop (:class:`mrctl.daemon.loop.FixedRateLoop`)
  with :class:`mrctl.daemon.controller.Controller` as its tick. Signal handlers run
  here too, so they only set flags (``loop.stop()``, a reload event);
- a **monitor thread** does everything slow: the live progress line,
  systemd ``STATUS=``/``WATCHDOG=1`` (sent only while the loop's tick
  counter advances, i.e. from a healthy loop), and config reloads (parse and
  validate off the loop, then hand the new laws over at a tick boundary);
- a **status thread** answers ``mrctl status`` on a Unix socket (mode 0660);
- the **recorder's writer thread** (:mod:`mrctl.daemon.recorder`).

Every way out of the loop (end of experiment, SIGINT, SIGTERM, driver lost,
exception) goes through one ``finally`` that commands 0 A first.

Exit codes: 0 normal end or stopped by signal; 1 internal error; 2 bad
config; 3 link failure (could not open, infeasible, driver lost); 4 the run
log could not be written completely.
"""

from __future__ import annotations

import json
import math
import os
import platform
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, TextIO

from mrctl import __version__
from mrctl.config import ConfigError, Node, load_experiment
from mrctl.daemon.controller import RUN_COLUMNS, RUN_FORMATS, Controller
from mrctl.experiment import Experiment, build
from mrctl.io.base import LinkError, Status
from mrctl.util.jsonutil import jsonable
from mrctl.daemon.loop import FixedRateLoop
from mrctl.runlog.metrics import format_summary, tracked_force, tracking_summary
from mrctl.daemon.rt import RtSettings, apply_rt, restore
from mrctl.daemon.safety import SafetyConfig, SafetySupervisor
from mrctl.daemon.timing import format_summary as format_timing

EXIT_OK, EXIT_FAILURE, EXIT_CONFIG, EXIT_LINK, EXIT_LOG = 0, 1, 2, 3, 4


# ----------------------------------------------------------------------------
# systemd notification (sd_notify protocol, no libsystemd dependency)
class Notifier:
    """Sends sd_notify datagrams to $NOTIFY_SOCKET; a no-op without it.

    Why not python-systemd: it is a C extension not on PyPI wheels for every
    platform, and the protocol is one datagram per message."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        path = env.get("NOTIFY_SOCKET")
        self.addr: str | bytes | None = None
        if path:
            self.addr = ("\0" + path[1:]) if path.startswith("@") else path
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        self.watchdog_s: float | None = None
        if usec and usec.isdigit() and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) / 1e6
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return self.addr is not None

    def send(self, *lines: str) -> bool:
        if self.addr is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.sendto("\n".join(lines).encode(), self.addr)
            return True
        except OSError:
            return False

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


# ----------------------------------------------------------------------------
# status socket
def default_status_socket() -> str:
    """$RUNTIME_DIRECTORY (systemd RuntimeDirectory=) or a per-user temp path."""
    rd = os.environ.get("RUNTIME_DIRECTORY")
    if rd:
        return str(Path(rd.split(":")[0]) / "status.sock")
    return f"/tmp/mrctl-{os.getuid()}/status.sock"


class StatusServer:
    """Answers each connection with one JSON line of live state, then closes."""

    def __init__(self, path: str, snapshot: Callable[[], dict[str, Any]]) -> None:
        self.path = path
        self.snapshot = snapshot
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        p = Path(self.path)
        p.parent.mkdir(parents=True, exist_ok=True, mode=0o770)
        if p.is_socket() or p.exists():
            if not p.is_socket():
                raise OSError(f"status socket path exists and is not a socket: {p}")
            if _socket_alive(str(p)):
                raise OSError(f"another mrctl is serving status at {p}")
            p.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o117)  # the socket is born 0660, never briefly wider
        try:
            sock.bind(str(p))
        finally:
            os.umask(old)
        os.chmod(p, 0o660)
        sock.listen(8)
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="mrctl-status", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            with conn:
                try:
                    conn.settimeout(1.0)
                    conn.sendall((json.dumps(jsonable(self.snapshot(), nonfinite="null")) + "\n").encode())
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()
            try:
                os.unlink(self.path)
            except OSError:
                pass


def _socket_alive(path: str) -> bool:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(0.5)
    try:
        s.connect(path)
        return True
    except OSError:
        return False
    finally:
        s.close()


def query_status(path: str, timeout_s: float = 2.0) -> dict[str, Any]:
    """Client side of ``mrctl status``; raises OSError with a clear message."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        try:
            s.connect(path)
        except FileNotFoundError:
            raise OSError(f"no mrctl running (no status socket at {path})") from None
        except ConnectionRefusedError:
            raise OSError(f"no mrctl running (stale status socket at {path})") from None
        chunks = []
        while True:
            b = s.recv(65536)
            if not b:
                break
            chunks.append(b)
    finally:
        s.close()
    return json.loads(b"".join(chunks).decode())


# ----------------------------------------------------------------------------
# building the run from a config
def make_backend(exp: Experiment) -> Any:
    """Backends by name: the one table (``backend.type``)."""
    cfg = exp.config.backend
    kind = cfg.type
    if kind == "sim":
        from mrctl.io.sim import SimLink
        from mrctl.model.bench import SimBench

        bench = SimBench(exp.plant_params, exp.excitation, exp.dt, exp.config.plant.driver_tau_s, exp.make_sensors())
        return SimLink(bench)
    if kind == "serial":
        from mrctl.io.serial import SerialLink

        return SerialLink(cfg.url, cfg.baudrate, timeout_s=cfg.timeout_s, watchdog_ms=cfg.watchdog_ms,
                          spin_wait=cfg.spin_wait)
    if kind == "modbus-tcp":
        from mrctl.io.modbus import ModbusLink

        return ModbusLink("tcp", host=cfg.host, port=cfg.port, unit_id=cfg.unit_id, register_map=cfg.register_map,
                          timeout_s=cfg.timeout_s, use_fc23=cfg.use_fc23, watchdog_ms=cfg.watchdog_ms,
                          open_timeout_s=cfg.open_timeout_s, spin_wait=cfg.spin_wait)
    if kind == "modbus-rtu":
        from mrctl.io.modbus import ModbusLink

        return ModbusLink("rtu", url=cfg.url, baudrate=cfg.baudrate, parity=cfg.parity, stopbits=cfg.stopbits,
                          unit_id=cfg.unit_id, register_map=cfg.register_map, timeout_s=cfg.timeout_s,
                          use_fc23=cfg.use_fc23, watchdog_ms=cfg.watchdog_ms, open_timeout_s=cfg.open_timeout_s,
                          rtu_local_echo=cfg.rtu_local_echo, spin_wait=cfg.spin_wait)
    raise ConfigError([f"backend.type: {kind!r} not supported"])  # pragma: no cover - schema prevents it


def safety_config(cfg: Node, dt: float) -> SafetyConfig:
    s = cfg.safety
    return SafetyConfig(
        I_max=s.I_max, max_slew_A_per_s=s.max_slew_A_per_s, hold_ticks=s.hold_ticks, max_age_s=s.max_age_s,
        x_range_m=s.x_range_m, v_range_mps=s.v_range_mps, F_range_N=s.F_range_N,
        require_force=s.require_force,
        status_fault_mask=int(Status.FAULTS) if s.fault_on_device_status else 0,
        auto_resume=s.auto_resume, resume_good_ticks=s.resume_good_ticks, dt_s=dt,
    )


def lead_s(cfg: Node, backend: Any) -> float:
    """Latency compensation lead (s): explicit, or 'auto' = 1.5 ticks on exchange
    links (one request/reply per tick + the device's own tick), 0 when split."""
    lead = cfg.latency.lead_s
    if lead == "auto":
        return 0.0 if getattr(backend, "split", False) else 1.5 / cfg.rate_hz
    return float(lead)


def rt_settings(cfg: Node) -> RtSettings:
    r = cfg.rt
    return RtSettings(fifo_priority=r.fifo_priority, lock_memory=r.lock_memory, cpus=r.cpus,
                      timer_slack_ns=r.timer_slack_ns, gc_freeze=r.gc_freeze, gc_disable=r.gc_disable)


# ----------------------------------------------------------------------------
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
        self.reload_event = threading.Event()
        self.stop_event = threading.Event()
        self.exp: Experiment | None = None
        self.loop: FixedRateLoop | None = None
        self.ctl: Controller | None = None
        self.sup: SafetySupervisor | None = None
        self.rec: Any = None
        self.rt_results: list[Any] = []
        self.messages: list[str] = []
        self.started_mono = time.monotonic()
        self.reloads_ok = 0
        self.reloads_rejected = 0
        self.last_reload_error: str | None = None
        self.exit_current_A = math.nan  # what the way out commanded (0.0 unless it failed)

    # -- output helpers ---------------------------------------------------
    def say(self, msg: str) -> None:
        print(msg, file=self.opts.stream, flush=True)

    def warn(self, msg: str) -> None:
        self.messages.append(msg)
        print(f"mrctl: {msg}", file=self.opts.err, flush=True)

    # -- status -------------------------------------------------------------
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
                     link_errors=ctl.link_errors, law=getattr(ctl.law, "name", "?"))
        if sup is not None:
            d.update(safety_state=sup.state.name, fault=sup.fault.name if sup.fault else "NONE",
                     fault_reason=sup.reason, safety_counters=sup.counters().as_dict())
        if loop is not None:
            d["timing"] = loop.stats.summary(last_n=5000)
        if self.rec is not None:
            d["recorder"] = self.rec.stats()
        return d

    # -- monitor thread -------------------------------------------------------
    def _monitor(self, total_ticks: int | None) -> None:
        n = self.notifier
        wd = n.watchdog_s
        last_ticks = -1
        last_wd = 0.0
        last_live = 0.0
        is_tty = self.opts.err.isatty() if hasattr(self.opts.err, "isatty") else False
        while not self.stop_event.wait(0.05):
            now = time.monotonic()
            ctl = self.ctl
            if self.reload_event.is_set():
                self.reload_event.clear()
                self._reload()
            ticks = ctl.ticks if ctl else 0
            if wd is not None and now - last_wd >= wd / 2:
                if ticks > last_ticks:  # the loop is alive: only then feed the watchdog
                    n.send("WATCHDOG=1")
                    last_wd = now
                last_ticks = ticks
            if now - last_live >= (0.5 if is_tty else 5.0):
                last_live = now
                line = self._live_line(total_ticks)
                if n.enabled:
                    n.send(f"STATUS={line}")
                if self.opts.live:
                    if is_tty:
                        print("\r" + line[:160].ljust(160), end="", file=self.opts.err, flush=True)
                    else:
                        print(line, file=self.opts.err, flush=True)
        if self.opts.live and is_tty:
            print(file=self.opts.err, flush=True)

    def _live_line(self, total_ticks: int | None) -> str:
        ctl, sup, loop = self.ctl, self.sup, self.loop
        ticks = ctl.ticks if ctl else 0
        if total_ticks:
            frac = min(1.0, ticks / total_ticks)
            bar = "#" * int(frac * 20)
            head = f"[{bar:<20}] {100 * frac:5.1f}% "
        else:
            head = f"{ticks} ticks "
        timing = loop.stats.live_line() if loop else ""
        fault = sup.state.name if sup else "?"
        I = ctl.I_last if ctl else 0.0
        return f"{head}I={I:.3f} A {fault} link_err={ctl.link_errors if ctl else 0} | {timing}"

    # -- SIGHUP reload ---------------------------------------------------------
    def _reload(self) -> None:
        """Validate the config file again; swap demand and inverse laws if valid."""
        assert self.exp is not None and self.ctl is not None
        try:
            new = build(load_experiment(self.opts.config_path))
            old = self.exp.config
            changed = [k for k in ("backend", "rate_hz", "safety", "plant", "excitation", "parameters", "loop", "rt")
                       if _as_plain(new.config.get(k)) != _as_plain(old.get(k))]
            swapped = ["demand", "inverse"]
            self.ctl.pending = (new.law, new.demand)
            self.reloads_ok += 1
            msg = f"reload: new {', '.join(swapped)} taken at the next tick"
            if changed:
                msg += f"; changes to {', '.join(changed)} need a restart and were not applied"
            self.warn(msg)
            self.notifier.send(f"STATUS={msg}")
        except ConfigError as exc:
            self.reloads_rejected += 1
            self.last_reload_error = str(exc)
            self.warn(f"reload rejected, keeping the running config: {exc}")
        except Exception as exc:  # noqa: BLE001 - a reload must never take the loop down
            self.reloads_rejected += 1
            self.last_reload_error = f"{type(exc).__name__}: {exc}"
            self.warn(f"reload rejected, keeping the running config: {self.last_reload_error}")

    def _check_link(self, exp: Experiment, backend: Any) -> Experiment | None:
        """Feasibility of the configured rate on this link (docs/design.md);
        returns the experiment to run (maybe at a reduced rate) or None to refuse."""
        from mrctl.config import load_yaml, validate_experiment
        from mrctl.daemon.feasibility import assess, probe, wire_time_s

        cfg = exp.config
        rtts, errors = probe(backend, cfg.link.probe_exchanges)
        f = assess(cfg.rate_hz, wire_time_s(cfg.backend), rtts, errors, what=cfg.backend.type)
        if f.ok:
            self.say(f.message)
            return exp
        if cfg.link.on_infeasible == "reduce_rate" and f.suggested_rate_hz:
            self.warn(f"{f.message} Running at {f.suggested_rate_hz:g} Hz instead.")
            data = load_yaml(self.opts.config_path)
            data["rate_hz"] = f.suggested_rate_hz
            self.exp = build(validate_experiment(data, Path(self.opts.config_path).parent, self.opts.config_path))
            assert self.sup is not None
            self.sup = SafetySupervisor(safety_config(self.exp.config, self.exp.dt))
            assert self.ctl is not None
            self.ctl.sup = self.sup
            return self.exp
        self.warn(f"refusing to start: {f.message}")
        return None

    # -- the run ---------------------------------------------------------------
    def run(self) -> int:
        o = self.opts
        try:
            exp = self.exp = build(load_experiment(o.config_path))
        except ConfigError as exc:
            self.warn(str(exc))
            return EXIT_CONFIG
        cfg = exp.config
        duration = o.duration_s if o.duration_s is not None else cfg.duration_s
        total_ticks = int(round(duration * cfg.rate_hz)) if duration else None
        try:
            backend = make_backend(exp)
        except ConfigError as exc:
            self.warn(str(exc))
            return EXIT_CONFIG
        self.say(f"mrctl {__version__}: {exp.name}, law {cfg.inverse.law}, {cfg.rate_hz:g} Hz, "
                 f"{'%.3f s' % duration if duration else 'until stopped'}; backend {backend.describe()}")
        try:
            backend.open()
        except (LinkError, OSError) as exc:
            self.warn(f"cannot open backend: {exc}")
            return EXIT_LINK
        sup = self.sup = SafetySupervisor(safety_config(cfg, exp.dt))
        ctl = self.ctl = Controller(backend, exp.law, exp.demand, sup, exp.dt,
                                    driver_retries=cfg.safety.driver_retries,
                                    link_loss_ticks=max(1, round(cfg.safety.link_loss_s * cfg.rate_hz)),
                                    reconnect_every_ticks=max(1, round(cfg.safety.reconnect_interval_s * cfg.rate_hz)),
                                    lead_s=lead_s(cfg, backend))
        # the first thing a (re)start does on the wire: 0 A
        err = ctl.safe_stop()
        if err:
            self.warn(f"could not command 0 A at start: {err}")
            backend.close()
            return EXIT_LINK
        if cfg.backend.type != "sim":
            exp = self._check_link(exp, backend)
            if exp is None:
                backend.close()
                return EXIT_LINK
            cfg = exp.config
            ctl.law, ctl.demand, ctl.dt = exp.law, exp.demand, exp.dt
            total_ticks = int(round(duration * cfg.rate_hz)) if duration else None
        if cfg.loop.pacing == "device":
            from mrctl.daemon.feasibility import check_device_pacing

            try:
                backend.set_device_paced(True, exp.dt, cfg.loop.spin_margin_s)
            except ValueError as exc:  # e.g. a Modbus map without an enable register
                self.warn(f"loop.pacing: {exc}")
                ctl.safe_stop()
                backend.close()
                return EXIT_CONFIG
            why = check_device_pacing(backend, exp.dt)
            if why:
                self.warn(f"refusing to start: {why}")
                ctl.safe_stop()
                backend.close()
                return EXIT_LINK
            self.say(f"device pacing: the loop runs on the device's clock ({cfg.rate_hz:g} Hz)")
        exp.law.reset()
        loop = self.loop = FixedRateLoop(cfg.rate_hz, wait=cfg.loop.wait, spin_margin_s=cfg.loop.spin_margin_s,
                                         clock=o.clock_ns, sleep=o.sleep)
        ctl.loop = loop
        meta = {
            "mrctl_version": __version__, "python": platform.python_version(), "host": platform.node(),
            "config_file": str(Path(o.config_path).resolve()), "config": jsonable(cfg),
            "parameters": exp.params.as_dict(), "backend": backend.describe(),
            "columns_units": dict(zip(RUN_COLUMNS, ("s", "m", "m/s", "N", "N", "A", "tick", "", "s", "A", "N",
                                                    "us", "us", "flags", "count"))),
        }
        status_path = o.status_socket or cfg.service.status_socket or default_status_socket()
        status = StatusServer(status_path, self.snapshot)
        monitor = threading.Thread(target=self._monitor, args=(total_ticks,), name="mrctl-monitor", daemon=True)
        exit_code = EXIT_OK
        old_handlers: dict[int, Any] = {}
        old_switch = sys.getswitchinterval()
        try:
            if o.out:
                from mrctl.daemon.recorder import Recorder

                # host pacing: the loop formats the log in its idle time; device
                # pacing has no idle time between compute and send, but sleeps
                # in the exchange, when the writer thread can format
                host_paced = cfg.loop.pacing == "host"
                self.rec = Recorder(o.out, RUN_COLUMNS, meta, capacity_ticks=cfg.record.buffer_ticks,
                                    flush_interval_s=cfg.record.flush_interval_s, rate_hz=cfg.rate_hz,
                                    fmt=RUN_FORMATS, defer_format=host_paced)
                ctl.record = self.rec.record
                if host_paced:
                    loop.background = self.rec.format_pending
            try:
                status.start()
            except OSError as exc:
                self.warn(f"status socket unavailable ({exc}); running without it")
                status = None  # type: ignore[assignment]
            monitor.start()
            for sig in (signal.SIGINT, signal.SIGTERM):
                old_handlers[sig] = signal.signal(sig, lambda s, f: loop.stop())
            old_handlers[signal.SIGHUP] = signal.signal(signal.SIGHUP, lambda s, f: self.reload_event.set())
            # threads above exist before RT setup, so they do not inherit SCHED_FIFO/affinity
            self.rt_results = apply_rt(rt_settings(cfg))
            for r in self.rt_results:
                self.say(f"rt: {r}")
            sys.setswitchinterval(2e-4)  # a writer thread must not hold the GIL for 5 ms
            self.notifier.send("READY=1", f"STATUS=running {exp.name}")
            if cfg.loop.pacing == "device":
                loop.run_device_paced(ctl.acquire, ctl.tick_paced, duration_s=duration)
            else:
                loop.run(ctl.tick, duration_s=duration)
            if ctl.stopped_reason:
                self.warn(ctl.stopped_reason)
                exit_code = EXIT_LINK
        except KeyboardInterrupt:
            pass  # a second Ctrl-C during start-up: still leave safely below
        except Exception as exc:  # noqa: BLE001 - report, then leave safely below
            self.warn(f"internal error: {type(exc).__name__}: {exc}")
            exit_code = EXIT_FAILURE
        finally:
            err = ctl.safe_stop()  # 0 A first, whatever happened
            self.exit_current_A = ctl.I_last if err is None else math.nan
            self.notifier.send("STOPPING=1")
            sys.setswitchinterval(old_switch)
            restore()
            for sig, h in old_handlers.items():
                signal.signal(sig, h)
            self.stop_event.set()
            if monitor.is_alive():
                monitor.join(timeout=2.0)
            if status is not None:
                status.close()
            backend.close()
            if err:
                self.warn(f"could not command 0 A on exit: {err}")
                exit_code = exit_code or EXIT_LINK
        return self._finish(exit_code)

    def _finish(self, exit_code: int) -> int:
        assert self.loop is not None and self.ctl is not None and self.sup is not None and self.exp is not None
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
                from mrctl.daemon.recorder import read_sidecar, sidecar_path, _write_json_atomic

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
