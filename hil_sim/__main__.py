"""``python -m hil_sim``: the simulated MR-damper bench as its own process.

    python -m hil_sim [--config config/hil_bench.yaml] [--transport serial]
                      [--link /tmp/mrctl-sim-tty] [--bind 127.0.0.1:5020] [--baud N]
                      [--duration S] [--seed N] [--truth truth.csv] [--wait hybrid]
                      [--fault KIND@AT_S+FOR_S[,param=value]] ...

Prints one ``hil_sim ready ...`` line on stdout once it serves (also to
``--ready-file PATH``, removed at exit); SIGTERM or SIGINT (or
``--duration``) stops it cleanly: 0 A, truth log flushed, symlink removed, exit 0. Start-up errors (bad config, unusable link path, port in
use, missing transport) are one line per problem on stderr and exit 2.
Details: docs/hil_sim.md.
"""

from __future__ import annotations

from mrctl.util.blas import limit_blas_threads

limit_blas_threads()  # before anything imports numpy (mrctl/util/blas.py)

import argparse  # noqa: E402
import math
import os
import signal
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

TRANSPORTS = ("serial", "modbus-tcp", "modbus-rtu")
DEVICES = ("labjack_t7",)
DEFAULT_LINK = "/tmp/mrctl-sim-tty"
DEFAULT_BIND = "127.0.0.1:5020"
DEFAULT_BAUD = 921600
DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "config" / "hil_bench.yaml"
READY_TIMEOUT_S = 10.0

#: Used when no --config is given and config/hil_bench.yaml is not beside the package.
BUILTIN_CONFIG: dict[str, Any] = {
    "version": 1,
    "rate_hz": 1000,
    "parameters": "table1",
    "excitation": {"type": "sine", "amplitude_m": 0.010, "frequency_hz": 1.0},
}


class StartupError(Exception):
    """A problem that stops the process before it serves: exit 2, one line each."""

    def __init__(self, *lines: str) -> None:
        self.lines = list(lines)
        super().__init__("; ".join(lines))


def _parse_bind(text: str) -> tuple[str, int]:
    """``HOST:PORT``, or ``PORT`` alone = loopback (``127.0.0.1:PORT``): nothing
    listens beyond this machine unless a host is named."""
    if text.isdigit():
        text = f"{DEFAULT_BIND.rpartition(':')[0]}:{text}"
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT or PORT, got {text!r}")
    host = host.strip("[]")
    try:
        p = int(port)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port must be a number, got {port!r}") from None
    if not 0 <= p < 65536:
        raise argparse.ArgumentTypeError(f"port out of range: {p}")
    return host, p


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def _nonneg_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m hil_sim",
        description="Simulated MR-damper bench (shaker + LuGre plant + driver + sensors) on its own "
                    "1 kHz clock, served over the real protocols for hardware-in-the-loop tests.",
    )
    ap.add_argument("--config", type=Path, default=None,
                    help=f"bench YAML (default: {DEFAULT_CONFIG.relative_to(DEFAULT_CONFIG.parent.parent)})")
    ap.add_argument("--transport", choices=TRANSPORTS, default="serial", help="protocol to serve (default serial)")
    ap.add_argument("--device", choices=DEVICES, default=None,
                    help="emulate a bought DAQ instead of mrctl's register map: labjack_t7 (with --transport "
                         "modbus-tcp; the wiring is the config's labjack_t7 section, docs/hil_sim.md)")
    ap.add_argument("--latency-s", type=float, default=None, metavar="S",
                    help="--device: command-response time per request (overrides labjack_t7.latency_s)")
    ap.add_argument("--link", default=DEFAULT_LINK,
                    help=f"serial/modbus-rtu: symlink to create for the host side of the pty (default {DEFAULT_LINK})")
    ap.add_argument("--bind", type=_parse_bind, default=_parse_bind(DEFAULT_BIND), metavar="HOST:PORT",
                    help=f"modbus-tcp: address to listen on (default {DEFAULT_BIND}, loopback; PORT alone = "
                         "127.0.0.1:PORT; port 0 = any free port, shown in the READY line)")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD,
                    help=f"modbus-rtu: baud rate (default {DEFAULT_BAUD}); sets the RTU inter-frame silence, "
                         "the pty itself has no baud rate")
    ap.add_argument("--duration", type=_positive_float, default=None, metavar="S",
                    help="stop after S seconds (overrides duration_s)")
    ap.add_argument("--at-rest", action="store_true",
                    help="the shaker holds still at x = 0 whatever the bench file says: the damper at rest "
                         "that mrctl calibrate measures (docs/hardware.md)")
    ap.add_argument("--seed", type=_nonneg_int, default=None, help="sensor-noise seed (overrides seed)")
    ap.add_argument("--truth", type=Path, default=None, metavar="FILE.csv",
                    help="write the per-tick ground-truth log here (+ FILE.json summary at exit)")
    ap.add_argument("--serve", choices=("inline", "thread"), default="inline",
                    help="serve the link from the clock thread while it spins (inline, lowest latency, "
                         "one busy core; the clock then spins, whatever --wait says) or from blocking "
                         "server threads")
    ap.add_argument("--wait", choices=("hybrid", "sleep", "spin"), default="hybrid",
                    help="clock wait strategy (default hybrid: sleep, then spin the last 0.2 ms)")
    ap.add_argument("--ready-file", type=Path, default=None, metavar="PATH",
                    help="write the ready line to PATH once the bench serves (a stale PATH is removed at start, "
                         "PATH is removed at exit): a script waits for it before starting mrctl run")
    ap.add_argument("--fault", action="append", default=[], metavar="KIND@AT_S+FOR_S[,param=value]",
                    help="schedule a fault on the device clock (repeatable; added to the config's faults), "
                         "e.g. drop_replies@2.0+0.05 or delay_replies@3+0.3,delay_s=0.003; kinds: "
                         "drop_replies, delay_replies, corrupt_crc, garbage, stale_seq, nan, out_of_range, "
                         "modbus_exception, disconnect, ignore_writes, ignore_setpoints, estop (docs/hil_sim.md)")
    return ap


