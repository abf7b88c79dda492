"""The simulated bench as a Modbus slave: TCP (many clients) and RTU (a tty).

Reads serve ``state.latest_sample()`` encoded by the register map; writes to
the setpoint block call ``state.set_setpoint(current_A, enable)``.

Why not pymodbus's server: measured here at ~0.5 ms p50 / ~1.7 ms p99 per
FC23 request on loopback (asyncio, datastore layers, logging); the 1 kHz
loop needs the device side well under 100 µs. The lean loops below decode
MBAP/RTU and the four function codes we need (FC3, FC4, FC16, FC23) with
``struct``; everything else gets ILLEGAL_FUNCTION. The request every mrctl
tick sends (FC23 over exactly the map's blocks) takes a fast path: ~5-8 µs
of Python hot, ~30 µs when called once per millisecond (cold caches).
pymodbus's client and ``mbpoll`` talk to it (tests/test_modbus.py).

Setpoints: every accepted write (FC16 or FC23) calls ``state.set_setpoint(
current, enable, watchdog_ms=..., clear_faults=...)`` with the write block's
current values: ``enable`` register bit 0 = ENABLE, bit 1 = CLEAR_FAULTS
(the serial protocol's SetpointFlag bits); no enable register → enabled;
``watchdog_ms`` 0 or unmapped → the bench's default watchdog.

Addressing: each table answers reads anywhere inside the span of its mapped
registers (gaps read 0, the holding span includes the setpoint block, which
reads back what was last written); outside → ILLEGAL_DATA_ADDRESS. Writes
must stay inside the write block; a non-finite setpoint → ILLEGAL_DATA_VALUE
(not applied). FC23 writes before it reads (Modbus spec).

Unit ids: TCP answers the map's unit id, 0 and 255 (the "not used" value
for direct TCP devices), other units get GATEWAY_NO_RESPONSE (0x0B). RTU
answers its own unit id only; unit 0 is broadcast (writes applied, no reply).
"""

from __future__ import annotations

import os
import random
import select
import socket
import struct
import threading
import time
from collections import deque
from typing import Any, Callable, NamedTuple

from hil_sim.faults import FaultBit
from hil_sim.state import DeviceState, OwedReply
from mrctl.io.base import FrameError
from mrctl.io.modbus import (
    FC_READ_HOLDING,
    FC_READ_INPUT,
    FC_READ_WRITE,
    FC_WRITE_MULTIPLE,
    crc16_modbus,
    open_serial_port,
)
from mrctl.io.registers import RegisterMap
from mrctl.io.registers import default_register_map as _default_register_map

__all__ = [
    "default_register_map",
    "ModbusDevice",
    "serve_modbus_tcp",
    "ModbusTcpInline",
    "serve_modbus_tcp_inline",
    "serve_modbus_rtu",
    "mbap_frame_length",
    "rtu_request_length",
    "rtu_feed",
    "ILLEGAL_FUNCTION",
    "ILLEGAL_DATA_ADDRESS",
    "ILLEGAL_DATA_VALUE",
    "GATEWAY_NO_RESPONSE",
]

ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03
GATEWAY_NO_RESPONSE = 0x0B

_HHB = struct.Struct(">HHB")
_HH = struct.Struct(">HH")
_RW = struct.Struct(">HHHHB")
_RW_FULL = struct.Struct(">BHHHHB")
_MBAP = struct.Struct(">HHHB")
_MAX_CLIENTS = 16
_POLL_S = 0.05  # how often idle loops look at ``stop``
_FAULT_POLL_S = 0.001  # ... and at the fault bits, when faults are scheduled
SLAVE_DEVICE_FAILURE = 0x04

_DROP = int(FaultBit.DROP_REPLIES)
_DELAY = int(FaultBit.DELAY_REPLIES)
_CORRUPT = int(FaultBit.CORRUPT_CRC)
_GARBAGE = int(FaultBit.GARBAGE)
_EXCEPTION = int(FaultBit.MODBUS_EXCEPTION)
_DISCONNECT = int(FaultBit.DISCONNECT)
_IGNORE = int(FaultBit.IGNORE_WRITES)
_REPLY_FAULTS = _DROP | _DELAY | _CORRUPT | _GARBAGE


def default_register_map() -> RegisterMap:
    """The map hil_sim serves unless told otherwise (docs/registers.md)."""
    return _default_register_map()


