"""What the Modbus servers share on the wire: where a request ends in a byte
stream (MBAP for TCP, function-code lengths for RTU), the exception codes,
and how often the servers' waits look up. The device that answers the
requests is :mod:`hil_sim.modbus_device`; its servers are
:mod:`hil_sim.modbus_tcp` and :mod:`hil_sim.modbus_rtu`.
"""

from __future__ import annotations

from mrctl.io.base import FrameError
from mrctl.io.modbus import FC_READ_WRITE, FC_WRITE_MULTIPLE

__all__ = [
    "FAULT_POLL_S",
    "GATEWAY_NO_RESPONSE",
    "IDLE_POLL_S",
    "ILLEGAL_DATA_ADDRESS",
    "ILLEGAL_DATA_VALUE",
    "ILLEGAL_FUNCTION",
    "SLAVE_DEVICE_FAILURE",
    "mbap_frame_length",
    "rtu_request_length",
]

ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03
SLAVE_DEVICE_FAILURE = 0x04
GATEWAY_NO_RESPONSE = 0x0B

#: how often the servers' idle waits look at ``stop`` (s) ...
IDLE_POLL_S = 0.05
#: ... and at the fault bits, when faults are scheduled (s)
FAULT_POLL_S = 0.001


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