def _fail(lines: list[str]) -> int:
    for line in lines:
        print(f"hil_sim: {line}", file=sys.stderr)
    sys.stderr.flush()
    return 2


def _load_config(args: argparse.Namespace):
    from hil_sim.config import ConfigError, load_bench_config, validate_bench
    from hil_sim.faults import check_transport

    kw = dict(seed=args.seed, duration_s=args.duration, faults=args.fault, at_rest=args.at_rest)
    try:
        if args.config is not None:
            cfg = load_bench_config(args.config, **kw)
        elif DEFAULT_CONFIG.is_file():
            cfg = load_bench_config(DEFAULT_CONFIG, **kw)
        else:
            cfg = validate_bench(dict(BUILTIN_CONFIG), Path.cwd(), "built-in defaults", **kw)
    except ConfigError as e:
        head = f"{e.source}: " if e.source else ""
        raise StartupError(*(f"{head}{err}" for err in e.errors)) from None
    errors = check_transport(cfg.faults, args.transport)
    if errors:
        head = f"{cfg.source}: " if cfg.source and any(not f.source.startswith("--") for f in cfg.faults) else ""
        raise StartupError(*(e if e.startswith("--") else f"{head}{e}" for e in errors))
    return cfg


def _check_tcp_free(host: str, port: int) -> None:
    """Fail early, with a clear message, if host:port can't be listened on."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise StartupError(f"--bind {host}:{port}: cannot resolve host: {e.strerror}") from None
    family, _, _, _, addr = infos[0]
    s = socket.socket(family, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(addr)
    except OSError as e:
        raise StartupError(f"--bind {host}:{port}: cannot listen: {e.strerror}") from None
    finally:
        s.close()


def _import_modbus(transport: str):
    """The transport's server module (hil_sim.modbus_tcp or hil_sim.modbus_rtu)."""
    import importlib

    name = "hil_sim." + transport.replace("-", "_")
    try:
        return importlib.import_module(name)
    except ImportError as e:
        what = f"{name} is not installed" if e.name == name else str(e)
        raise StartupError(f"--transport {transport}: not available ({what})") from None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except StartupError as e:
        return _fail(e.lines)