def mbap_frame_length(buf: bytes | bytearray) -> int:
    """Total length of the MBAP frame at the start of ``buf``; 0 = need more bytes.

    Raises :class:`FrameError` for an impossible header (protocol id ≠ 0,
    length < 2 or > 254): the stream can't be resynchronised, drop the
    connection. Never raises anything else.
    """
    if len(buf) < 6:
        return 0
    pid = buf[2] << 8 | buf[3]
    length = buf[4] << 8 | buf[5]
    if pid != 0:
        raise FrameError(f"MBAP protocol id {pid}, expected 0")
    if not 2 <= length <= 254:
        raise FrameError(f"MBAP length {length} out of range 2..254")
    total = 6 + length
    return total if len(buf) >= total else 0


def rtu_request_length(buf: bytes | bytearray) -> int | None:
    """Length of the RTU request at the start of ``buf``.

    None = need more bytes; -1 = unknown function code, delimit it by line
    silence. Never raises.
    """
    n = len(buf)
    if n < 2:
        return None
    fc = buf[1]
    if fc in (1, 2, 3, 4, 5, 6):
        return 8
    if fc == FC_WRITE_MULTIPLE:
        return 9 + buf[6] if n >= 7 else None
    if fc == FC_READ_WRITE:
        return 13 + buf[10] if n >= 11 else None
    return -1


class Deferred(NamedTuple):
    """A reply to a SYNC request: sent by the clock after the tick that
    applies its setpoint (``owed``), built then from that tick's sample."""

    owed: OwedReply
    build: Callable[[], bytes]


