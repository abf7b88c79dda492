"""LabJack's Modbus Feedback (MBFB, function 76) and the plain requests a preset link falls back to.

Frame layout (T-series datasheet, "Protocol Details [Direct Modbus TCP]", "Modbus Feedback
(MBFB, function #76)"; the same layout is in ``labjack/C_CPP_LJM``
``more/utilities/stepwise_feedback.c`` and the ``async_labjack`` crate's
``src/modbus_feedback/mbfb.rs``): after the MBAP header and the function code 76, one frame per
operation, executed in order:

* read:  ``0x00``, address (UINT16, big-endian), number of registers (1 byte);
* write: ``0x01``, address, number of registers, then the registers' data (2 bytes each).

The response is the MBAP header, 76, then the read frames' data back to back in request order
(writes return nothing); a refused request is the usual Modbus exception (``76 | 0x80``, code).

The function code is the device preset's (``modbus.mbfb``: 76 on a T7). Everything here is pure
bytes, built once per link (a tick only patches the written values and the transaction id into
the request), the MBAP header and the FC3/FC16 PDUs by :mod:`mrctl.io.modbus.codec`. :class:`Op`
lists are the tick's operations; the same list serves both protocols: one MBFB request, or one
FC3/FC16 request per operation.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from mrctl.io.modbus.codec import (
    FC_READ_HOLDING as FC_READ, FC_WRITE_MULTIPLE as FC_WRITE, MAX_ADU_TCP, mbap_frame, read_request_pdu,
    write_request_pdu,
)

__all__ = ["FC_READ", "FC_WRITE", "STRUCTS", "Op", "Request", "as_stored", "mbfb_request", "plain_requests"]

_FMT = {"float32": "f", "uint32": "I", "uint16": "H"}
_NREGS = {"float32": 2, "uint32": 2, "uint16": 1}
#: a preset's register types, big-endian (high word first), as a T7 sends them
STRUCTS = {dtype: struct.Struct(">" + f) for dtype, f in _FMT.items()}


def as_stored(dtype: str, value: object) -> object:
    """``value`` as a register of ``dtype`` holds it (a float32 rounded): what a read-back returns."""
    st = STRUCTS[dtype]
    return st.unpack(st.pack(value))[0]


@dataclass(frozen=True)
class Op:
    """One operation of the tick: read ``count`` values of ``dtype`` from ``address`` on, or write one."""

    write: bool
    address: int
    dtype: str
    count: int = 1

    @property
    def n_regs(self) -> int:
        return _NREGS[self.dtype] * self.count


class Request:
    """One prebuilt request: ``adu`` (MBAP with tid 0, patched per send), where each written value
    goes (``slots``: struct and offset per write op, in op order), the reply's function code, its
    exact length, the struct that decodes its data (reads in op order) and where that data starts
    (``data_off``). ``tail``: the reply's bytes from offset 2 on that do not vary (protocol id 0,
    MBAP length, unit, function; FC3's byte count, FC16's echoed address and count), so one
    ``startswith`` checks a whole reply but its transaction id and data."""

    __slots__ = ("adu", "slots", "fc", "resp_len", "decode", "data_off", "tail")

    def __init__(self, adu: bytearray, slots: list[tuple[struct.Struct, int]], fc: int, resp_len: int,
                 decode: struct.Struct | None) -> None:
        self.adu, self.slots, self.fc, self.resp_len, self.decode = adu, slots, fc, resp_len, decode
        self.data_off = resp_len if decode is None else resp_len - decode.size
        length = resp_len - 6
        tail = bytes((0, 0, length >> 8, length & 0xFF, adu[6], fc))
        if fc == FC_READ:
            tail += bytes((resp_len - 9,))
        elif fc == FC_WRITE:
            tail += bytes(adu[8:12])
        self.tail = tail


def _adu(pdu: bytes, unit: int) -> bytearray:
    return bytearray(mbap_frame(0, unit, pdu))


def mbfb_request(ops: list[Op], unit: int, fc: int) -> Request:
    """The whole tick in one MBFB request (function ``fc``, the preset's ``modbus.mbfb``)."""
    body = bytearray((fc,))
    slots: list[tuple[struct.Struct, int]] = []
    rfmt = ">"
    for op in ops:
        if not 1 <= op.n_regs <= 255:
            raise ValueError(f"MBFB frame of {op.n_regs} registers at {op.address}")
        body += struct.pack(">BHB", 1 if op.write else 0, op.address, op.n_regs)
        if op.write:
            st = STRUCTS[op.dtype]
            slots.append((st, 7 + len(body)))
            body += bytes(st.size)
        else:
            rfmt += _FMT[op.dtype] * op.count
    dec = struct.Struct(rfmt)
    adu = _adu(bytes(body), unit)
    if len(adu) > MAX_ADU_TCP or 8 + dec.size > MAX_ADU_TCP:
        raise ValueError(f"MBFB request of {len(adu)} bytes (reply {8 + dec.size}): beyond a Modbus TCP ADU "
                         f"({MAX_ADU_TCP})")
    return Request(adu, slots, fc, 8 + dec.size, dec if dec.size else None)


def plain_requests(ops: list[Op], unit: int) -> list[Request]:
    """The same tick as one FC3 or FC16 per operation (devices or firmware without MBFB)."""
    out = []
    for op in ops:
        st = struct.Struct(">" + _FMT[op.dtype] * op.count)
        if op.write:
            adu = _adu(write_request_pdu(op.address, bytes(st.size)), unit)
            out.append(Request(adu, [(st, len(adu) - st.size)], FC_WRITE, 12, None))
        else:
            adu = _adu(read_request_pdu(FC_READ, op.address, op.n_regs), unit)
            out.append(Request(adu, [], FC_READ, 9 + st.size, st))
    return out
