"""ModbusLink: the loop's :class:`~mrctl.io.base.Link` over Modbus TCP or RTU.

One :meth:`ModbusLink.exchange` per tick writes the setpoint block and reads
the sample block(s) described by a :class:`~mrctl.io.registers.RegisterMap`:

* **FC23** (read/write multiple registers) when the map's read quantities
  are all holding registers: one request, one response per tick. The device
  performs the write before the read (Modbus spec), like the serial protocol.
* otherwise (or when the device rejects FC23) **FC16** write, then one
  **FC3/FC4** read per read block: two or more transactions per tick.

``use_fc23=None`` probes once at :meth:`~ModbusLink.open`: an FC23 with 0 A,
output disabled; an ILLEGAL_FUNCTION exception (or no answer at all) makes
the link fall back to FC16 + FC3/FC4 for good.

Why not pymodbus's clients on the hot path (numbers: docs/registers.md): the
synchronous serial client *sleeps* at least 1 ms twice per transaction to
detect end-of-frame silence (``ModbusSerialClient._wait_for_data``): ≥ 2 ms
per RTU transaction (measured p50 2.6 ms on a pty), so 1 kHz is impossible
with it. The synchronous TCP client works but costs ~60 µs more per FC23
than this module at p50 and its timeouts have millisecond granularity;
pymodbus's PDU objects + framer cost ~12-20 µs per FC23 (encode + decode)
against ~1.5 µs for the precompiled frames below. So this module frames
MBAP/RTU itself (the formats are tiny and fixed: every response length is
known in advance, so RTU reads exactly that many bytes), and keeps pymodbus
for what it is good at here: exception-code names
(:class:`pymodbus.constants.ExcCodes`) and, in the tests, the reference
encoder/decoder/CRC our bytes are checked against.

Error mapping, every exchange:

* nothing (valid) arrived by the deadline → :class:`LinkTimeout`
* bytes arrived but not a valid response: CRC, length, byte count, unit id,
  function code, MBAP protocol id, non-finite x/v/t → :class:`FrameError`
* Modbus exception response → :class:`DeviceError` (``code`` = exception
  code, message names it, e.g. ``ILLEGAL_FUNCTION``)
* connection refused/reset/closed by peer, tty gone → :class:`Disconnected`;
  the link drops the socket/port and :meth:`open` reconnects.

A TCP response with another transaction id (the late answer to a tick that
timed out) is discarded and counted (``stale_replies``); RTU has no
transaction id, so the input is flushed before every request (a late reply
can't shift later exchanges by one).
"""

from __future__ import annotations

import math
import os
import select
import socket
import struct
import time
from typing import Any, Mapping

from pymodbus.constants import ExcCodes

from mrctl.io.base import DeviceError, Disconnected, FrameError, LinkTimeout, Sample, Status, sleep_until_ns
from mrctl.io.base import network_device_key, serial_device_key  # device ownership (hardening)
from mrctl.io.registers import RegisterMap, default_register_map

__all__ = [
    "FC_READ_HOLDING",
    "FC_READ_INPUT",
    "FC_WRITE_MULTIPLE",
    "FC_READ_WRITE",
    "DEFAULT_TCP_PORT",
    "DEFAULT_RTU_BAUD",
    "DEFAULT_TCP_TIMEOUT_S",
    "DEFAULT_WATCHDOG_MS",
    "ModbusLink",
    "crc16_modbus",
    "exception_name",
    "read_request_pdu",
    "write_request_pdu",
    "read_write_request_pdu",
    "mbap_frame",
    "rtu_frame",
    "decode_response_pdu",
    "decode_tcp_response",
    "decode_rtu_response",
    "rtu_tick_frames",
    "rtu_transaction_wire_time_s",
    "rtu_bits_per_char",
    "default_rtu_timeout_s",
    "open_serial_port",
]

FC_READ_HOLDING = 3
FC_READ_INPUT = 4
FC_WRITE_MULTIPLE = 16
FC_READ_WRITE = 23
_TABLE_FC = {"holding": FC_READ_HOLDING, "input": FC_READ_INPUT}

DEFAULT_TCP_PORT = 502
DEFAULT_RTU_BAUD = 921600
#: TCP reply deadline per tick. Loopback p99 is ~0.1-0.2 ms (docs/registers.md);
#: a real device/gateway on a LAN usually needs more: set timeout_s.
DEFAULT_TCP_TIMEOUT_S = 0.5e-3
#: Device turnaround + OS latency allowance on top of RTU wire time (as SerialLink).
RTU_TURNAROUND_ALLOWANCE_S = 250e-6
MIN_REPLY_TIMEOUT_S = 0.5e-3
#: Written to the watchdog register (if mapped) every tick, as the serial protocol does.
DEFAULT_WATCHDOG_MS = 50
#: Connect + FC23 probe deadline at open().
DEFAULT_OPEN_TIMEOUT_S = 1.0

_MBAP = struct.Struct(">HHHB")  # tid, protocol id (0), length (unit + pdu), unit
_NO_LOAD_CELL = int(Status.NO_LOAD_CELL)  # plain int: IntFlag ops cost µs on the hot path
_INF = math.inf
_MAX_ADU_TCP = 260
_MAX_HUNT_BYTES = 256  # RTU: garbage skipped before giving up on a reply