class ModbusDevice:
    """Register image + request handling shared by the TCP and RTU servers.

    ``fc23=False`` makes the device answer FC23 with ILLEGAL_FUNCTION (a
    device without it; the client then falls back to FC16 + FC3/FC4).
    Thread-safe: TCP connections share one device.
    """

    def __init__(self, state: DeviceState, register_map: RegisterMap | None = None, *, fc23: bool = True) -> None:
        self.state = state
        self.rmap = rmap = register_map if register_map is not None else _default_register_map()
        self.fc23 = fc23
        self.unit_id = rmap.unit_id
        self._lock = threading.Lock()
        self._local = threading.local()  # .owed: the OwedReply of the request being handled
        self._spans = rmap.spans()
        self._read_blocks = list(rmap.read_blocks)
        wb = rmap.write_block
        self._wb = (wb.address, wb.end)
        self._write_regs = bytearray(rmap.encode_write(0.0, False, 0))
        # Fast path for the request every mrctl tick sends: FC23 writing the
        # whole write block and reading exactly the (single, holding) read
        # block. At 1 kHz with cold caches the generic path costs ~40 µs of
        # Python per request here; this one skips the parsing and checks that
        # the header comparison already proves.
        self._fast_hdr = b""
        self._fast_len = -1
        self._fast_resp = b""
        if rmap.fc23_capable:
            rb = rmap.read_blocks[0]
            self._fast_hdr = _RW_FULL.pack(FC_READ_WRITE, rb.address, rb.count, wb.address, wb.count, 2 * wb.count)
            self._fast_len = len(self._fast_hdr) + 2 * wb.count
            self._fast_resp = bytes((FC_READ_WRITE, 2 * rb.count))
        # counters
        self.requests = 0
        self.exceptions = 0
        self.setpoints = 0
        self.frames_dropped = 0  #: RTU frames with a bad CRC given whole, bad MBAP headers
        self.crc_errors = 0  #: RTU candidates failing their CRC while hunting
        self.bytes_discarded = 0  #: RTU junk bytes skipped
        self.watchdog_ms: float | None = None  #: last written watchdog (passed to the bench's clock)
        self._rng = random.Random(0)
        self.fault_counts = {"requests_ignored": 0, "exceptions_injected": 0, "replies_dropped": 0,
                             "replies_delayed": 0, "replies_corrupted": 0, "garbage_bytes": 0,
                             "disconnects": 0, "connections_refused": 0}

    def counters(self) -> dict[str, Any]:
        return {"requests": self.requests, "exceptions": self.exceptions, "setpoints": self.setpoints,
                "frames_dropped": self.frames_dropped, "crc_errors": self.crc_errors,
                "bytes_discarded": self.bytes_discarded, "faults": dict(self.fault_counts)}

    # -- faults (hil_sim/faults.py) -------------------------------------------------
    def _fault_pdu(self, pdu: bytes | bytearray | memoryview, fbits: int) -> bytes | None:
        """Request-side faults: None = ignore the request (no reply, nothing applied),
        else the exception reply. Called only while a fault bit is set."""
        if fbits & _IGNORE:
            self.fault_counts["requests_ignored"] += 1
            return None
        self.fault_counts["exceptions_injected"] += 1
        return self._exc(pdu[0] if len(pdu) else 0, SLAVE_DEVICE_FAILURE)

    def fault_reply(self, adu: bytes, tcp: bool) -> tuple[bytes | None, float]:
        """Reply-side faults for one response ADU: (bytes to send or None, delay s)."""
        fbits = self.state.fault_bits
        if not fbits & _REPLY_FAULTS:
            return adu, 0.0
        fc = self.fault_counts
        if fbits & _DROP:
            fc["replies_dropped"] += 1
            return None, 0.0
        faults = self.state.faults
        if fbits & _CORRUPT:
            fc["replies_corrupted"] += 1
            if tcp:  # an impossible MBAP length: the client must resynchronise
                adu = adu[:4] + b"\x00\x00" + adu[6:]
            else:  # RTU: flip the CRC's high byte
                adu = adu[:-1] + bytes((adu[-1] ^ 0xFF,))
        if fbits & _GARBAGE:
            n = int(faults.param(_GARBAGE, "n_bytes") or 16) if faults is not None else 16
            adu = self._rng.randbytes(n) + adu
            fc["garbage_bytes"] += n
        delay = 0.0
        if fbits & _DELAY:
            delay = float(faults.param(_DELAY, "delay_s") or 0.0) if faults is not None else 0.0
            fc["replies_delayed"] += 1
        return adu, delay

    def reply_now(self, adu: bytes, tcp: bool, delayed: deque) -> bytes | None:
        """One response through the reply faults: the bytes to send now, or
        None (dropped, or queued on ``delayed`` as (due monotonic s, bytes);
        while anything is queued, later replies queue behind it, in order)."""
        if not (self.state.fault_bits & _REPLY_FAULTS or delayed):
            return adu
        out, delay = self.fault_reply(adu, tcp)
        if out is None:
            return None
        if delay > 0 or delayed:
            due = time.monotonic() + delay
            if delayed and delayed[-1][0] > due:
                due = delayed[-1][0]  # FIFO
            delayed.append((due, out))
            return None
        return out

    # -- PDU level ---------------------------------------------------------------
    def handle_pdu(self, pdu: bytes | bytearray | memoryview) -> bytes | None:
        """Response PDU for a request PDU; None only for an empty PDU. Never raises."""
        if len(pdu) < 1:
            return None
        self.requests += 1
        fc = pdu[0]
        if self.fc23 and len(pdu) == self._fast_len and pdu[:10] == self._fast_hdr:
            data = pdu[10:]
            w = self.rmap.decode_write(data)
            I = w.current_setpoint_A
            if I - I == 0.0:
                with self._lock:
                    self._write_regs[:] = data
                    self._apply(w)
                return self._fast_resp + self.rmap.encode_sample(self.state.latest_sample())[0]
        try:
            if fc == FC_READ_HOLDING or fc == FC_READ_INPUT:
                if len(pdu) != 5:
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                address, count = _HH.unpack_from(pdu, 1)
                if not 1 <= count <= 125:
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                table = "holding" if fc == FC_READ_HOLDING else "input"
                data = self._read(table, address, count)
                if data is None:
                    return self._exc(fc, ILLEGAL_DATA_ADDRESS)
                return bytes((fc, 2 * count)) + data
            if fc == FC_WRITE_MULTIPLE:
                if len(pdu) < 6:
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                address, count, bc = _HHB.unpack_from(pdu, 1)
                if not 1 <= count <= 123 or bc != 2 * count or len(pdu) != 6 + bc:
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                if not self._writable(address, count):
                    return self._exc(fc, ILLEGAL_DATA_ADDRESS)
                if not self._write(address, pdu[6:]):
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                return bytes(pdu[:5])
            if fc == FC_READ_WRITE and self.fc23:
                if len(pdu) < 10:
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                ra, rc, wa, wc, bc = _RW.unpack_from(pdu, 1)
                if not 1 <= rc <= 125 or not 1 <= wc <= 121 or bc != 2 * wc or len(pdu) != 10 + bc:
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                if not self._writable(wa, wc) or not self._readable("holding", ra, rc):
                    return self._exc(fc, ILLEGAL_DATA_ADDRESS)
                if not self._write(wa, pdu[10:]):
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                data = self._read("holding", ra, rc)
                assert data is not None
                return bytes((fc, 2 * rc)) + data
            return self._exc(fc, ILLEGAL_FUNCTION)
        except Exception:  # noqa: BLE001 - a device must answer, not die (DEVICE_FAILURE)
            return self._exc(fc, 0x04)

    def _exc(self, fc: int, code: int) -> bytes:
        self.exceptions += 1
        return bytes(((fc | 0x80) & 0xFF, code))

    def _readable(self, table: str, address: int, count: int) -> bool:
        span = self._spans.get(table)
        return span is not None and span[0] <= address and address + count <= span[1]

    def _writable(self, address: int, count: int) -> bool:
        return self._wb[0] <= address and address + count <= self._wb[1]

    def _read(self, table: str, address: int, count: int) -> bytes | None:
        if not self._readable(table, address, count):
            return None
        blocks = self.rmap.encode_sample(self.state.latest_sample())
        for b, data in zip(self._read_blocks, blocks):
            if b.table == table and b.address == address and b.count == count:
                return data  # the client's own block: no image to assemble
        start, end = self._spans[table]
        image = bytearray(2 * (end - start))
        for b, data in zip(self._read_blocks, blocks):
            if b.table == table:
                image[2 * (b.address - start) : 2 * (b.end - start)] = data
        if table == "holding":
            with self._lock:
                image[2 * (self._wb[0] - start) : 2 * (self._wb[1] - start)] = self._write_regs
        return bytes(image[2 * (address - start) : 2 * (address + count - start)])

    def _write(self, address: int, data: bytes | bytearray | memoryview) -> bool:
        off = 2 * (address - self._wb[0])
        with self._lock:
            old = bytes(self._write_regs)
            self._write_regs[off : off + len(data)] = data
            w = self.rmap.decode_write(self._write_regs)
            I = w.current_setpoint_A
            if not I - I == 0.0:  # NaN/inf: reject, keep the old value
                self._write_regs[:] = old
                return False
            self._apply(w)
        return True

    def _apply(self, w: Any) -> None:
        """Hand a (finite) setpoint to the bench; caller holds the lock.
        With SYNC (bit 2 of enable) the reply is owed until the clock's next
        tick: the ADU layer picks the :class:`OwedReply` up from ``_local``."""
        self.setpoints += 1
        wd = w.watchdog_ms
        self.watchdog_ms = wd
        owed = None
        if w.sync:
            owed = self._local.owed = OwedReply()
        self.state.set_setpoint(
            w.current_setpoint_A,
            True if w.enable is None else w.enable,
            watchdog_ms=int(wd) if wd is not None and wd > 0 else 0,
            clear_faults=w.clear_faults,
            owe=owed,
        )

    def _take_owed(self, pdu: bytes | bytearray | memoryview, resp: bytes | None,
                   wrap: Callable[[bytes], bytes]) -> Deferred | None:
        """If the request just handled set SYNC and succeeded: its reply,
        rebuilt from the sample of the tick that applies it, to be sent by the
        clock thread. Always clears the thread's owed reply, so it can never
        be taken by a later request."""
        owed = getattr(self._local, "owed", None)
        self._local.owed = None
        if owed is None or resp is None or resp[0] & 0x80:
            return None
        req = bytes(pdu)
        fc = req[0]

        def build() -> bytes:
            if fc == FC_READ_WRITE:
                ra, rc = _HH.unpack_from(req, 1)
                data = self._read("holding", ra, rc)
                return wrap(bytes((fc, 2 * rc)) + (data or b""))
            return wrap(req[:5])  # FC16: the echo

        return Deferred(owed, build)

    # -- ADU level -----------------------------------------------------------------
    def handle_tcp_frame(self, frame: bytes | bytearray) -> bytes | None:
        """Response ADU for one complete MBAP frame (see :func:`mbap_frame_length`). Never raises."""
        if len(frame) < 8:
            return None
        tid, _pid, _length, unit = _MBAP.unpack_from(frame, 0)
        if unit != self.unit_id and unit not in (0, 255):
            resp: bytes | None = self._exc(frame[7], GATEWAY_NO_RESPONSE)
        elif self.state.fault_bits & (_IGNORE | _EXCEPTION):
            resp = self._fault_pdu(memoryview(frame)[7:], self.state.fault_bits)
        else:
            resp = self.handle_pdu(memoryview(frame)[7:])
            d = self._take_owed(memoryview(frame)[7:], resp, lambda r: _MBAP.pack(tid, 0, len(r) + 1, unit) + r)
            if d is not None:
                return d  # type: ignore[return-value]
        if resp is None:
            return None
        return _MBAP.pack(tid, 0, len(resp) + 1, unit) + resp

    def handle_rtu_frame(self, frame: bytes | bytearray) -> bytes | None:
        """Response ADU for one RTU frame; None = no reply (CRC, other unit, broadcast). Never raises."""
        n = len(frame)
        if n < 4:
            self.frames_dropped += 1
            return None
        if crc16_modbus(memoryview(frame)[: n - 2]) != frame[n - 2] | frame[n - 1] << 8:
            self.frames_dropped += 1
            return None
        unit = frame[0]
        if unit != self.unit_id and unit != 0:
            return None
        if self.state.fault_bits & (_IGNORE | _EXCEPTION):
            resp = self._fault_pdu(memoryview(frame)[1 : n - 2], self.state.fault_bits)
        else:
            resp = self.handle_pdu(memoryview(frame)[1 : n - 2])

            def wrap(r: bytes, unit: int = unit) -> bytes:
                body = bytes((unit,)) + r
                return body + crc16_modbus(body).to_bytes(2, "little")

            d = self._take_owed(memoryview(frame)[1 : n - 2], resp if unit != 0 else None, wrap)
            if d is not None:
                return d  # type: ignore[return-value]
        if resp is None or unit == 0:
            return None
        body = bytes((unit,)) + resp
        return body + crc16_modbus(body).to_bytes(2, "little")


