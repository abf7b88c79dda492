"""The compact binary serial protocol, version 1 (spec: docs/protocol.md).

* :mod:`.frames`: the frame layout, types and flags, CRC, wire time,
  encoding (:class:`SetpointEncoder` for the hot path) and decoding one
  complete frame;
* :mod:`.decoder`: :class:`FrameDecoder`, finding frames in a byte stream.

The names below are the package's interface (the serial link, hil_sim, the
benchmarks and the tests import them from here).
"""

from mrctl.io.protocol.decoder import FrameDecoder
from mrctl.io.protocol.frames import (
    CRC_INIT,
    CRC_SIZE,
    DEFAULT_WATCHDOG_MS,
    ERROR_FRAME_SIZE,
    EXCHANGE_BYTES,
    HEADER_SIZE,
    MAX_PAYLOAD,
    PREAMBLE,
    PROTOCOL_VERSION,
    SAMPLE_FRAME_SIZE,
    SETPOINT_FRAME_SIZE,
    ErrorCode,
    ErrorFrame,
    ForeignFrame,
    Frame,
    FrameType,
    ProtocolVersionError,
    SampleFrame,
    SetpointEncoder,
    SetpointFlag,
    SetpointFrame,
    crc16,
    decode_frame,
    encode,
    encode_error,
    encode_frame,
    encode_sample,
    encode_setpoint,
    exchange_wire_time_s,
    wire_time_s,
)

__all__ = [
    "PREAMBLE",
    "PROTOCOL_VERSION",
    "HEADER_SIZE",
    "CRC_SIZE",
    "CRC_INIT",
    "MAX_PAYLOAD",
    "DEFAULT_WATCHDOG_MS",
    "FrameType",
    "SetpointFlag",
    "ErrorCode",
    "SETPOINT_FRAME_SIZE",
    "SAMPLE_FRAME_SIZE",
    "ERROR_FRAME_SIZE",
    "EXCHANGE_BYTES",
    "SetpointFrame",
    "SampleFrame",
    "ErrorFrame",
    "ForeignFrame",
    "Frame",
    "ProtocolVersionError",
    "crc16",
    "encode_frame",
    "encode_setpoint",
    "encode_sample",
    "encode_error",
    "encode",
    "decode_frame",
    "SetpointEncoder",
    "FrameDecoder",
    "wire_time_s",
    "exchange_wire_time_s",
]
