"""Modbus frame codec: CRC, request PDUs/ADUs, response checks, wire time.

Everything here is pure bytes and arithmetic (no I/O), shared by the link
(:mod:`mrctl.io.modbus.link`) and the simulated device (``hil_sim``):

* CRC-16/MODBUS, table-driven;
* request PDUs (FC3/FC4 read, FC16 write, FC23 read/write) and their TCP
  (MBAP) and RTU (unit + CRC) frames;
* response decoders that either return the register bytes or raise the
  typed :class:`~mrctl.io.base.FrameError` / :class:`~mrctl.io.base.DeviceError`;
* Modbus exception-code names (the spellings of pymodbus 3.16.1's
  ``ExcCodes``, so messages read the same whether or not pymodbus is
  installed; a test compares the two tables);
* the *precompiled per-tick transactions* (:class:`Tx`): each request
  frame of a tick is built once, and a tick only patches the write block,
  the TCP transaction id or the RTU CRC into it;
* RTU wire time (the feasibility check and the default RTU deadline).
"""

from __future__ import annotations

import math
import struct

from mrctl.io.base import DeviceError, FrameError
from mrctl.io.registers import RegisterMap

__all__ = [
    "FC_READ_HOLDING",
    "FC_READ_INPUT",
    "FC_WRITE_MULTIPLE",
    "FC_READ_WRITE",
    "EXCEPTION_NAMES",
    "ILLEGAL_FUNCTION",
    "MBAP",
    "MAX_ADU_TCP",
    "Tx",
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
    "plan_transactions",
    "rtu_tick_frames",
    "rtu_transaction_wire_time_s",
    "rtu_bits_per_char",
    "default_rtu_timeout_s",
]

FC_READ_HOLDING = 3
FC_READ_INPUT = 4
FC_WRITE_MULTIPLE = 16
FC_READ_WRITE = 23
_TABLE_FC = {"holding": FC_READ_HOLDING, "input": FC_READ_INPUT}

#: Modbus exception code → name, spelled as pymodbus 3.16.1's ``ExcCodes``
#: (its GATEWAY_PATH_UNAVIABLE included) so messages do not depend on it.
EXCEPTION_NAMES: dict[int, str] = {
    1: "ILLEGAL_FUNCTION",
    2: "ILLEGAL_ADDRESS",
    3: "ILLEGAL_VALUE",
    4: "DEVICE_FAILURE",
    5: "ACKNOWLEDGE",
    6: "DEVICE_BUSY",
    7: "NEGATIVE_ACKNOWLEDGE",
    8: "MEMORY_PARITY_ERROR",
    10: "GATEWAY_PATH_UNAVIABLE",
    11: "GATEWAY_NO_RESPONSE",
}
ILLEGAL_FUNCTION = 1

#: Device turnaround + OS latency allowance on top of RTU wire time (as SerialLink).
RTU_TURNAROUND_ALLOWANCE_S = 250e-6
MIN_REPLY_TIMEOUT_S = 0.5e-3

MBAP = struct.Struct(">HHHB")  # tid, protocol id (0), length (unit + pdu), unit
MAX_ADU_TCP = 260


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
    """Name of a Modbus exception code (:data:`EXCEPTION_NAMES`), or hex."""
    return EXCEPTION_NAMES.get(code) or f"0x{code:02X}"



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
    return MBAP.pack(tid & 0xFFFF, 0, len(pdu) + 1, unit) + bytes(pdu)


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
    rtid, pid, length, runit = MBAP.unpack_from(frame, 0)
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


# --------------------------------------------------------------------------
# Precompiled per-tick transactions
class Tx:
    """One request of a tick: its frame template and what its response must look like.

    ``adu`` is the whole request frame, built once; per tick the link packs
    the write block at ``data_off`` (``writes``), patches the TCP
    transaction id into bytes 0-1 or the RTU CRC into the last two (the CRC
    of the constant bytes before the write data is ``crc_prefix``, over
    ``crc_prefix_len`` bytes). ``resp_len``: the length of a normal
    response; ``resp_tail`` (TCP): the expected response bytes 2..8 (FC16:
    all after the transaction id), compared in one slice on the fast path.
    ``block``: which read block the response carries (-1: none, FC16)."""

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

    def build_tcp(self, unit: int) -> "Tx":
        self.adu = bytearray(mbap_frame(0, unit, self._pdu))
        self.data_off = 7 + (self._data_off_pdu or 0)
        self.resp_len = 7 + (5 if self.fc == FC_WRITE_MULTIPLE else 2 + 2 * self.n_regs)
        # Expected reply after the tid: constant except the register data.
        if self.fc == FC_WRITE_MULTIPLE:
            self.resp_tail = mbap_frame(0, unit, self._pdu[:5])[2:]
        else:
            self.resp_tail = mbap_frame(0, unit, bytes((self.fc, 2 * self.n_regs)) + bytes(2 * self.n_regs))[2:9]
        return self

    def build_rtu(self, unit: int) -> "Tx":
        self.adu = bytearray(rtu_frame(unit, self._pdu))
        self.data_off = 1 + (self._data_off_pdu or 0)
        # CRC of the constant bytes before the write data, computed once.
        self.crc_prefix_len = self.data_off if self.writes else len(self.adu) - 2
        self.crc_prefix = crc16_modbus(self.adu[: self.crc_prefix_len])
        self.resp_len = 8 if self.fc == FC_WRITE_MULTIPLE else 5 + 2 * self.n_regs
        return self


def plan_transactions(rmap: RegisterMap, use_fc23: bool, transport: str, unit: int) -> list[Tx]:
    """The requests of one tick, framed for ``transport`` ("tcp" or "rtu"):
    one FC23, or FC16 then one FC3/FC4 per read block."""
    wb = rmap.write_block
    zeros = bytes(2 * wb.count)
    if use_fc23:
        rb = rmap.read_blocks[0]
        pdu = read_write_request_pdu(rb.address, rb.count, wb.address, zeros)
        txs = [Tx(FC_READ_WRITE, pdu, rb.count, 10, True, 0)]
    else:
        txs = [Tx(FC_WRITE_MULTIPLE, write_request_pdu(wb.address, zeros), wb.count, 6, True)]
        for i, b in enumerate(rmap.read_blocks):
            fc = _TABLE_FC[b.table]
            txs.append(Tx(fc, read_request_pdu(fc, b.address, b.count), b.count, None, False, i))
    return [t.build_tcp(unit) if transport == "tcp" else t.build_rtu(unit) for t in txs]
