#!/usr/bin/env python3
"""Per-tick round trip of a Link (one ``exchange``) against a simulated device.

The device runs in a **separate process** (its own GIL and wake-ups) and this
process calls ``link.exchange()`` N times at ~1 kHz, recording each call's
duration. Reported: p50/p99/p99.9/max µs, errors by type, and where the time
goes:

* ``client_us``  — the link's own Python per exchange (encode, CRC, decode,
  Sample), measured with timeit against an in-memory transport that answers
  instantly (no syscalls);
* ``server_us``  — the device's request handling (ModbusDevice.handle_*),
  measured with timeit in this process;
* ``floor``      — a raw ping-pong of similar byte counts with a trivial echo
  process over the same kind of channel (loopback TCP / pty): the kernel +
  wake-up cost no Python code avoids;
* the rest of p50 is syscalls, select() and scheduling on both sides.

Devices (``--device``): ``process`` = ``serve_modbus_tcp``/``serve_modbus_rtu``
in a subprocess with a light 1 kHz sample publisher (default: isolates the
link); ``hil_sim`` = ``python -m hil_sim`` (plant clock spinning, as in the
HIL tests; the only device for ``--transport serial``); ``thread`` = in this
process (shares our GIL: shows why not).

    python bench/link_roundtrip.py                        # modbus-tcp and modbus-rtu
    python bench/link_roundtrip.py --transport modbus-tcp --fc23 off -n 10000
    python bench/link_roundtrip.py --device hil_sim --transport modbus-tcp --transport modbus-rtu --transport serial
    python bench/link_roundtrip.py --client pymodbus      # pymodbus's sync clients, for comparison
    python bench/link_roundtrip.py --json out.json

A transport is an entry in ``TRANSPORTS``: (start device → (handle, Link),
client cost, server cost, floor). The measuring loop only speaks the Link
interface, so the serial protocol and both Modbus flavours share it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import threading
import time
import timeit
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mrctl.io.base import LinkError, Sample  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- device process
def _clock_thread(state: Any, stop: threading.Event, period_s: float = 1e-3) -> threading.Thread:
    """Publish a plausible sample every period (stands in for hil_sim's clock)."""

    def run() -> None:
        k = 0
        t0 = time.monotonic()
        while not stop.is_set():
            k += 1
            t = time.monotonic() - t0
            state.publish(Sample(k, t, 0.01 * math.sin(t), 0.05 * math.cos(t), 100.0 * math.sin(t), 8, 0.5))
            stop.wait(period_s)

    th = threading.Thread(target=run, daemon=True, name="clock")
    th.start()
    return th


def serve_main(argv: list[str]) -> None:
    """Child process: ``--serve modbus-tcp|modbus-rtu|echo-tcp|echo-pty ...``; prints its ready line."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--serve", required=True)
    ap.add_argument("--path", default="")
    ap.add_argument("--fd", type=int, default=-1, help="serve RTU on this inherited fd instead of --path")
    ap.add_argument("--baud", type=int, default=921600)
    ap.add_argument("--no-fc23", action="store_true")
    ap.add_argument("--reply-bytes", type=int, default=35)
    a = ap.parse_args(argv)
    stop = threading.Event()

    def ready(msg: str) -> None:
        print(msg, flush=True)

    # parent closes our stdin to stop us
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    if a.serve.startswith("echo"):
        _echo_server(a.serve, a.path, a.reply_bytes, stop, ready)
        return
    from hil_sim.modbus_tcp import serve_modbus_tcp
    from hil_sim.modbus_rtu import serve_modbus_rtu
    from hil_sim.state import DeviceState

    state = DeviceState()
    _clock_thread(state, stop)
    if a.serve == "modbus-tcp":
        serve_modbus_tcp(state, "127.0.0.1", 0, None, stop, ready, fc23=not a.no_fc23)
    elif a.serve == "modbus-rtu":
        serve_modbus_rtu(state, a.fd if a.fd >= 0 else a.path, a.baud, None, stop, ready, fc23=not a.no_fc23)
    else:
        raise SystemExit(f"unknown --serve {a.serve}")


def _echo_server(kind: str, path: str, reply_bytes: int, stop: threading.Event, ready: Callable[[str], None]) -> None:
    """Trivial responder: any read → ``reply_bytes`` bytes back. The wake-up floor."""
    import select
    import socket

    reply = bytes(reply_bytes)
    if kind == "echo-tcp":
        ls = socket.create_server(("127.0.0.1", 0))
        ready(f"echo-tcp 127.0.0.1:{ls.getsockname()[1]}")
        c, _ = ls.accept()
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        while not stop.is_set():
            if not select.select([c], [], [], 0.05)[0]:
                continue
            if not c.recv(4096):
                return
            c.sendall(reply)
    else:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        ready(f"echo-pty {path}")
        while not stop.is_set():
            if not select.select([fd], [], [], 0.05)[0]:
                continue
            try:
                if not os.read(fd, 4096):
                    return
            except OSError:
                return
            os.write(fd, reply)


@dataclass
class Device:
    """A device process (or thread) and how to stop it."""

    ready: str
    proc: subprocess.Popen | None = None
    thread: threading.Thread | None = None
    stop_event: threading.Event | None = None
    keep: list = field(default_factory=list)  # fds to keep open while running

    def stop(self) -> None:
        if self.proc is not None:
            try:
                self.proc.stdin.close()  # type: ignore[union-attr]
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.stop_event is not None:
            self.stop_event.set()
            if self.thread is not None:
                self.thread.join(5)
        for fd in self.keep:
            try:
                os.close(fd)
            except OSError:
                pass


def start_process(args: list[str], pass_fds: tuple[int, ...] = ()) -> Device:
    proc = subprocess.Popen(
        [sys.executable, str(Path(__file__).resolve()), *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=str(ROOT),
        pass_fds=pass_fds,
    )
    line = proc.stdout.readline().strip()  # type: ignore[union-attr]
    if not line:
        proc.kill()
        raise SystemExit(f"device process {args} did not start")
    return Device(line, proc=proc)


def start_thread(target: Callable[..., None], *args: Any, **kw: Any) -> Device:
    from hil_sim.state import DeviceState

    state = DeviceState()
    stop = threading.Event()
    got: list[str] = []
    _clock_thread(state, stop)
    th = threading.Thread(target=target, args=(state, *args, stop, got.append), kwargs=kw, daemon=True)
    th.start()
    t_end = time.monotonic() + 5
    while not got and time.monotonic() < t_end:
        time.sleep(0.01)
    return Device(got[0] if got else "?", thread=th, stop_event=stop)


def start_hil_sim(transport: str, a: argparse.Namespace) -> Device:
    """``python -m hil_sim`` (the real bench: plant clock, GIL switch interval 0.2 ms)."""
    import tempfile

    args = ["-m", "hil_sim", "--transport", transport, "--duration", "3600"]
    args += ["--serve", a.hil_serve]
    tmpdir = None
    if transport == "modbus-tcp":
        args += ["--bind", "127.0.0.1:0"]
    else:
        tmpdir = tempfile.mkdtemp(prefix="link_roundtrip-")
        args += ["--link", os.path.join(tmpdir, "tty"), "--baud", str(a.baud)]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, cwd=str(ROOT), env=env)
    t_end = time.monotonic() + 20
    while time.monotonic() < t_end:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        if not line:
            break
        if line.startswith("hil_sim ready"):
            return _HilSim(line.strip(), proc=proc, tmpdir=tmpdir)
    proc.kill()
    raise SystemExit(f"python -m hil_sim --transport {transport} did not become ready")


@dataclass
class _HilSim(Device):
    tmpdir: str | None = None

    def field(self, key: str) -> str:
        return self.ready.split(f"{key}=")[1].split()[0]

    def stop(self) -> None:
        import signal

        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.tmpdir:
            import shutil

            shutil.rmtree(self.tmpdir, ignore_errors=True)


def _pty_pair() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


# ----------------------------------------------------------------------------- transports
@dataclass
class Transport:
    start: Callable[[argparse.Namespace], tuple[Device, Any]]  # → (device, link)
    client_cost_us: Callable[[argparse.Namespace], dict[str, float]]
    server_cost_us: Callable[[argparse.Namespace], dict[str, float]]
    floor: Callable[[argparse.Namespace, int], list[float]]  # raw ping-pong durations (s)


def _fc23_arg(a: argparse.Namespace) -> bool | None:
    return {"auto": None, "on": True, "off": False}[a.fc23]


class PymodbusLink:
    """pymodbus's synchronous client behind the Link interface (comparison only).

    One FC23 per exchange via ``readwrite_registers``; registers decoded with
    the same RegisterMap. Errors are not mapped finely: anything → LinkError.
    """

    def __init__(self, client: Any) -> None:
        from mrctl.io.registers import default_register_map

        self.client = client
        self.rm = default_register_map()
        self.is_open = False

    def open(self) -> None:
        if not self.client.connect():
            raise LinkError("pymodbus client cannot connect")
        self.is_open = True

    def close(self) -> None:
        self.client.close()
        self.is_open = False

    def describe(self) -> str:
        return f"pymodbus {type(self.client).__name__} (sync), FC23 readwrite_registers"

    def exchange(self, current_A: float) -> Sample:
        import struct as _struct

        rb, wb = self.rm.read_blocks[0], self.rm.write_block
        words = list(_struct.unpack(f">{wb.count}H", self.rm.encode_write(current_A, True, 50)))
        try:
            r = self.client.readwrite_registers(read_address=rb.address, read_count=rb.count,
                                                write_address=wb.address, values=words, device_id=1)
        except Exception as e:  # noqa: BLE001
            raise LinkError(str(e)) from e
        if r.isError():
            raise LinkError(str(r))
        v = self.rm.decode_read(_struct.pack(f">{rb.count}H", *r.registers))
        return Sample(v.seq, v.t_dev * 1e-6, v.x_m, v.v_mps, v.F_N, v.status, v.current_applied_A)


def _modbus_tcp_start(a: argparse.Namespace) -> tuple[Device, Any]:
    from mrctl.io.modbus import ModbusLink

    if a.device == "hil_sim":
        dev = start_hil_sim("modbus-tcp", a)
        port = int(dev.field("bind").rsplit(":", 1)[1])  # type: ignore[attr-defined]
    elif a.device == "thread":
        from hil_sim.modbus_tcp import serve_modbus_tcp

        dev = start_thread(serve_modbus_tcp, "127.0.0.1", 0, None, fc23=not a.device_no_fc23)
        port = int(dev.ready.rsplit(":", 1)[1])
    else:
        dev = start_process(["--serve", "modbus-tcp"] + (["--no-fc23"] if a.device_no_fc23 else []))
        port = int(dev.ready.rsplit(":", 1)[1])
    if a.client == "pymodbus":
        from pymodbus.client import ModbusTcpClient

        return dev, PymodbusLink(ModbusTcpClient("127.0.0.1", port=port, timeout=max(a.timeout_ms * 1e-3, 0.1)))
    link = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=a.timeout_ms * 1e-3, use_fc23=_fc23_arg(a),
                      spin_wait=a.client_wait == "spin")
    return dev, link


def _modbus_rtu_start(a: argparse.Namespace) -> tuple[Device, Any]:
    from mrctl.io.modbus import ModbusLink

    if a.device == "hil_sim":
        dev = start_hil_sim("modbus-rtu", a)
        url = dev.field("link")  # type: ignore[attr-defined]
        if a.client == "pymodbus":
            from pymodbus.client import ModbusSerialClient

            return dev, PymodbusLink(ModbusSerialClient(url, baudrate=a.baud, parity="N",
                                                        timeout=max(a.timeout_ms * 1e-3, 0.1)))
        return dev, ModbusLink("rtu", url=url, baudrate=a.baud, timeout_s=a.timeout_ms * 1e-3,
                               spin_wait=a.client_wait == "spin",
                               use_fc23=_fc23_arg(a))
    master, slave, path = _pty_pair()
    if a.client == "pymodbus":  # it needs a path: device on the master fd, client on the slave path
        from pymodbus.client import ModbusSerialClient

        dev = start_process(["--serve", "modbus-rtu", "--fd", str(master), "--baud", str(a.baud)], pass_fds=(master,))
        dev.keep += [master, slave]
        client = ModbusSerialClient(path, baudrate=a.baud, parity="N", timeout=max(a.timeout_ms * 1e-3, 0.1))
        return dev, PymodbusLink(client)
    if a.device == "thread":
        from hil_sim.modbus_rtu import serve_modbus_rtu

        dev = start_thread(serve_modbus_rtu, path, a.baud, None, fc23=not a.device_no_fc23)
    else:
        dev = start_process(["--serve", "modbus-rtu", "--path", path, "--baud", str(a.baud)]
                            + (["--no-fc23"] if a.device_no_fc23 else []))
    dev.keep += [master, slave]
    link = ModbusLink("rtu", url=master, baudrate=a.baud, timeout_s=a.timeout_ms * 1e-3, use_fc23=_fc23_arg(a),
                      spin_wait=a.client_wait == "spin")
    return dev, link


class _InstantIO:
    """In-memory RTU transport answering every request with a canned response."""

    def __init__(self, responses: dict[int, bytes]) -> None:
        self.responses = responses
        self.pending = b""

    def write(self, data: bytes | bytearray, deadline: float) -> None:
        self.pending = self.responses[data[1]]

    def read(self, n: int, deadline: float, max_n: int = 0, wake_ns: int = 0) -> bytes:
        n = max(n, max_n)
        out, self.pending = self.pending[:n], self.pending[n:]
        return out

    def flush_input(self) -> int:
        return 0

    def close(self) -> None:
        pass


class _InstantSocket:
    """In-memory TCP 'socket': recv returns the canned response with the request's tid."""

    def __init__(self, responses: dict[int, bytes]) -> None:
        self.responses = responses
        self.pending = b""

    def send(self, data: bytes | bytearray) -> int:
        r = self.responses[data[7]]
        self.pending = bytes(data[:2]) + r[2:]
        return len(data)

    def recv(self, n: int) -> bytes:
        out, self.pending = self.pending, b""
        return out

    def fileno(self) -> int:  # select() on it: always "readable" via the pipe below
        return _ALWAYS_READABLE[0]

    def close(self) -> None:
        pass


_ALWAYS_READABLE: list[int] = []


def _canned_link(transport: str, fc23: bool) -> Any:
    """A ModbusLink wired to an instant in-memory device (client-side cost only)."""
    from hil_sim.modbus_device import ModbusDevice
    from hil_sim.state import DeviceState
    from mrctl.io.modbus import ModbusLink, rtu_frame

    state = DeviceState()
    state.publish(Sample(1, 0.5, 0.01, 0.02, 3.0, 8, 0.5))
    dev = ModbusDevice(state)
    link = ModbusLink(transport, host="x", url="x", use_fc23=fc23, timeout_s=0.1)
    link._set_plan(fc23)  # noqa: SLF001 - bench builds the request templates to answer them
    responses = {}
    for tx in link._txs:  # noqa: SLF001
        req = bytes(tx.adu)
        if transport == "tcp":
            responses[tx.fc] = dev.handle_tcp_frame(req)
        else:
            pdu = req[1:-2]
            responses[tx.fc] = rtu_frame(1, dev.handle_pdu(pdu))
    if transport == "tcp":
        if not _ALWAYS_READABLE:
            r, w = os.pipe()
            os.write(w, b"x")
            _ALWAYS_READABLE[:] = [r, w]
        link._attach_transport(use_fc23=fc23, sock=_InstantSocket(responses))  # noqa: SLF001
    else:
        link._attach_transport(use_fc23=fc23, io=_InstantIO(responses))  # noqa: SLF001
    return link


def _modbus_client_cost(transport: str) -> Callable[[argparse.Namespace], dict[str, float]]:
    def cost(a: argparse.Namespace) -> dict[str, float]:
        from mrctl.io.modbus import crc16_modbus
        from mrctl.io.registers import default_register_map

        fc23 = a.fc23 != "off"
        link = _canned_link(transport, fc23)
        n = 20000
        what = "select on a ready fd" if transport == "tcp" else "no syscalls"
        out = {f"exchange_us hot (all client Python + {what})": _ti(lambda: link.exchange(0.5), n),
               "exchange_us paced p50 (same, once per 1 ms: cold caches)": _paced_p50(lambda: link.exchange(0.5), a)}
        rm = default_register_map()
        buf = bytearray(64)
        blk = rm.encode_read(Sample(1, 0.5, 0.01, 0.02, 3.0, 8, 0.5))[0]
        out["encode_write_into_us"] = _ti(lambda: rm.encode_write_into(buf, 20, 0.5, True, 50), n)
        out["decode_read_us"] = _ti(lambda: rm.decode_read(blk), n)
        if transport == "rtu":
            frame = bytes(31)
            out["crc16_31B_us"] = _ti(lambda: crc16_modbus(frame), n)
        if not fc23:
            return out
        try:  # the same FC23 encode/decode through pymodbus's PDU classes + framer, for comparison
            from pymodbus.framer import FramerRTU, FramerSocket
            from pymodbus.pdu import DecodePDU
            from pymodbus.pdu.register_message import ReadWriteMultipleRegistersRequest

            fr = (FramerSocket if transport == "tcp" else FramerRTU)(DecodePDU(False))
            resp = (link._io.sock if transport == "tcp" else link._io).responses[23]  # noqa: SLF001

            def pm_encode() -> bytes:
                return fr.buildFrame(ReadWriteMultipleRegistersRequest(
                    read_address=0, read_count=13, write_address=16, write_registers=[1, 2, 3, 4], dev_id=1))

            out["pymodbus_encode_fc23_us"] = _ti(pm_encode, n // 4)
            out["pymodbus_decode_fc23_us"] = _ti(lambda: fr.handleFrame(resp, 1, 0), n // 4)
        except Exception as e:  # noqa: BLE001 - comparison only
            out["pymodbus_compare_error"] = str(e)  # type: ignore[assignment]
        return out

    return cost


def _modbus_server_cost(transport: str) -> Callable[[argparse.Namespace], dict[str, float]]:
    def cost(a: argparse.Namespace) -> dict[str, float]:
        from hil_sim.modbus_device import ModbusDevice
        from hil_sim.state import DeviceState
        from mrctl.io.modbus import mbap_frame, read_write_request_pdu, rtu_frame
        from mrctl.io.registers import default_register_map

        rm = default_register_map()
        state = DeviceState()
        state.publish(Sample(1, 0.5, 0.01, 0.02, 3.0, 8, 0.5))
        dev = ModbusDevice(state, rm)
        pdu = read_write_request_pdu(0, 13, 16, rm.encode_write(0.5, True, 50))
        if transport == "tcp":
            frame = mbap_frame(1, 1, pdu)
            fn = lambda: dev.handle_tcp_frame(frame)  # noqa: E731
        else:
            frame = rtu_frame(1, pdu)
            fn = lambda: dev.handle_rtu_frame(frame)  # noqa: E731
        return {"hot": _ti(fn, 20000), "paced p50": _paced_p50(fn, a)}

    return cost


def _floor_tcp(a: argparse.Namespace, n: int) -> list[float]:
    import select
    import socket

    dev = start_process(["--serve", "echo-tcp", "--reply-bytes", "35"])
    try:
        port = int(dev.ready.rsplit(":", 1)[1])
        s = socket.create_connection(("127.0.0.1", port))
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.setblocking(False)
        req = bytes(27)
        out = []
        for _ in _paced(n, a.rate):
            t0 = time.perf_counter()
            s.send(req)
            got = 0
            while got < 35:
                select.select([s], [], [], 1.0)
                got += len(s.recv(4096))
            out.append(time.perf_counter() - t0)
        s.close()
        return out
    finally:
        dev.stop()


def _floor_pty(a: argparse.Namespace, n: int) -> list[float]:
    import select

    master, slave, path = _pty_pair()
    dev = start_process(["--serve", "echo-pty", "--path", path, "--reply-bytes", "31"])
    dev.keep += [master, slave]
    try:
        out = []
        for _ in _paced(n, a.rate):
            t0 = time.perf_counter()
            os.write(master, bytes(21))
            got = 0
            while got < 31:
                select.select([master], [], [], 1.0)
                got += len(os.read(master, 4096))
            out.append(time.perf_counter() - t0)
        return out
    finally:
        dev.stop()


def _serial_start(a: argparse.Namespace) -> tuple[Device, Any]:
    """The framed binary protocol (mrctl.io.serial) against ``python -m hil_sim --transport serial``."""
    from mrctl.io.serial import SerialLink

    if a.device != "hil_sim":
        raise SystemExit("--transport serial is served by hil_sim only: use --device hil_sim")
    dev = start_hil_sim("serial", a)
    return dev, SerialLink(dev.field("link"), a.baud, timeout_s=a.timeout_ms * 1e-3,  # type: ignore[attr-defined]
                           spin_wait=a.client_wait == "spin")


def _serial_client_cost(a: argparse.Namespace) -> dict[str, float]:
    from mrctl.io.protocol import FrameDecoder, SetpointEncoder, encode_sample

    enc = SetpointEncoder()
    dec = FrameDecoder()
    frame = encode_sample(1, 1, 1000, 0.01, 0.02, 3.0, 0.5, 8)
    n = 20000
    return {"encode_setpoint_us": _ti(lambda: enc.encode(1, 0.5), n),
            "decode_sample_us (FrameDecoder.feed)": _ti(lambda: dec.feed(frame), n)}


TRANSPORTS: dict[str, Transport] = {
    "modbus-tcp": Transport(_modbus_tcp_start, _modbus_client_cost("tcp"), _modbus_server_cost("tcp"), _floor_tcp),
    "modbus-rtu": Transport(_modbus_rtu_start, _modbus_client_cost("rtu"), _modbus_server_cost("rtu"), _floor_pty),
    "serial": Transport(_serial_start, _serial_client_cost, lambda a: {}, _floor_pty),
}


# ----------------------------------------------------------------------------- measuring
def _ti(fn: Callable[[], object], n: int) -> float:
    """Best of 5 timeit runs, µs per call."""
    return min(timeit.repeat(fn, number=n, repeat=5)) / n * 1e6


def _paced_p50(fn: Callable[[], object], a: argparse.Namespace, n: int = 1000) -> float:
    """p50 µs of fn() called once per period: what the code costs after a sleep
    (caches, TLB and branch predictors cold, CPU maybe clocked down)."""
    d = []
    clock = time.perf_counter
    for _ in _paced(n, a.rate):
        t0 = clock()
        fn()
        d.append(clock() - t0)
    d.sort()
    return d[len(d) // 2] * 1e6


def _paced(n: int, rate_hz: float):
    """Yield n times at ~rate_hz (sleep most of the gap, spin the last 200 µs)."""
    period = 1.0 / rate_hz
    t_next = time.perf_counter()
    for k in range(n):
        t_next += period
        yield k
        while True:
            d = t_next - time.perf_counter()
            if d <= 0:
                break
            if d > 300e-6:
                time.sleep(d - 200e-6)


def percentiles_us(xs: list[float]) -> dict[str, float]:
    if not xs:
        return {}
    s = sorted(xs)
    n = len(s)

    def p(q: float) -> float:
        return s[min(n - 1, int(q * n))] * 1e6

    return {"n": n, "p50": p(0.50), "p99": p(0.99), "p99.9": p(0.999), "max": s[-1] * 1e6,
            "mean": sum(s) / n * 1e6}


def run_transport(name: str, a: argparse.Namespace) -> dict[str, Any]:
    tr = TRANSPORTS[name]
    dev, link = tr.start(a)
    res: dict[str, Any] = {"transport": name, "device": a.device, "ready": dev.ready}
    durs: list[float] = []
    errors: dict[str, int] = {}
    try:
        link.open()
        res["link"] = link.describe()
        for _ in range(min(200, a.n // 10)):  # warm-up
            try:
                link.exchange(0.5)
            except LinkError:
                pass
        clock = time.perf_counter
        for k in _paced(a.n, a.rate):
            t0 = clock()
            try:
                link.exchange(0.5 + 1e-4 * (k % 100))
            except LinkError as e:
                errors[type(e).__name__] = errors.get(type(e).__name__, 0) + 1
                if not link.is_open:
                    link.open()
                continue
            durs.append(clock() - t0)
        res["counters"] = link.counters() if hasattr(link, "counters") else {}
    finally:
        try:
            link.close()
        finally:
            dev.stop()
    res["roundtrip_us"] = percentiles_us(durs)
    res["errors"] = errors
    res["client"] = a.client
    res["client_us"] = tr.client_cost_us(a) if a.client == "mrctl" else {}
    res["server_us"] = tr.server_cost_us(a)
    if not a.no_floor:
        res["floor_us"] = percentiles_us(tr.floor(a, min(a.n, 3000)))
    return res


def _fmt(res: dict[str, Any]) -> str:
    rt = res["roundtrip_us"]
    lines = [f"== {res['transport']} ({res['client']} client, device: {res['device']}): {res.get('link', '')}"]
    if rt:
        lines.append(
            f"   exchange  p50 {rt['p50']:.0f}  p99 {rt['p99']:.0f}  p99.9 {rt['p99.9']:.0f}  "
            f"max {rt['max']:.0f} µs   (n={rt['n']}, errors {res['errors'] or 0})"
        )
    fl = res.get("floor_us")
    if fl:
        lines.append(f"   raw ping-pong floor (same channel, trivial echo process)  p50 {fl['p50']:.0f}  "
                     f"p99 {fl['p99']:.0f}  max {fl['max']:.0f} µs")
    if res["client_us"]:
        lines.append("   client-side Python per exchange (timeit, instant fake device):")
    for k, v in res["client_us"].items():
        lines.append(f"     {k:55s} {v:7.2f} µs" if isinstance(v, float) else f"     {k}: {v}")
    if res["server_us"]:
        sv = res["server_us"]
        lines.append(f"   device request handling: hot {sv['hot']:.2f} µs, paced p50 {sv['paced p50']:.1f} µs")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--serve" in argv:
        serve_main(argv)
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--transport", choices=list(TRANSPORTS), action="append",
                    help="repeatable; default modbus-tcp and modbus-rtu")
    ap.add_argument("-n", type=int, default=5000, help="exchanges per transport (default 5000)")
    ap.add_argument("--rate", type=float, default=1000.0, help="exchanges per second (default 1000)")
    ap.add_argument("--fc23", choices=["auto", "on", "off"], default="auto")
    ap.add_argument("--device-no-fc23", action="store_true", help="device rejects FC23 (client falls back)")
    ap.add_argument("--baud", type=int, default=921600, help="RTU baud (a pty ignores it)")
    ap.add_argument("--timeout-ms", type=float, default=5.0,
                    help="per-exchange deadline (generous: we measure, not police)")
    ap.add_argument("--device", choices=["process", "hil_sim", "thread"], default="process",
                    help="process: serve_modbus_* in a subprocess with a light 1 kHz sample publisher "
                         "(default); hil_sim: python -m hil_sim (plant clock spinning, as in HIL tests); "
                         "thread: in this process (shares the GIL: worse)")
    ap.add_argument("--hil-serve", choices=["inline", "thread"], default="inline",
                    help="with --device hil_sim: how it serves the link (its --serve; "
                         "inline = from the spinning clock thread, the default)")
    ap.add_argument("--client-wait", choices=["spin", "sleep"], default="spin",
                    help="mrctl client: poll for the reply (spin_wait, the default) or sleep in select()")
    ap.add_argument("--client", choices=["mrctl", "pymodbus"], default="mrctl",
                    help="pymodbus = its synchronous client, for comparison")
    ap.add_argument("--no-floor", action="store_true", help="skip the raw ping-pong baseline")
    ap.add_argument("--json", help="write results here")
    a = ap.parse_args(argv)
    results = []
    for name in a.transport or ["modbus-tcp", "modbus-rtu"]:
        res = run_transport(name, a)
        print(_fmt(res), flush=True)
        results.append(res)
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
