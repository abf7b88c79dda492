"""LabJack's Modbus Feedback (function 76) as the emulated T7 serves it.

The request's frames (T-series datasheet, "Protocol Details [Direct Modbus TCP]", "Modbus Feedback
(MBFB, function #76)") are executed in order: ``0x00, address, count`` reads ``count`` registers,
``0x01, address, count, data`` writes them. The reply is 76 and the reads' data back to back. A
frame the device refuses ends the request with a Modbus exception; the writes before it stay done
(what a real T7 does there is not documented: nothing is rolled back here).
"""

from __future__ import annotations

import struct
from typing import Callable

from hil_sim.modbus_wire import ILLEGAL_DATA_VALUE
from mrctl.io.modbus.codec import MAX_ADU_TCP

__all__ = ["handle_mbfb"]

_BHB = struct.Struct(">BHB")


def handle_mbfb(pdu: bytes, read: Callable[[int, int], bytes | int], write: Callable[[int, bytes], int | None],
                exc: Callable[[int], bytes]) -> bytes:
    """The reply PDU to an MBFB request PDU (its function code first, as the request's);
    ``read``/``write`` return an exception code when refused."""
    out, pos, n = bytearray(pdu[:1]), 1, len(pdu)
    if n < 5:
        return exc(ILLEGAL_DATA_VALUE)
    while pos < n:
        if pos + 4 > n:
            return exc(ILLEGAL_DATA_VALUE)
        kind, address, count = _BHB.unpack_from(pdu, pos)
        pos += 4
        if kind == 0:
            data = read(address, count)
            if isinstance(data, int):
                return exc(data)
            out += data
        elif kind == 1:
            if pos + 2 * count > n or count < 1:
                return exc(ILLEGAL_DATA_VALUE)
            err = write(address, pdu[pos:pos + 2 * count])
            pos += 2 * count
            if err is not None:
                return exc(err)
        else:
            return exc(ILLEGAL_DATA_VALUE)
    if len(out) + 7 > MAX_ADU_TCP:
        # the reply would not fit one standard Modbus TCP ADU: refused here, where a T7 goes to its
        # 1040-byte Ethernet packet (datasheet 6.0); stricter than the device, and mrctl's ticks stay within
        return exc(ILLEGAL_DATA_VALUE)
    return bytes(out)