# --------------------------------------------------------------------------
# TCP
def serve_modbus_tcp(
    state: DeviceState,
    host: str,
    port: int,
    register_map: RegisterMap | None,
    stop: threading.Event,
    ready: Callable[[str], None] | None = None,
    *,
    fc23: bool = True,
    max_clients: int = _MAX_CLIENTS,
    on_device: Callable[[ModbusDevice], None] | None = None,
) -> None:
    """Serve Modbus TCP on (host, port) until ``stop`` is set.

    ``port`` 0 picks a free port; ``ready`` gets ``"modbus-tcp HOST:PORT"``
    with the real port once listening. One thread per connection (mbpoll can
    poll alongside the loop); at most ``max_clients`` at once, further
    connections are closed on accept. On stop every connection is closed
    (clients see Disconnected) before returning.

    The ``disconnect`` fault closes every client connection and the listening
    socket (new connections are refused) until the window ends, then listens
    again on the same port.
    """
    dev = ModbusDevice(state, register_map, fc23=fc23)
    if on_device is not None:
        on_device(dev)
    poll_s = _FAULT_POLL_S if state.faults else _POLL_S
    lsock: socket.socket | None = socket.create_server((host, port))
    lsock.settimeout(poll_s)
    actual = lsock.getsockname()[1]
    conns: dict[threading.Thread, socket.socket] = {}

    def drop_all() -> None:
        for t, conn in conns.items():
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for t in conns:
            t.join(1.0)
        conns.clear()

    try:
        if ready is not None:
            ready(f"modbus-tcp {host}:{actual}")
        while not stop.is_set():
            if state.fault_bits & _DISCONNECT:
                if lsock is not None:
                    dev.fault_counts["disconnects"] += 1
                    lsock.close()
                    lsock = None
                    drop_all()
                stop.wait(_FAULT_POLL_S)
                continue
            if lsock is None:  # the disconnect window is over: listen again
                lsock = socket.create_server((host, actual))
                lsock.settimeout(poll_s)
            try:
                conn, _addr = lsock.accept()
            except (socket.timeout, InterruptedError):
                continue
            except OSError:
                if stop.is_set():
                    break
                raise
            for t in [t for t in conns if not t.is_alive()]:
                del conns[t]
            if len(conns) >= max_clients:
                conn.close()
                continue
            t = threading.Thread(target=_tcp_connection, args=(dev, conn, stop), name="modbus-tcp-conn", daemon=True)
            conns[t] = conn
            t.start()
    finally:
        if lsock is not None:
            lsock.close()
        drop_all()