# --------------------------------------------------------------------------
# CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF); sent low byte first.
def _make_crc_table() -> tuple[int, ...]:
    table = []
    for b in range(256):
        c = b
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
        table.append(c)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16_modbus(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/MODBUS of ``data`` (continue a running CRC by passing ``crc``).

    Table-driven pure Python, ~0.1 µs/byte (pymodbus's FramerRTU.compute_CRC
    gives the same value, byte-swapped, at ~3x the cost). On the wire the
    CRC goes low byte first: ``crc.to_bytes(2, "little")``.
    """
    t = _CRC_TABLE
    for b in data:
        crc = (crc >> 8) ^ t[(crc ^ b) & 0xFF]
    return crc


def exception_name(code: int) -> str:
    """Name of a Modbus exception code (pymodbus's ExcCodes), or hex."""
    try:
        return ExcCodes(code).name
    except ValueError:
        return f"0x{code:02X}"


# --------------------------------------------------------------------------
# PDU / ADU builders (requests) and response decoders.
def read_request_pdu(fc: int, address: int, count: int) -> bytes:
    """FC3/FC4 request PDU."""
    return struct.pack(">BHH", fc, address, count)


def write_request_pdu(address: int, data: bytes | bytearray) -> bytes:
    """FC16 request PDU writing ``data`` (2 bytes per register)."""
    return struct.pack(">BHHB", FC_WRITE_MULTIPLE, address, len(data) // 2, len(data)) + bytes(data)


def read_write_request_pdu(read_address: int, read_count: int, write_address: int, data: bytes | bytearray) -> bytes:
    """FC23 request PDU: write ``data`` at ``write_address``, then read."""
    return struct.pack(
        ">BHHHHB", FC_READ_WRITE, read_address, read_count, write_address, len(data) // 2, len(data)
    ) + bytes(data)


def mbap_frame(tid: int, unit: int, pdu: bytes | bytearray) -> bytes:
    """Modbus TCP ADU: MBAP header + PDU."""
    return _MBAP.pack(tid & 0xFFFF, 0, len(pdu) + 1, unit) + bytes(pdu)


def rtu_frame(unit: int, pdu: bytes | bytearray) -> bytes:
    """Modbus RTU ADU: unit + PDU + CRC (low byte first)."""
    body = bytes((unit,)) + bytes(pdu)
    return body + crc16_modbus(body).to_bytes(2, "little")


def decode_response_pdu(pdu: bytes | bytearray | memoryview, fc: int, n_registers: int) -> bytes:
    """Register bytes of a response PDU to request ``fc`` reading ``n_registers``.

    FC16 (``n_registers`` = registers written): returns b"" after checking
    the echoed count. Raises :class:`DeviceError` for an exception response,
    :class:`FrameError` for anything else unexpected. Never raises other types.
    """
    n = len(pdu)
    if n < 2:
        raise FrameError(f"response PDU too short: {n} bytes")
    rfc = pdu[0]
    if rfc == fc | 0x80:
        if n != 2:
            raise FrameError(f"exception response is {n} bytes, expected 2")
        code = pdu[1]
        raise DeviceError(code, f"Modbus exception {code} {exception_name(code)} for function {fc}")
    if rfc != fc:
        raise FrameError(f"response function code {rfc} to a function {fc} request")
    if fc == FC_WRITE_MULTIPLE:
        if n != 5:
            raise FrameError(f"FC16 response is {n} bytes, expected 5")
        count = pdu[3] << 8 | pdu[4]
        if count != n_registers:
            raise FrameError(f"FC16 response confirms {count} registers, wrote {n_registers}")
        return b""
    bc = pdu[1]
    if bc != 2 * n_registers or n != 2 + bc:
        raise FrameError(
            f"function {fc} response: byte count {bc}, PDU {n} bytes; expected {2 * n_registers} data bytes"
        )
    return bytes(pdu[2:])


def decode_tcp_response(
    frame: bytes | bytearray | memoryview, tid: int, unit: int, fc: int, n_registers: int
) -> bytes:
    """Check one complete MBAP frame answering (tid, unit, fc); return its register bytes.

    Raises :class:`FrameError` (MBAP fields, length) or :class:`DeviceError`
    (exception response); nothing else.
    """
    n = len(frame)
    if n < 9:
        raise FrameError(f"MBAP frame too short: {n} bytes")
    rtid, pid, length, runit = _MBAP.unpack_from(frame, 0)
    if pid != 0:
        raise FrameError(f"MBAP protocol id {pid}, expected 0")
    if length != n - 6:
        raise FrameError(f"MBAP length {length} but frame carries {n - 6} bytes")
    if rtid != tid:
        raise FrameError(f"MBAP transaction id {rtid}, expected {tid}")
    if runit != unit:
        raise FrameError(f"response from unit {runit}, expected {unit}")
    return decode_response_pdu(memoryview(frame)[7:], fc, n_registers)


def decode_rtu_response(frame: bytes | bytearray | memoryview, unit: int, fc: int, n_registers: int) -> bytes:
    """Check one complete RTU frame answering (unit, fc); return its register bytes.

    Raises :class:`FrameError` (length, CRC, unit, function, byte count) or
    :class:`DeviceError` (a CRC-valid exception response); nothing else.
    """
    n = len(frame)
    if n < 5:
        raise FrameError(f"RTU frame too short: {n} bytes")
    crc_rx = frame[n - 2] | frame[n - 1] << 8
    crc = crc16_modbus(memoryview(frame)[: n - 2])
    if crc != crc_rx:
        raise FrameError(f"RTU CRC mismatch: frame has 0x{crc_rx:04X}, computed 0x{crc:04X}")
    if frame[0] != unit:
        raise FrameError(f"response from unit {frame[0]}, expected {unit}")
    return decode_response_pdu(memoryview(frame)[1 : n - 2], fc, n_registers)


# --------------------------------------------------------------------------
# RTU wire time (feasibility check)
def rtu_bits_per_char(parity: str = "E", stopbits: float = 1, bytesize: int = 8) -> int:
    """Bits per character on the wire: start + data + parity + stop (8E1 = 11, 8N1 = 10)."""
    return int(1 + bytesize + (0 if str(parity).upper() == "N" else 1) + math.ceil(stopbits))


def rtu_tick_frames(register_map: RegisterMap, use_fc23: bool) -> list[tuple[int, int]]:
    """(request bytes, response bytes) of each RTU transaction in one tick."""
    w = register_map.write_block.count
    if use_fc23:
        if not register_map.fc23_capable:
            raise ValueError("register map cannot use FC23 (read quantities not in one holding block)")
        r = register_map.read_blocks[0].count
        return [(13 + 2 * w, 5 + 2 * r)]
    frames = [(9 + 2 * w, 8)]
    frames += [(8, 5 + 2 * b.count) for b in register_map.read_blocks]
    return frames


def rtu_transaction_wire_time_s(
    register_map: RegisterMap,
    baudrate: float,
    use_fc23: bool,
    bits_per_char: int = 11,
    fixed_t35_above_19200: bool = False,
) -> float:
    """Seconds one tick occupies an RTU line: every frame's characters plus a
    3.5-character silence before each frame (request and response).

    ``bits_per_char`` = 11 for spec RTU (8E1, 8O1 or 8N2), 10 for the common
    non-compliant 8N1. ``fixed_t35_above_19200`` applies the spec's
    recommendation of a fixed 1.75 ms t3.5 above 19200 Bd (devices that do
    this cannot do 1 kHz at any rate). Excludes device processing and OS/USB
    latency. E.g. the default map with FC23 at 115200 Bd 8E1: 52 bytes →
    4.97 ms + 2 × 0.33 ms gaps ≈ 5.6 ms: 1 kHz is impossible.
    """
    if not baudrate > 0:
        raise ValueError(f"baudrate must be > 0, got {baudrate!r}")
    frames = rtu_tick_frames(register_map, use_fc23)
    t_char = bits_per_char / baudrate
    t35 = 1.75e-3 if (fixed_t35_above_19200 and baudrate > 19200) else 3.5 * t_char
    chars = sum(a + b for a, b in frames)
    return chars * t_char + 2 * len(frames) * t35


def default_rtu_timeout_s(register_map: RegisterMap, baudrate: float, use_fc23: bool, bits_per_char: int = 11) -> float:
    """Per-tick RTU deadline: wire time + 250 µs turnaround, at least 0.5 ms."""
    wire = rtu_transaction_wire_time_s(register_map, baudrate, use_fc23, bits_per_char)
    return max(MIN_REPLY_TIMEOUT_S, wire + RTU_TURNAROUND_ALLOWANCE_S)


def open_serial_port(url: str, *, baudrate: int, parity: str = "E", stopbits: float = 1, **kwargs: Any) -> Any:
    """pyserial ``serial_for_url`` (8 data bits), with one pty workaround.

    Linux ptys accept PARENB the first time a pty is configured but reject
    it with EINVAL on every later open (seen with pyserial 3.5). A pty has
    no line, so parity means nothing there: on ``/dev/pts/*`` a failed open
    is retried with parity N. Real ports get exactly what was asked for.
    """
    import serial

    try:
        return serial.serial_for_url(url, baudrate=baudrate, parity=parity, stopbits=stopbits, bytesize=8, **kwargs)
    except (serial.SerialException, OSError):
        if parity == "N" or not os.path.realpath(str(url)).startswith("/dev/pts/"):
            raise
        return serial.serial_for_url(url, baudrate=baudrate, parity="N", stopbits=stopbits, bytesize=8, **kwargs)


# --------------------------------------------------------------------------
# Precompiled per-tick transactions
class _Tx:
    """One request template and what its response must look like."""

    __slots__ = (
        "fc", "n_regs", "adu", "data_off", "crc_prefix", "crc_prefix_len", "resp_len", "writes", "block",
        "_pdu", "_data_off_pdu", "resp_tail",
    )

    def __init__(self, fc: int, pdu: bytes, n_regs: int, data_off_pdu: int | None, writes: bool, block: int = -1) -> None:
        self.fc = fc
        self.n_regs = n_regs  # registers in the response data (FC16: registers written)
        self.writes = writes
        self.block = block  # index into read_blocks (-1 for FC16)
        self.adu = bytearray()
        self.data_off = 0
        self.crc_prefix = 0xFFFF
        self.crc_prefix_len = 0
        self.resp_len = 0
        self.resp_tail = b""
        self._pdu = pdu
        self._data_off_pdu = data_off_pdu

    def build_tcp(self, unit: int) -> "_Tx":
        self.adu = bytearray(mbap_frame(0, unit, self._pdu))
        self.data_off = 7 + (self._data_off_pdu or 0)
        self.resp_len = 7 + (5 if self.fc == FC_WRITE_MULTIPLE else 2 + 2 * self.n_regs)
        # Expected reply after the tid: constant except the register data.
        if self.fc == FC_WRITE_MULTIPLE:
            self.resp_tail = mbap_frame(0, unit, self._pdu[:5])[2:]
        else:
            self.resp_tail = mbap_frame(0, unit, bytes((self.fc, 2 * self.n_regs)) + bytes(2 * self.n_regs))[2:9]
        return self

    def build_rtu(self, unit: int) -> "_Tx":
        self.adu = bytearray(rtu_frame(unit, self._pdu))
        self.data_off = 1 + (self._data_off_pdu or 0)
        # CRC of the constant bytes before the write data, computed once.
        self.crc_prefix_len = self.data_off if self.writes else len(self.adu) - 2
        self.crc_prefix = crc16_modbus(self.adu[: self.crc_prefix_len])
        self.resp_len = 8 if self.fc == FC_WRITE_MULTIPLE else 5 + 2 * self.n_regs
        return self


def _plan(rmap: RegisterMap, use_fc23: bool) -> list[_Tx]:
    wb = rmap.write_block
    zeros = bytes(2 * wb.count)
    if use_fc23:
        rb = rmap.read_blocks[0]
        pdu = read_write_request_pdu(rb.address, rb.count, wb.address, zeros)
        return [_Tx(FC_READ_WRITE, pdu, rb.count, 10, True, 0)]
    txs = [_Tx(FC_WRITE_MULTIPLE, write_request_pdu(wb.address, zeros), wb.count, 6, True)]
    for i, b in enumerate(rmap.read_blocks):
        txs.append(_Tx(_TABLE_FC[b.table], read_request_pdu(_TABLE_FC[b.table], b.address, b.count), b.count, None, False, i))
    return txs


# --------------------------------------------------------------------------
# Byte transports
class _FdIO:
    """Serial line over a raw fd: select + os.read with an absolute deadline.

    Why not pyserial's read(): its timeout is per call and changing it costs
    a tcsetattr; with our own deadline one exact-length read is one select
    plus one read, and overshoot is bounded by the scheduler, not a slice.
    """

    def __init__(self, fd: int, owner: Any = None, spin: bool = False) -> None:
        self.fd = fd
        self.owner = owner  # pyserial object that owns fd (closed with us), or None
        #: wait for input by polling (select with timeout 0), never sleeping in
        #: select: see ModbusLink's ``spin_wait``
        self.spin = spin
        os.set_blocking(fd, False)

    def write(self, data: bytes | bytearray, deadline: float) -> None:
        fd = self.fd
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                n = 0
            except OSError as e:
                raise Disconnected(f"write failed: {e}") from e
            view = view[n:]
            if view:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not select.select([], [fd], [], remaining)[1]:
                    raise LinkTimeout("write blocked past the deadline")

    def read(self, n: int, deadline: float, max_n: int = 0, wake_ns: int = 0) -> bytes:
        """At least ``n`` bytes (fewer only if the deadline passed), at most
        ``max(n, max_n)``. ``wake_ns``: sleep until this ``monotonic_ns`` time
        before waiting (nothing can be there earlier)."""
        fd = self.fd
        out = b""
        clock = time.monotonic
        want = max(n, max_n)
        spin = self.spin
        if wake_ns:
            sleep_until_ns(wake_ns)
        try:
            while len(out) < n:
                remaining = deadline - clock()
                if remaining < 0:
                    remaining = 0
                if not select.select([fd], [], [], 0.0 if spin else remaining)[0]:
                    if remaining > 0 and spin:
                        continue
                    break
                try:
                    chunk = os.read(fd, want - len(out))
                except BlockingIOError:  # spurious readiness
                    continue
                if not chunk:  # readable but nothing: device gone (as pyserial)
                    raise Disconnected("device reports readiness to read but returned no data")
                out += chunk
        except OSError as e:
            raise Disconnected(f"read failed: {e}") from e
        return out

    def flush_input(self) -> int:
        n = 0
        try:
            while select.select([self.fd], [], [], 0)[0]:
                chunk = os.read(self.fd, 4096)
                if not chunk:
                    break
                n += len(chunk)
        except OSError:
            pass
        return n

    def close(self) -> None:
        if self.owner is not None:
            try:
                self.owner.close()
            except Exception:  # noqa: BLE001
                pass


class _PySerialIO:
    """Fallback for pyserial URL handlers without a file descriptor (socket://, loop://...)."""

    def __init__(self, port: Any, poll_s: float) -> None:
        self.port = port
        self.poll_s = poll_s

    def write(self, data: bytes | bytearray, deadline: float) -> None:
        import serial

        try:
            self.port.write(bytes(data))
        except serial.SerialTimeoutException as e:
            raise LinkTimeout(f"write blocked: {e}") from e
        except (serial.SerialException, OSError) as e:
            raise Disconnected(f"write failed: {e}") from e

    def read(self, n: int, deadline: float, max_n: int = 0, wake_ns: int = 0) -> bytes:
        import serial

        if wake_ns:
            sleep_until_ns(wake_ns)
        out = b""
        try:
            while len(out) < n:
                out += self.port.read(n - len(out))
                if len(out) < n and time.monotonic() >= deadline:
                    break
        except (serial.SerialException, OSError) as e:
            raise Disconnected(f"read failed: {e}") from e
        return out

    def flush_input(self) -> int:
        try:
            n = self.port.in_waiting
            self.port.reset_input_buffer()
            return int(n)
        except Exception:  # noqa: BLE001
            return 0

    def close(self) -> None:
        try:
            self.port.close()
        except Exception:  # noqa: BLE001
            pass


# --------------------------------------------------------------------------
class ModbusLink:
    """:class:`mrctl.io.base.Link` over Modbus TCP (``transport="tcp"``) or RTU (``"rtu"``).

    TCP: ``host``, ``port``. RTU: ``url`` = device path or pyserial URL, or an
    already-open file descriptor (int; e.g. a pty master — the link sets it
    non-blocking and does not close it), plus ``baudrate``/``parity``/``stopbits``
    (Modbus default 8E1).

    ``unit_id`` overrides the register map's. ``timeout_s`` is the deadline of
    a whole tick (all its transactions); default TCP 0.5 ms, RTU wire time +
    250 µs (≥ 0.5 ms). ``use_fc23``: True/False, or None to probe at open.
    ``watchdog_ms`` is written every tick if the map has a watchdog register.
    ``rtu_local_echo``: the RS-485 adapter echoes what we send; read it back
    and drop it before the response. ``spin_wait``: wait for a reply by
    polling (select with timeout 0) instead of sleeping in select(): busy for
    one round trip (~0.1-0.3 ms), but a thread sleeping in select() wakes up
    to ~1.5 ms late on a VM (docs/performance.md), as with the serial link.
    """

    def __init__(
        self,
        transport: str,
        *,
        host: str | None = None,
        port: int = DEFAULT_TCP_PORT,
        url: str | int | None = None,
        baudrate: int = DEFAULT_RTU_BAUD,
        parity: str = "E",
        stopbits: float = 1,
        unit_id: int | None = None,
        register_map: RegisterMap | Mapping[str, Any] | None = None,
        timeout_s: float | None = None,
        use_fc23: bool | None = None,
        watchdog_ms: float = DEFAULT_WATCHDOG_MS,
        open_timeout_s: float = DEFAULT_OPEN_TIMEOUT_S,
        safe_on_close: bool = True,
        rtu_local_echo: bool = False,
        serial_kwargs: Mapping[str, Any] | None = None,
        spin_wait: bool = True,
    ) -> None:
        if transport not in ("tcp", "rtu"):
            raise ValueError(f"transport must be 'tcp' or 'rtu', got {transport!r}")
        self.transport = transport
        if register_map is None:
            rmap = default_register_map()
        elif isinstance(register_map, RegisterMap):
            rmap = register_map
        else:
            rmap = RegisterMap.from_mapping(register_map)
        if unit_id is not None and unit_id != rmap.unit_id:
            rmap = rmap.with_unit_id(unit_id)
        if transport == "rtu" and not 1 <= rmap.unit_id <= 247:
            raise ValueError(f"RTU unit_id must be 1..247 (0 is broadcast: no replies), got {rmap.unit_id}")
        if use_fc23 and not rmap.fc23_capable:
            raise ValueError(
                "use_fc23=True but the register map's read quantities are not one holding block "
                f"({rmap.describe()})"
            )
        self.register_map = rmap
        self.unit_id = rmap.unit_id
        if transport == "tcp":
            if not host:
                raise ValueError("Modbus TCP needs host")
            self.host = host
            self.port = int(port)
            self.url: str | int | None = None
        else:
            if url is None or url == "":
                raise ValueError("Modbus RTU needs url (device path, pyserial URL or fd)")
            self.url = url
            self.host = None
            self.port = 0
        self.baudrate = int(baudrate)
        self.parity = str(parity).upper()
        self.stopbits = stopbits
        self.bits_per_char = rtu_bits_per_char(self.parity, stopbits)
        self._timeout_arg = timeout_s
        if timeout_s is not None and not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.use_fc23_config = use_fc23
        #: decided at construction (True/False) or at open() (probe); None before the probe
        self.use_fc23: bool | None = use_fc23 if use_fc23 is not None else (None if rmap.fc23_capable else False)
        self.watchdog_ms = watchdog_ms
        rmap.encode_write(0.0, False, watchdog_ms)  # ValueError now if the watchdog doesn't fit its register
        self.open_timeout_s = float(open_timeout_s)
        self.safe_on_close = safe_on_close
        self.rtu_local_echo = rtu_local_echo
        self._serial_kwargs = dict(serial_kwargs or {})
        #: False → writes go out with enable = 0 (device holds 0 A).
        self.enabled = True
        # device pacing (set_device_paced): SYNC bit set, deadline + one period
        self._sync_bits = 0
        self._extra_timeout_s = 0.0
        self._period_ns = 0
        self._sleep_margin_ns = 0
        self._t_reply_ns = 0  # monotonic ns of the last device-paced reply (0 = none yet)
        self.spin_wait = bool(spin_wait)
        self._clear_pending = False
        self.timeout_s = self._default_timeout(self.use_fc23 if self.use_fc23 is not None else rmap.fc23_capable)

        self._sock: socket.socket | None = None
        self._fds: list[int] = []
        self._io: Any = None
        self._rx = bytearray()
        self._txs: list[_Tx] = []
        self._tid = 0
        self._seq_local = 0
        self._seq_last: int | None = None
        self._seq_total = 0
        self._t_last: int | None = None
        self._t_total = 0
        self._seq_mod = rmap.counter_modulus("seq")
        self._t_mod = rmap.counter_modulus("t_dev")
        self._has_seq = rmap.has("seq")
        self._has_t = rmap.has("t_dev")
        self._read_bufs: list[bytes] = [b""] * len(rmap.read_blocks)
        # counters (cumulative over reopen)
        self.exchanges = 0  #: successful exchanges
        self.transactions = 0  #: Modbus request/response pairs completed
        self.timeouts = 0
        self.frame_errors = 0  #: exchanges that ended in FrameError
        self.crc_errors = 0  #: RTU responses with a bad CRC
        self.invalid_values = 0  #: responses whose x/v/t (or F/I as ±inf) were not finite
        self.device_errors = 0  #: Modbus exception responses
        self.stale_replies = 0  #: TCP responses with an old transaction id (discarded)
        self.bytes_discarded = 0  #: junk bytes skipped/flushed
        self.disconnects = 0
        self.device_clock_resets = 0  #: t_dev went backwards (device restarted?)
        self.fc23_fallbacks = 0  #: probes that fell back to FC16 + FC3/FC4
        self.last_exception_code: int | None = None

    kinds = ("modbus-tcp", "modbus-rtu")
    split = False
    host_clocked = False
    true_force_N = math.nan

    def begin_tick(self, k: int) -> None:
        pass

    @classmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "ModbusLink":
        """From the validated ``backend`` section (type modbus-tcp or modbus-rtu)."""
        common = dict(unit_id=cfg.unit_id, register_map=cfg.register_map, timeout_s=cfg.timeout_s,
                      use_fc23=cfg.use_fc23, watchdog_ms=cfg.watchdog_ms, open_timeout_s=cfg.open_timeout_s,
                      spin_wait=cfg.spin_wait)
        if cfg.type == "modbus-tcp":
            return cls("tcp", host=cfg.host, port=cfg.port, **common)
        return cls("rtu", url=cfg.url, baudrate=cfg.baudrate, parity=cfg.parity, stopbits=cfg.stopbits,
                   rtu_local_echo=cfg.rtu_local_echo, **common)

    @classmethod
    def wire_time_s(cls, cfg: Any) -> float | None:
        """RTU: every frame of one tick plus the 3.5-character gaps; TCP: None."""
        if cfg.type != "modbus-rtu":
            return None
        fc23 = cfg.use_fc23 if cfg.use_fc23 is not None else True
        bits = rtu_bits_per_char(getattr(cfg, "parity", "E"), getattr(cfg, "stopbits", 1))
        return rtu_transaction_wire_time_s(cfg.register_map, cfg.baudrate, fc23, bits)

    def _default_timeout(self, fc23: bool) -> float:
        if self._timeout_arg is not None:
            return float(self._timeout_arg)
        if self.transport == "tcp":
            return DEFAULT_TCP_TIMEOUT_S
        return default_rtu_timeout_s(self.register_map, self.baudrate, fc23, self.bits_per_char)

    # -- counters ------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """Snapshot of all counters, for logs/metrics (not for the hot path)."""
        return {
            k: getattr(self, k)
            for k in (
                "exchanges",
                "transactions",
                "timeouts",
                "frame_errors",
                "crc_errors",
                "invalid_values",
                "device_errors",
                "stale_replies",
                "bytes_discarded",
                "disconnects",
                "device_clock_resets",
                "fc23_fallbacks",
            )
        }

    # -- lifecycle -------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._sock is not None or self._io is not None

    def open(self) -> None:
        """Connect (idempotent); probe FC23 if ``use_fc23`` was None.

        Raises :class:`Disconnected` if the connection/port can't be opened,
        or the probe's :class:`LinkError` if the device doesn't answer.
        """
        if self.is_open:
            return
        if self.transport == "tcp":
            self._open_tcp()
        else:
            self._open_rtu()
        self._rx.clear()
        self._seq_last = None
        self._t_last = None
        try:
            if self.use_fc23_config is None and self.register_map.fc23_capable:
                self._probe()
            else:
                self._set_plan(bool(self.use_fc23))
        except BaseException:
            self._drop()
            raise

    def _open_tcp(self) -> None:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.open_timeout_s)
        except OSError as e:  # refused, unreachable, timeout (socket.timeout is an OSError)
            raise Disconnected(f"cannot connect to {self.host}:{self.port}: {e}") from e
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            pass
        sock.setblocking(False)
        self._sock = sock
        self._fds = [sock.fileno()]

    def _open_rtu(self) -> None:
        if isinstance(self.url, int):
            try:
                os.fstat(self.url)
            except OSError as e:
                raise Disconnected(f"fd {self.url}: {e}") from e
            self._io = _FdIO(self.url, spin=self.spin_wait)
            return
        import serial

        try:
            port = open_serial_port(
                self.url,
                baudrate=self.baudrate,
                parity=self.parity,
                stopbits=self.stopbits,
                timeout=min(max(self.timeout_s / 4, 100e-6), 20e-3),
                write_timeout=max(self.timeout_s, 5e-3),
                **{"exclusive": True, **self._serial_kwargs},  # flock: one owner (hardening)
            )
            port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as e:
            raise Disconnected(f"cannot open {self.url}: {e}") from e
        try:
            fd = port.fileno()
        except Exception:  # noqa: BLE001 - URL handlers have no fd
            fd = None
        self._io = _FdIO(fd, owner=port, spin=self.spin_wait) if isinstance(fd, int) else _PySerialIO(port, port.timeout)

    def _attach_transport(self, *, use_fc23: bool, sock: Any = None, io: Any = None) -> None:
        """Use an already-open transport instead of open() (tests, benchmarks).

        ``sock``: a non-blocking socket-like object (send, recv, fileno) for
        TCP; ``io``: an object with ``write(data, deadline)``, ``read(n,
        deadline)``, ``flush_input()``, ``close()`` for RTU. No probe.
        """
        if sock is not None:
            self._sock = sock
            self._fds = [sock.fileno()]
        else:
            self._io = io
        self._set_plan(use_fc23)

    def _set_plan(self, fc23: bool) -> None:
        self.use_fc23 = fc23
        self.timeout_s = self._default_timeout(fc23)
        txs = _plan(self.register_map, fc23)
        unit = self.unit_id
        self._txs = [t.build_tcp(unit) if self.transport == "tcp" else t.build_rtu(unit) for t in txs]

    def _probe(self) -> None:
        """FC23 once (0 A, disabled); ILLEGAL_FUNCTION or silence → FC16 + FC3/FC4."""
        self._set_plan(True)
        try:
            self._transact_all(0.0, False, time.monotonic() + self.open_timeout_s)
            return
        except DeviceError as e:
            if e.code != ExcCodes.ILLEGAL_FUNCTION:
                raise
        except LinkTimeout:
            pass  # some devices ignore unknown functions instead of answering
        self.fc23_fallbacks += 1
        self._set_plan(False)
        self._transact_all(0.0, False, time.monotonic() + self.open_timeout_s)

    def close(self) -> None:
        """Write 0 A with enable = 0 (best effort), then close. Idempotent."""
        if not self.is_open:
            return
        try:
            if self.safe_on_close and self._txs:
                tx = self._txs[0]  # FC23 or FC16: the writing transaction
                self._transaction(tx, 0.0, False, time.monotonic() + max(self.timeout_s, 0.05))
        except Exception:  # noqa: BLE001 - closing must not fail on a dead link
            pass
        finally:
            self._drop()

    def _drop(self) -> None:
        sock, self._sock = self._sock, None
        io, self._io = self._io, None
        if sock is not None:
            try:
                sock.close()
            except OSError:
                pass
        if io is not None:
            io.close()

    def __enter__(self) -> "ModbusLink":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def device_key(self) -> str | None:  # device ownership (hardening)
        if self.transport == "tcp":
            return network_device_key("modbus-tcp", str(self.host), self.port, self.unit_id)
        return serial_device_key(self.url)

    def describe(self) -> str:
        rm = self.register_map
        mode = {True: "FC23", False: "FC16+FC3/4", None: "FC23 (probe at open)"}[self.use_fc23]
        if self.transport == "tcp":
            where = f"modbus-tcp {self.host}:{self.port}"
        else:
            fc23 = bool(self.use_fc23) if self.use_fc23 is not None else rm.fc23_capable
            wire = rtu_transaction_wire_time_s(rm, self.baudrate, fc23, self.bits_per_char)
            url = f"fd {self.url}" if isinstance(self.url, int) else self.url
            where = (
                f"modbus-rtu {url} @ {self.baudrate} Bd 8{self.parity}{self.stopbits:g} "
                f"({wire * 1e6:.0f} µs on the wire per tick)"
            )
        return f"{where}, {rm.describe()}, {mode}, timeout {self.timeout_s * 1e3:.3g} ms"

    # -- the tick ------------------------------------------------------------
    @property
    def device_paced(self) -> bool:
        """True while every write sets SYNC (:meth:`set_device_paced`)."""
        return self._sync_bits != 0

    def set_device_paced(self, on: bool, period_s: float, spin_margin_s: float = 3e-4) -> None:
        """Device pacing (docs/registers.md): every write sets SYNC (bit 2 of
        the enable register), so the device applies it at its next tick and
        answers after it; an exchange then returns at the device's next tick.
        The deadline grows by one period. Needs an ``enable`` register.
        While waiting, the link sleeps until ``spin_margin_s`` before the
        reply is due (one period after the previous one), then polls (with
        ``spin_wait``; else it waits in select()), as the serial link does."""
        if on and not self.register_map.has("enable"):
            raise ValueError("device pacing needs an 'enable' register in the map (its bit 2 is SYNC)")
        if on and not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s!r}")
        self._sync_bits = 4 if on else 0
        self._extra_timeout_s = period_s if on else 0.0
        self._period_ns = round(period_s * 1e9) if on else 0
        self._sleep_margin_ns = round(spin_margin_s * 1e9)
        self._t_reply_ns = 0

    def exchange(self, current_A: float) -> Sample:
        """Write ``current_A`` (A) (+ enable, watchdog), read and return the sample."""
        if not self.is_open:
            raise Disconnected(f"{self.describe()}: not open")
        if not -3.4e38 < current_A < 3.4e38:
            raise ValueError(f"current_A must be finite, got {current_A!r}")
        flags = (1 if self.enabled else 0) | self._sync_bits
        deadline = time.monotonic() + self.timeout_s + self._extra_timeout_s
        period = self._period_ns
        # device pacing: the reply comes one device period after the last
        wake_ns = self._t_reply_ns + period - self._sleep_margin_ns if period and self._t_reply_ns else 0
        if self._clear_pending:
            self._transact_all(current_A, flags | 2, deadline, wake_ns)
            self._clear_pending = False
        else:
            self._transact_all(current_A, flags, deadline, wake_ns)
        if period:
            self._t_reply_ns = time.monotonic_ns()
        return self._to_sample()

    def request_clear_faults(self) -> bool:
        """Set CLEAR_FAULTS (bit 1 of the enable register) in the next exchange's write.

        Clears latched device status such as WATCHDOG_TRIPPED, like the serial
        protocol's CLEAR_FAULTS flag. False if the map has no enable register.
        """
        if not self.register_map.has("enable"):
            return False
        self._clear_pending = True
        return True

    def _transact_all(self, current_A: float, enable: bool | int, deadline: float, wake_ns: int = 0) -> None:
        """The tick's transactions; ``wake_ns``: the first one's wait for its
        reply starts with a sleep until then (device pacing)."""
        for tx in self._txs:
            data = self._transaction(tx, current_A, enable, deadline, wake_ns)
            wake_ns = 0
            if tx.block >= 0:
                self._read_bufs[tx.block] = data

    def _transaction(self, tx: _Tx, current_A: float, enable: bool | int, deadline: float,
                     wake_ns: int = 0) -> bytes:
        """One request/response; counts and maps every failure to a typed error."""
        adu = tx.adu
        if tx.writes:
            self.register_map.encode_write_into(adu, tx.data_off, current_A, enable, self.watchdog_ms)
        try:
            if self._sock is not None:
                data = self._tcp_transaction(tx, adu, deadline, wake_ns)
            else:
                data = self._rtu_transaction(tx, adu, deadline, wake_ns)
        except LinkTimeout:
            self.timeouts += 1
            raise
        except FrameError:
            self.frame_errors += 1
            raise
        except DeviceError as e:
            self.device_errors += 1
            self.last_exception_code = e.code
            raise
        except Disconnected:
            self.disconnects += 1
            self._drop()
            raise
        self.transactions += 1
        return data

    # TCP ------------------------------------------------------------------------
    def _tcp_transaction(self, tx: _Tx, adu: bytearray, deadline: float, wake_ns: int = 0) -> bytes:
        # Non-blocking socket + select.select: Python's own socket timeouts go
        # through poll() with a millisecond timeout rounded up, which would
        # turn a 0.5 ms deadline into 1 ms; select takes microseconds.
        sock = self._sock
        assert sock is not None
        tid = self._tid = (self._tid + 1) & 0xFFFF
        adu[0] = tid >> 8
        adu[1] = tid & 0xFF
        clock = time.monotonic
        rx = self._rx
        fds = self._fds
        spin = self.spin_wait
        try:
            try:
                sent = sock.send(adu)
            except BlockingIOError:
                sent = 0
            if sent != len(adu):  # never for ~30 bytes on a healthy socket
                view = memoryview(adu)[sent:]
                while view:
                    remaining = deadline - clock()
                    if remaining <= 0 or not select.select([], fds, [], remaining)[1]:
                        raise LinkTimeout(f"{self.host}:{self.port}: send blocked past the deadline")
                    try:
                        view = view[sock.send(view):]
                    except BlockingIOError:
                        pass
            while True:
                n = len(rx)
                if n >= 6:
                    if rx[2] or rx[3] or not 2 <= (rx[4] << 8 | rx[5]) <= _MAX_ADU_TCP - 6:
                        self._tcp_desync(sock)
                        raise FrameError(f"{self.host}:{self.port}: bad MBAP header; stream flushed")
                    total = 6 + (rx[4] << 8 | rx[5])
                    if n >= total:
                        frame = bytes(rx[:total])
                        del rx[:total]
                        if frame[0] << 8 | frame[1] != tid:
                            self.stale_replies += 1
                            continue
                        return decode_tcp_response(frame, tid, self.unit_id, tx.fc, tx.n_regs)
                if wake_ns:
                    sleep_until_ns(wake_ns)
                    wake_ns = 0
                remaining = deadline - clock()
                if not select.select(fds, (), (), 0.0 if spin else (remaining if remaining > 0 else 0))[0]:
                    if spin and remaining > 0:
                        continue
                    raise LinkTimeout(
                        f"{self.host}:{self.port}: no reply to tid {tid} within {self.timeout_s * 1e3:.3g} ms"
                    )
                try:
                    chunk = sock.recv(4096)
                except BlockingIOError:  # spurious readiness
                    continue
                if not chunk:
                    raise Disconnected(f"{self.host}:{self.port}: connection closed by peer")
                # Fast path: exactly the expected reply, nothing buffered.
                if not rx and len(chunk) == tx.resp_len and chunk[0] << 8 | chunk[1] == tid:
                    if tx.fc == FC_WRITE_MULTIPLE:
                        if chunk[2:] == tx.resp_tail:
                            return b""
                    elif chunk[2:9] == tx.resp_tail:
                        return chunk[9:]
                rx += chunk
        except OSError as e:  # reset, broken pipe, ...
            raise Disconnected(f"{self.host}:{self.port}: {e}") from e

    def _tcp_desync(self, sock: socket.socket) -> None:
        """After an impossible MBAP header: drop what we have and what's queued."""
        self.bytes_discarded += len(self._rx)
        self._rx.clear()
        try:
            while True:
                chunk = sock.recv(4096)
                if not chunk:
                    break
                self.bytes_discarded += len(chunk)
        except OSError:
            pass

    # RTU ------------------------------------------------------------------------
    def _rtu_transaction(self, tx: _Tx, adu: bytearray, deadline: float, wake_ns: int = 0) -> bytes:
        io = self._io
        # RTU has no transaction id: whatever is waiting now is a late answer
        # to an earlier request (or noise). Drop it every time (one select(),
        # ~1-2 µs), or one late reply would shift every later exchange by one.
        self.bytes_discarded += io.flush_input()
        n = len(adu)
        if tx.writes:
            crc = crc16_modbus(memoryview(adu)[tx.crc_prefix_len : n - 2], tx.crc_prefix)
        else:
            crc = tx.crc_prefix
        adu[n - 2] = crc & 0xFF
        adu[n - 1] = crc >> 8
        io.write(adu, deadline)
        if self.rtu_local_echo:
            echo = io.read(n, deadline)
            if echo != adu:
                raise FrameError(f"{self.url}: local echo mismatch ({len(echo)} of {n} bytes)")
        unit = self.unit_id
        fc = tx.fc
        # ≥ 5 bytes tell an exception (5 bytes long) from data; ask for the
        # whole expected reply at once (RTU: nothing can follow it).
        buf = io.read(5, deadline, tx.resp_len, wake_ns)
        skipped = 0
        # Hunt for "unit, fc" (or the exception form) if junk precedes the reply.
        while len(buf) >= 2 and not (buf[0] == unit and (buf[1] == fc or buf[1] == fc | 0x80)):
            if skipped >= _MAX_HUNT_BYTES:
                break
            i = 1
            while i < len(buf) and buf[i] != unit:
                i += 1
            skipped += i
            buf = buf[i:]
            if len(buf) < 5:
                buf += io.read(5 - len(buf), deadline, tx.resp_len - len(buf))
                if len(buf) < 5:
                    break
        self.bytes_discarded += skipped
        if len(buf) < 5:
            if not buf and not skipped:
                raise LinkTimeout(f"{self.url}: no reply within {self.timeout_s * 1e3:.3g} ms")
            raise FrameError(
                f"{self.url}: incomplete reply ({len(buf)} bytes after {skipped} skipped) "
                f"within {self.timeout_s * 1e3:.3g} ms"
            )
        total = 5 if buf[1] & 0x80 else tx.resp_len
        if buf[0] == unit and len(buf) < total:
            buf += io.read(total - len(buf), deadline)
            if len(buf) < total:
                raise FrameError(
                    f"{self.url}: reply truncated at {len(buf)} of {total} bytes within {self.timeout_s * 1e3:.3g} ms"
                )
        elif len(buf) > total:  # trailing junk (flushed before the next request anyway)
            self.bytes_discarded += len(buf) - total
            buf = buf[:total]
        try:
            return decode_rtu_response(buf, unit, fc, tx.n_regs)
        except FrameError as e:
            if "CRC" in str(e):
                self.crc_errors += 1
            raise FrameError(f"{self.url}: {e}") from None
        except DeviceError as e:
            raise DeviceError(e.code, f"{self.url}: {e}") from None

    # decode ---------------------------------------------------------------------
    def _to_sample(self) -> Sample:
        seq, t_raw, x, v, F, status, I_app = self.register_map.decode_read(*self._read_bufs)
        # A well-formed reply with non-finite values is a healthy link carrying
        # bad data: return it and let the safety supervisor judge it (bad
        # sample: hold, then 0 A), as the serial backend does. Raising here
        # made NaN data look like a dead link (exit 3). Counted for the log.
        if not (x - x == 0.0 and v - v == 0.0):
            self.invalid_values += 1
        if F is None:
            F = math.nan
            status = (status or 0) | _NO_LOAD_CELL
        elif F == _INF or F == -_INF:
            self.invalid_values += 1
        if status is None:
            status = 0
        elif status & _NO_LOAD_CELL:
            F = math.nan
        if I_app is None:
            I_app = math.nan
        elif I_app == _INF or I_app == -_INF:
            self.invalid_values += 1
        # seq: extend narrower counters to 32 bits so the safety layer's
        # modulo-2**32 staleness test works across the wrap.
        if self._has_seq:
            mod = self._seq_mod
            if mod == 1 << 32:
                seq_out = seq
            else:
                last = self._seq_last
                if last is None:
                    self._seq_total = seq
                else:
                    self._seq_total += (seq - last) % mod  # type: ignore[operator]
                self._seq_last = seq
                seq_out = self._seq_total & 0xFFFFFFFF
        else:
            self._seq_local = (self._seq_local + 1) & 0xFFFFFFFF
            seq_out = self._seq_local
        if not self._has_t:
            t = time.monotonic()
        elif self._t_mod is None:
            t = t_raw  # float32 seconds, already scaled
            if not t - t == 0.0:
                self.invalid_values += 1
                self.frame_errors += 1
                raise FrameError(f"t_dev decoded to {t!r}")
        else:
            mod = self._t_mod
            last = self._t_last
            if last is None:
                self._t_total = t_raw
            else:
                delta = (t_raw - last) % mod
                if delta < mod >> 1:
                    self._t_total += delta
                else:  # went backwards: device restarted its clock
                    self.device_clock_resets += 1
                    self._t_total = t_raw
            self._t_last = t_raw
            t = self.register_map.t_dev_seconds(self._t_total)
        self.exchanges += 1
        return Sample(seq_out, t, x, v, F, status, I_app)