def _run(args: argparse.Namespace) -> int:
    cfg = _load_config(args)

    from hil_sim.bench import BenchDevice
    from hil_sim.pty_endpoint import LinkPathError, PtyEndpoint
    from hil_sim.serial_device import SerialDevice
    from hil_sim.state import DeviceState
    from hil_sim.threads import run_server
    from hil_sim.truth import TruthLog
    from mrctl.io.registers import default_register_map

    # Short GIL switch interval: the clock spins while it waits, and a server
    # thread answering a request must not wait 5 ms (the default) for the GIL.
    sys.setswitchinterval(2e-4)

    inline = args.serve == "inline"
    t7 = None
    if args.device is not None:
        from hil_sim.labjack_t7 import device_errors

        errs = device_errors(args, cfg)
        if errs:
            raise StartupError(*errs)
    modbus = _import_modbus(args.transport) if args.transport.startswith("modbus") else None
    if args.transport == "modbus-tcp":
        _check_tcp_free(*args.bind)

    state = DeviceState()
    stop = threading.Event()
    device = None
    modbus_dev: list[Any] = []  # the ModbusDevice, for its counters in the summary

    def on_signal(signum: int, _frame: object) -> None:
        stop.set()
        if device is not None:
            device.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    failed: list[str] = []
    cleanups: list[Callable[[], object]] = []
    threads: list[threading.Thread] = []
    truth = None
    clock_thread = None
    status = 0
    if args.ready_file is not None:
        try:  # a file left by an earlier bench must not announce this one
            args.ready_file.unlink(missing_ok=True)
        except OSError as e:
            raise StartupError(f"--ready-file {args.ready_file}: cannot remove the old file: {e.strerror}") from None
    try:
        if args.truth is not None:
            try:
                # inline serving: no writer thread (it would cost the spinning
                # clock GIL hand-offs); the clock formats rows in its idle spin
                truth = TruthLog(args.truth, cfg.rate_hz, threaded=not inline)
            except OSError as e:
                raise StartupError(f"--truth {args.truth}: cannot open: {e.strerror}") from None
        device = None if inline else BenchDevice(cfg, state, truth, wait=args.wait)

        def inline_device(poll: Callable[[], object]) -> Any:
            """One thread spins, ticks the bench on time and serves the link in
            between: a reply never waits for a thread wake-up (docs/hil_sim.md)."""
            if truth is not None:
                work = truth.work_once

                def idle() -> None:
                    poll()
                    work()
            else:
                idle = poll
            return BenchDevice(cfg, state, truth, wait="spin", idle=idle)

        # -- transport -----------------------------------------------------------
        ready_info: dict[str, str] = {"transport": args.transport}
        server_ready = threading.Event()
        server: Any = None
        if args.transport in ("serial", "modbus-rtu"):
            try:
                endpoint = PtyEndpoint(args.link)
            except LinkPathError as e:
                raise StartupError(str(e)) from None
            cleanups.append(endpoint.close)
            ready_info.update(link=str(args.link), tty=endpoint.tty_path)
        if args.transport == "serial":
            server = SerialDevice(state, endpoint.master_fd, stop, cfg.I_max_A, endpoint=endpoint, seed=cfg.seed)
            if inline:
                device = inline_device(server.poll_once)
            else:
                threads.append(run_server(server.serve, "serial", failed, stop))
            server_ready.set()
        elif args.transport == "modbus-rtu":
            # The RTU server takes the pty master fd directly (the device side).
            from hil_sim.modbus_device import ModbusDevice

            regs = default_register_map()
            ready_info["baud"] = str(args.baud)
            if inline:
                rtu = modbus.ModbusRtuInline(ModbusDevice(state, regs), endpoint.master_fd,
                                             modbus.rtu_silence_s(args.baud), endpoint)
                modbus_dev.append(rtu.dev)
                device = inline_device(rtu.poll_once)
                server_ready.set()
            else:
                threads.append(run_server(
                    lambda: modbus.serve_modbus_rtu(state, endpoint.master_fd, args.baud, regs, stop,
                                                    ready=lambda _msg: server_ready.set(), endpoint=endpoint,
                                                    on_device=modbus_dev.append),
                    "modbus-rtu", failed, stop))
        elif inline:  # modbus-tcp served from the clock thread
            host, port = args.bind
            if args.device is not None:
                from hil_sim.labjack_t7 import T7Device

                t7 = T7Device(state, cfg.t7, latency_s=args.latency_s)
                ready_info["device"] = args.device
            try:
                tcp = modbus.ModbusTcpInline(state, host, port, default_register_map(), device=t7,
                                             max_clients=16 if t7 is None else t7.max_connections)
            except OSError as e:
                raise StartupError(f"--bind {host}:{port}: cannot listen: {e.strerror}") from None
            cleanups.append(tcp.close)
            modbus_dev.append(tcp.dev)
            ready_info["bind"] = f"{host}:{tcp.port}"
            device = inline_device(tcp.poll_once if t7 is None else t7.poll_with(tcp.poll_once))
            server_ready.set()
        else:  # modbus-tcp, threaded
            host, port = args.bind
            regs = default_register_map()
            ready_info["bind"] = f"{host}:{port}"

            def tcp_ready(msg: str) -> None:
                # "modbus-tcp HOST:PORT" with the real port (--bind HOST:0 picks one)
                ready_info["bind"] = msg.rpartition(" ")[2] or ready_info["bind"]
                server_ready.set()

            threads.append(run_server(
                lambda: modbus.serve_modbus_tcp(state, host, port, regs, stop, ready=tcp_ready,
                                                on_device=modbus_dev.append),
                "modbus-tcp", failed, stop))

        # -- wait for the server, then start the clock -----------------------------
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not server_ready.wait(0.02):
            if failed or stop.is_set() or time.monotonic() > deadline:
                break
        if failed:
            raise StartupError(*failed)
        if not server_ready.is_set() and not stop.is_set():
            print(f"hil_sim: warning: {args.transport} server did not report ready within "
                  f"{READY_TIMEOUT_S:g} s; going on", file=sys.stderr, flush=True)

        def clock() -> None:
            try:
                from mrctl.daemon.rt import RtSettings, apply_rt

                apply_rt(RtSettings(timer_slack_ns=1000))  # best effort, never raises
                device.run(cfg.duration_s)
            finally:
                stop.set()

        clock_thread = run_server(clock, "clock", failed, stop)

        # -- READY ------------------------------------------------------------------
        device.first_tick.wait(READY_TIMEOUT_S)
        if not stop.is_set():
            fields = " ".join(f"{k}={v}" for k, v in ready_info.items())
            line = f"hil_sim ready {fields} rate_hz={cfg.rate_hz:g} seed={cfg.seed}"
            if args.ready_file is not None:  # before stdout: whoever reads either finds both
                _write_ready(args.ready_file, line)
                cleanups.append(lambda: args.ready_file.unlink(missing_ok=True))
            print(line, flush=True)

        while not stop.is_set():
            stop.wait(0.2)
    finally:
        stop.set()
        if device is not None:
            device.stop()
        if clock_thread is not None:
            clock_thread.join(5.0)
        for t in threads:
            t.join(2.0)
        for c in reversed(cleanups):
            c()
        summary: dict[str, Any] = {}
        if device is not None:
            summary = {"config": cfg.describe(), "transport": args.transport, "bench": device.summary()}
            if modbus_dev:
                summary["modbus"] = modbus_dev[0].counters()
            if server is not None:
                summary["serial"] = server.counters()
            if failed:
                summary["failed"] = failed
        if truth is not None:
            summary = truth.close(summary)
        if device is not None and clock_thread is not None:
            _print_summary(summary)
    if failed:
        status = 1
    return status