def _tcp_connection(dev: ModbusDevice, conn: socket.socket, stop: threading.Event) -> None:
    state = dev.state
    delayed: deque[tuple[float, bytes]] = deque()  # (due monotonic s, bytes): delay_replies
    try:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        poll_s = _FAULT_POLL_S if state.faults else _POLL_S
        conn.settimeout(poll_s)
        buf = bytearray()
        while not stop.is_set():
            if state.fault_bits & _DISCONNECT:
                return  # the listener closes the rest
            if delayed:
                now = time.monotonic()
                while delayed and delayed[0][0] <= now:
                    conn.sendall(delayed.popleft()[1])
                conn.settimeout(max(1e-4, min(poll_s, delayed[0][0] - now)) if delayed else poll_s)
            try:
                chunk = conn.recv(4096)
            except socket.timeout:
                continue
            if not chunk:
                return
            buf += chunk
            while True:
                try:
                    total = mbap_frame_length(buf)
                except FrameError:
                    dev.frames_dropped += 1
                    return  # unsynchronisable stream: drop the connection
                if not total:
                    break
                frame = bytes(buf[:total])
                del buf[:total]
                resp = dev.handle_tcp_frame(frame)
                if resp is None:
                    continue
                if isinstance(resp, Deferred):  # SYNC: the clock sends it after its tick
                    resp.owed.attach(lambda r=resp: conn.sendall(r.build()))
                    continue
                out = dev.reply_now(resp, True, delayed)
                if out is not None:
                    conn.sendall(out)
                elif delayed:
                    conn.settimeout(max(1e-4, min(poll_s, delayed[0][0] - time.monotonic())))
    except OSError:
        return
    finally:
        try:
            conn.close()
        except OSError:
            pass



class ModbusTcpInline:
    """Modbus TCP served from the clock thread's spin phase (``--serve inline``).

    The threaded server answers each request only once its connection thread
    has woken up and taken the GIL from the spinning clock; on this VM that
    often took longer than the rest of the period, so a device-paced (SYNC)
    request missed its tick (docs/performance.md). Here the clock itself
    polls the listening socket and every connection (one ``poll(0)`` system
    call per pass), parses, answers, and sends SYNC replies right after the
    tick that applies them: no thread hand-off anywhere.

    Same behaviour as :func:`serve_modbus_tcp` otherwise: up to
    ``max_clients`` connections, reply faults (drop, delay, corrupt,
    garbage), the ``disconnect`` window (all connections and the listener
    closed, then listening again on the same port). A client that does not
    read its replies (socket buffer full) is disconnected, since the clock
    must never block on it.
    """

    def __init__(self, state: DeviceState, host: str, port: int, register_map: RegisterMap | None = None,
                 *, fc23: bool = True, max_clients: int = _MAX_CLIENTS) -> None:
        self.dev = ModbusDevice(state, register_map, fc23=fc23)
        self.state = state
        self.host = host
        self.max_clients = max_clients
        self._poller = select.poll()
        self._lsock: socket.socket | None = None
        self.port = port
        self._listen()
        self.port = self._lsock.getsockname()[1]  # type: ignore[union-attr]
        #: fd -> [socket, receive buffer, delayed replies deque[(due monotonic s, bytes)]]
        self._conns: dict[int, list[Any]] = {}
        self._n_delayed = 0
        self._down = False  # inside a disconnect window

    def _listen(self) -> None:
        s = socket.create_server((self.host, self.port))
        s.setblocking(False)
        self._lsock = s
        self._poller.register(s.fileno(), select.POLLIN)

    def poll_once(self) -> None:
        """Serve whatever has arrived, without blocking. Never raises for a
        client's doing (a bad stream or a dead peer closes that connection)."""
        fbits = self.state.fault_bits
        if fbits & _DISCONNECT or self._down:
            if self._disconnect_window(fbits):
                return
        if self._n_delayed:
            self._flush_delayed()
        lsock = self._lsock
        lfd = lsock.fileno() if lsock is not None else -1
        for fd, ev in self._poller.poll(0):
            if fd == lfd:
                self._accept()
            else:
                self._receive(fd)

    def _disconnect_window(self, fbits: int) -> bool:
        """Close everything when the window opens, listen again when it ends;
        True = no link right now."""
        if fbits & _DISCONNECT:
            if not self._down:
                self._down = True
                self.dev.fault_counts["disconnects"] += 1
                for fd in list(self._conns):
                    self._drop(fd)
                if self._lsock is not None:
                    self._poller.unregister(self._lsock.fileno())
                    self._lsock.close()
                    self._lsock = None
            return True
        self._down = False
        self._listen()
        return False

    def _accept(self) -> None:
        assert self._lsock is not None
        while True:
            try:
                conn, _addr = self._lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # e.g. ECONNABORTED: the client gave up before we took it
            if len(self._conns) >= self.max_clients:
                conn.close()
                continue
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conns[conn.fileno()] = [conn, bytearray(), deque()]
            self._poller.register(conn.fileno(), select.POLLIN)

    def _drop(self, fd: int) -> None:
        c = self._conns.pop(fd, None)
        if c is None:
            return
        self._n_delayed -= len(c[2])
        try:
            self._poller.unregister(fd)
        except (KeyError, ValueError):
            pass
        try:
            c[0].close()
        except OSError:
            pass

    def _receive(self, fd: int) -> None:
        c = self._conns.get(fd)
        if c is None:
            return
        conn, buf = c[0], c[1]
        try:
            chunk = conn.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(fd)
            return
        if not chunk:
            self._drop(fd)
            return
        buf += chunk
        dev = self.dev
        while True:
            try:
                total = mbap_frame_length(buf)
            except FrameError:
                dev.frames_dropped += 1
                self._drop(fd)  # unsynchronisable stream: drop the connection
                return
            if not total:
                return
            frame = bytes(buf[:total])
            del buf[:total]
            resp = dev.handle_tcp_frame(frame)
            if resp is None:
                continue
            if isinstance(resp, Deferred):  # SYNC: the clock sends it after its tick
                resp.owed.attach(lambda fd=fd, r=resp: self._send(fd, r.build()))
                continue
            q = c[2]
            n_queued = len(q)
            out = dev.reply_now(resp, True, q)
            self._n_delayed += len(q) - n_queued
            if out is not None and not self._send(fd, out):
                return

    def _send(self, fd: int, data: bytes) -> bool:
        c = self._conns.get(fd)
        if c is None:
            return False  # the connection went away while the reply was owed
        try:
            n = c[0].send(data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError:
            self._drop(fd)
            return False
        if n != len(data):  # the client is not reading: it can't be waited for
            self._drop(fd)
            return False
        return True

    def _flush_delayed(self) -> None:
        now = time.monotonic()
        for fd in list(self._conns):
            q = self._conns[fd][2]
            while q and q[0][0] <= now:
                self._n_delayed -= 1
                if not self._send(fd, q.popleft()[1]):
                    break

    def close(self) -> None:
        """Close every connection (clients see Disconnected) and the listener."""
        for fd in list(self._conns):
            self._drop(fd)
        if self._lsock is not None:
            try:
                self._poller.unregister(self._lsock.fileno())
            except (KeyError, ValueError):
                pass
            self._lsock.close()
            self._lsock = None


def serve_modbus_tcp_inline(
    state: DeviceState,
    host: str,
    port: int,
    register_map: RegisterMap | None,
    stop: threading.Event,
    ready: Callable[[str], None] | None = None,
    *,
    fc23: bool = True,
    max_clients: int = _MAX_CLIENTS,
    on_device: Callable[[ModbusDevice], None] | None = None,
    pause_s: float = 1e-4,
) -> None:
    """:class:`ModbusTcpInline` polled in a loop until ``stop`` (a drop-in for
    :func:`serve_modbus_tcp`, for tests and benchmarks without a bench clock;
    ``pause_s`` between polls, 0 = spin a core as hil_sim's clock does)."""
    srv = ModbusTcpInline(state, host, port, register_map, fc23=fc23, max_clients=max_clients)
    if on_device is not None:
        on_device(srv.dev)
    try:
        if ready is not None:
            ready(f"modbus-tcp {host}:{srv.port}")
        poll = srv.poll_once
        while not stop.is_set():
            poll()
            if pause_s:
                time.sleep(pause_s)
    finally:
        srv.close()

# --------------------------------------------------------------------------
# RTU
def serve_modbus_rtu(
    state: DeviceState,
    port_path: str | int,
    baudrate: int,
    register_map: RegisterMap | None,
    stop: threading.Event,
    ready: Callable[[str], None] | None = None,
    *,
    fc23: bool = True,
    parity: str = "E",
    stopbits: float = 1,
    endpoint: Any = None,
    on_device: Callable[[ModbusDevice], None] | None = None,
) -> None:
    """Serve Modbus RTU on a tty until ``stop`` is set.

    ``endpoint``: the :class:`hil_sim.serial_device.PtyEndpoint` whose master fd
    ``port_path`` is; needed for the ``disconnect`` fault (pty hung up, then a
    new one linked at the same path).

    ``port_path``: a tty path (opened with pyserial at ``baudrate``, 8
    data bits, ``parity``/``stopbits``), or an open fd (int, e.g. a pty
    master; set non-blocking, not closed here). Requests are delimited by
    their known length (FC1-6, FC16, FC23; junk is hunted through, see
    :func:`rtu_feed`); other function codes by 3.5 characters of line
    silence (at least 1 ms, since ptys and USB adapters deliver bytes in
    bursts). If the tty goes away, serving stops
    and the call waits for ``stop``. On a pty (``/dev/pts/*``) a parity the
    kernel refuses on reopen falls back to N (see
    :func:`mrctl.io.modbus.open_serial_port`).
    """
    dev = ModbusDevice(state, register_map, fc23=fc23)
    if on_device is not None:
        on_device(dev)
    owner: Any = None
    if isinstance(port_path, int):
        fd = port_path
    else:
        owner = open_serial_port(port_path, baudrate=baudrate, parity=str(parity).upper(), stopbits=stopbits, timeout=0)
        fd = owner.fileno()
    os.set_blocking(fd, False)
    bits = 1 + 8 + (0 if str(parity).upper() == "N" else 1) + int(stopbits + 0.5)
    silence_s = max(3.5 * bits / baudrate, 1e-3)
    try:
        if ready is not None:
            ready(f"modbus-rtu {port_path} @ {baudrate} Bd")
        _rtu_loop(dev, fd, stop, silence_s, endpoint)
    finally:
        if owner is not None:
            try:
                owner.close()
            except Exception:  # noqa: BLE001
                pass
    stop.wait()


def _crc_ok(buf: bytes | bytearray, start: int, n: int) -> bool:
    end = start + n
    return crc16_modbus(memoryview(buf)[start : end - 2]) == buf[end - 2] | buf[end - 1] << 8


def _find_frame(buf: bytearray, start: int) -> int:
    """Index ≥ start of the first complete, CRC-valid, known-length request in buf, or -1."""
    n_buf = len(buf)
    for i in range(start, n_buf - 3):
        n = rtu_request_length(memoryview(buf)[i:])
        if n is not None and n > 0 and i + n <= n_buf and _crc_ok(buf, i, n):
            return i
    return -1


def rtu_feed(dev: ModbusDevice, buf: bytearray) -> list[bytes]:
    """Consume every complete request at the front of ``buf``; return the replies.

    Requests of known length are taken as soon as they are complete. A CRC
    failure drops one byte and hunts on (junk before a frame costs nothing
    but the junk); an incomplete candidate yields to a complete valid frame
    found further on (a false header can't hold back a real request). An
    unknown function code waits for line silence (the caller then passes the
    whole buffer to ``dev.handle_rtu_frame``), unless a valid known frame
    follows it. Never raises.
    """
    out: list[bytes] = []
    while len(buf) >= 4:
        n = rtu_request_length(buf)
        if n is None:
            break
        if n > 0:
            if len(buf) < n:
                j = _find_frame(buf, 1)
                if j < 0:
                    break  # wait for the rest
                dev.bytes_discarded += j
                del buf[:j]
                continue
            if _crc_ok(buf, 0, n):
                frame = bytes(buf[:n])
                del buf[:n]
                resp = dev.handle_rtu_frame(frame)
                if resp is not None:
                    out.append(resp)
                continue
            dev.crc_errors += 1
            dev.bytes_discarded += 1
            del buf[:1]
            continue
        j = _find_frame(buf, 1)  # unknown function code
        if j < 0:
            break
        dev.bytes_discarded += j
        del buf[:j]
    return out


def _rtu_loop(dev: ModbusDevice, fd: int, stop: threading.Event, silence_s: float, endpoint: Any = None) -> None:
    state = dev.state
    idle_s = _FAULT_POLL_S if state.faults else _POLL_S
    delayed: deque[tuple[float, bytes]] = deque()  # (due monotonic s, bytes): delay_replies
    buf = bytearray()

    def send(resp: bytes) -> bool:
        out = dev.reply_now(resp, False, delayed)
        return True if out is None else _write_all(fd, out)

    while not stop.is_set():
        if state.fault_bits & _DISCONNECT and endpoint is not None:
            dev.fault_counts["disconnects"] += 1
            delayed.clear()
            buf.clear()
            endpoint.hangup()
            while state.fault_bits & _DISCONNECT and not stop.is_set():
                stop.wait(_FAULT_POLL_S)
            if stop.is_set():
                return
            endpoint.reopen()
            fd = endpoint.master_fd
            continue
        wait = silence_s if buf else idle_s
        if delayed:
            now = time.monotonic()
            while delayed and delayed[0][0] <= now:
                if not _write_all(fd, delayed.popleft()[1]):
                    return
            if delayed:
                wait = max(1e-4, min(wait, delayed[0][0] - now))
        try:
            ready = select.select([fd], [], [], wait)[0]
            chunk = os.read(fd, 4096) if ready else None
        except BlockingIOError:
            continue
        except OSError:
            return  # tty gone (EIO: the other side of the pty closed)
        if ready and not chunk:
            return  # readable but empty: device gone
        if chunk:
            if state.fault_bits & _IGNORE:
                dev.fault_counts["requests_ignored"] += 1
                buf.clear()
                continue
            buf += chunk
            for resp in rtu_feed(dev, buf):
                if isinstance(resp, Deferred):  # SYNC: the clock sends it after its tick
                    resp.owed.attach(lambda r=resp: _write_all(fd, r.build()))
                    continue
                if not send(resp):
                    return
            if len(buf) > 1024:  # nothing valid in a whole kilobyte: start over
                dev.bytes_discarded += len(buf)
                buf.clear()
            continue
        if delayed and not ready:
            continue  # woke up for a delayed reply, not for line silence
        # Line silence: what's buffered is a whole frame of an unknown
        # function (→ ILLEGAL_FUNCTION if its CRC is good) or junk.
        if buf:
            resp = dev.handle_rtu_frame(bytes(buf)) if rtu_request_length(buf) == -1 else None
            if resp is not None:
                if not send(resp):
                    return
            else:
                dev.bytes_discarded += len(buf)
            buf.clear()


def _write_all(fd: int, data: bytes) -> bool:
    """Write everything; False if the tty is gone."""
    view = memoryview(data)
    try:
        while view:
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                select.select([], [fd], [], _POLL_S)
                continue
            view = view[n:]
    except OSError:
        return False
    return True