def _write_ready(path: Path, line: str) -> None:
    """The ready line to ``path``, whole or not at all (written beside it,
    then renamed): a waiting script never reads half a line."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(line + "\n")
        os.replace(tmp, path)
    except OSError as e:
        print(f"hil_sim: warning: --ready-file {path}: {e.strerror}", file=sys.stderr, flush=True)


def _print_summary(summary: dict[str, Any]) -> None:
    b = summary.get("bench", {})
    tm = b.get("timing", {})

    def f(x: Any) -> str:
        return "-" if x is None else f"{x:.0f}"

    line = (f"hil_sim: stopped after {b.get('ticks')} ticks; setpoints {b.get('setpoints_received')}, "
            f"watchdog trips {b.get('watchdog_trips')}; late p99/max {f(tm.get('lateness_p99_us'))}/"
            f"{f(tm.get('lateness_max_us'))} us, overruns {tm.get('overruns')}, "
            f"skipped {tm.get('skipped_deadlines')}")
    if "serial" in summary:
        s = summary["serial"]
        line += f"; serial replies {s['replies']}, crc errors {s['crc_errors']}"
    if "truth_log" in summary:
        t = summary["truth_log"]
        line += f"; truth rows {t['rows_written']} (dropped {t['rows_dropped']})"
        if t.get("error"):
            line += f", error: {t['error']}"
    print(line, file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
