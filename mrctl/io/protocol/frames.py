"""Compact binary serial protocol, version 1 (spec: docs/protocol.md).

Every frame::

    A5 5A | version u8 | type u8 | payload_len u8 | seq u32 | payload | crc u16

little-endian, packed, fixed payload size per type, CRC-16/CCITT-FALSE over
every byte before the CRC (preamble included). Per tick the host sends one
SETPOINT (17 bytes) and the device answers one SAMPLE (37 bytes).

Why these choices:

* a length byte in the header lets a receiver delimit and CRC-check frames of
  a version or type it does not know, so a version mismatch is *reported*
  (:class:`ProtocolVersionError`) instead of looking like line noise;
* ``binascii.crc_hqx`` is exactly CRC-16/CCITT-FALSE when seeded with 0xFFFF,
  C-fast and in the stdlib; firmware computes it in ~10 lines of C;
* fixed sizes let both sides do exact-length reads and compute wire time.

Decoding never raises anything but :class:`~mrctl.io.base.FrameError` and its
subclasses; the streaming decoder (:mod:`mrctl.io.protocol.decoder`) never
raises at all.
"""

from __future__ import annotations

import enum
import struct
from binascii import crc_hqx
from typing import NamedTuple, Union

from mrctl.io.base import FrameError

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
    "ChannelQueryFrame",
    "ChannelListFrame",
    "MAX_CHANNELS",
    "encode_channel_query",
    "encode_channel_list",
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
    "wire_time_s",
    "exchange_wire_time_s",
]

PREAMBLE = b"\xa5\x5a"
PROTOCOL_VERSION = 1
CRC_INIT = 0xFFFF
#: Longest payload any version may declare; bounds how long a receiver waits
#: on a candidate header before judging it (garbage can't stall it longer).
MAX_PAYLOAD = 64
#: Device watchdog the host asks for by default (ms without a valid SETPOINT
#: before the device applies 0 A). 0 on the wire means "device default".
DEFAULT_WATCHDOG_MS = 50

_U32 = 0xFFFFFFFF


class FrameType(enum.IntEnum):
    """Frame type byte. Bit 7 set = device → host."""

    SETPOINT = 0x01  #: host → device
    SAMPLE = 0x81  #: device → host, reply to SETPOINT
    ERROR = 0xE1  #: device → host, NAK instead of a SAMPLE
    CHANNEL_QUERY = 0x02  #: host → device: which extra channels do you have? (§2.5)
    CHANNEL_LIST = 0x82  #: device → host: their names (variable length)
    SAMPLE_X = 0x83  #: device → host: a SAMPLE followed by the channels' values (variable length)


class SetpointFlag(enum.IntFlag):
    """SETPOINT ``flags`` bits."""

    ENABLE = 0x01  #: clear → device applies 0 A and disables the output
    CLEAR_FAULTS = 0x02  #: ask the device to clear latched faults/status
    #: device pacing: apply this setpoint at the device's next sampling tick
    #: and answer after that tick, with its sample (docs/protocol.md §6.1)
    SYNC = 0x04
    #: answer with SAMPLE_X (the SAMPLE and the extra channels, §2.5); a device
    #: without channels ignores it and answers a plain SAMPLE
    CHANNELS = 0x08


class ErrorCode(enum.IntEnum):
    """ERROR frame ``code`` values."""

    BAD_CRC = 0x01  #: a frame with a plausible header failed its CRC
    BAD_VERSION = 0x02  #: version not supported; ``detail`` = device's version
    UNKNOWN_TYPE = 0x03  #: valid frame of a type the device doesn't handle
    BAD_LENGTH = 0x04  #: payload_len wrong for the type
    INTERNAL = 0xFF  #: device-internal failure


# --- layouts ---------------------------------------------------------------
_HEADER = struct.Struct("<2sBBBI")  # preamble, version, type, payload_len, seq
HEADER_SIZE = _HEADER.size  # 9
_CRC = struct.Struct("<H")
CRC_SIZE = _CRC.size  # 2
_SEQ = struct.Struct("<I")
_SEQ_OFFSET = 5

_SETPOINT_PAYLOAD = struct.Struct("<fBB")  # current_A, flags, watchdog_ms
_SAMPLE_PAYLOAD = struct.Struct("<IIffffH")  # echo_seq, t_dev_us, x_m, v_mps, F_N, current_A, status
_ERROR_PAYLOAD = struct.Struct("<IBB")  # echo_seq, code, detail

_PAYLOAD_LEN: dict[int, int] = {
    FrameType.SETPOINT: _SETPOINT_PAYLOAD.size,  # 6
    FrameType.SAMPLE: _SAMPLE_PAYLOAD.size,  # 26
    FrameType.ERROR: _ERROR_PAYLOAD.size,  # 6
    FrameType.CHANNEL_QUERY: 0,
}
#: most extra channels a SAMPLE_X carries: (MAX_PAYLOAD − 26) // 4
MAX_CHANNELS = 9
SETPOINT_FRAME_SIZE = HEADER_SIZE + _SETPOINT_PAYLOAD.size + CRC_SIZE  # 17
SAMPLE_FRAME_SIZE = HEADER_SIZE + _SAMPLE_PAYLOAD.size + CRC_SIZE  # 37
ERROR_FRAME_SIZE = HEADER_SIZE + _ERROR_PAYLOAD.size + CRC_SIZE  # 17
#: Bytes on the wire per tick (request + reply).
EXCHANGE_BYTES = SETPOINT_FRAME_SIZE + SAMPLE_FRAME_SIZE  # 54
_MIN_FRAME = HEADER_SIZE + CRC_SIZE

# Hot-path SETPOINT: only seq + payload change, packed in one call at offset 5.
_SETPOINT_VAR = struct.Struct("<IfBB")


# --- frames ----------------------------------------------------------------
class SetpointFrame(NamedTuple):
    """Host → device: apply this current."""

    seq: int  #: host sequence number (uint32)
    current_A: float  #: setpoint, A (float32 on the wire)
    flags: int = SetpointFlag.ENABLE  #: :class:`SetpointFlag` bits
    watchdog_ms: int = DEFAULT_WATCHDOG_MS  #: 0 = device default


class SampleFrame(NamedTuple):
    """Device → host: the latest measurement, answering one SETPOINT."""

    seq: int  #: device sequence number (uint32, +1 per frame sent)
    echo_seq: int  #: host seq of the SETPOINT this answers
    t_dev_us: int  #: device time of the measurement, µs (uint32, wraps)
    x_m: float
    v_mps: float
    F_N: float  #: NaN = no load cell
    current_A: float  #: current actually applied, A
    status: int  #: :class:`mrctl.io.base.Status` bits
    channels: tuple[float, ...] = ()  #: SAMPLE_X: the extra channels, in CHANNEL_LIST order


class ChannelQueryFrame(NamedTuple):
    """Host → device: which extra channels do you have?"""

    seq: int


class ChannelListFrame(NamedTuple):
    """Device → host: the names of its extra channels (ASCII, in SAMPLE_X order)."""

    seq: int
    echo_seq: int  #: the CHANNEL_QUERY's seq
    names: tuple[str, ...]


class ErrorFrame(NamedTuple):
    """Device → host NAK."""

    seq: int  #: device sequence number
    echo_seq: int  #: offending frame's seq, or last good host seq for BAD_CRC
    code: int  #: :class:`ErrorCode`
    detail: int = 0  #: code-specific (BAD_VERSION: device's version)


class ForeignFrame(NamedTuple):
    """A CRC-valid frame of another protocol version (fields not interpreted)."""

    version: int
    ftype: int
    seq: int
    payload: bytes


Frame = Union[SetpointFrame, SampleFrame, ErrorFrame, ForeignFrame, ChannelQueryFrame, ChannelListFrame]


class ProtocolVersionError(FrameError):
    """The peer speaks another protocol version. Not transient: fix firmware/config."""

    def __init__(self, expected: int, received: int) -> None:
        self.expected = expected
        self.received = received
        super().__init__(
            f"protocol version mismatch: host speaks v{expected}, device sent v{received}"
        )


# --- CRC / wire time ---------------------------------------------------------
def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0)."""
    return crc_hqx(data, CRC_INIT)


def wire_time_s(frame_bytes: int, baud: float, bits_per_byte: int = 10) -> float:
    """Seconds to shift ``frame_bytes`` at ``baud`` (8N1 = 10 bits/byte).

    Pure transmission time: excludes device turnaround, OS and USB latency.
    """
    if not baud > 0:
        raise ValueError(f"baud must be > 0, got {baud!r}")
    return frame_bytes * bits_per_byte / baud


def exchange_wire_time_s(baud: float, bits_per_byte: int = 10) -> float:
    """Wire time of one tick's SETPOINT + SAMPLE at ``baud``."""
    return wire_time_s(EXCHANGE_BYTES, baud, bits_per_byte)


# --- encoding ------------------------------------------------------------------
def encode_frame(ftype: int, seq: int, payload: bytes, version: int = PROTOCOL_VERSION) -> bytes:
    """Frame arbitrary payload bytes (any type/version); for tests and tools."""
    if len(payload) > 255:
        raise ValueError("payload longer than 255 bytes")
    body = _HEADER.pack(PREAMBLE, version, ftype, len(payload), seq & _U32) + payload
    return body + _CRC.pack(crc_hqx(body, CRC_INIT))


def encode_setpoint(
    seq: int,
    current_A: float,
    flags: int = SetpointFlag.ENABLE,
    watchdog_ms: int = DEFAULT_WATCHDOG_MS,
) -> bytes:
    """SETPOINT frame (17 bytes). Allocates; the loop uses :class:`SetpointEncoder`."""
    return encode_frame(
        FrameType.SETPOINT, seq, _SETPOINT_PAYLOAD.pack(current_A, flags, watchdog_ms)
    )


def encode_sample(
    seq: int,
    echo_seq: int,
    t_dev_us: int,
    x_m: float,
    v_mps: float,
    F_N: float,
    current_A: float,
    status: int,
    channels: tuple[float, ...] = (),
) -> bytes:
    """SAMPLE frame (37 bytes), or SAMPLE_X with ``channels``; device side, fakes and tests."""
    payload = _SAMPLE_PAYLOAD.pack(
        echo_seq & _U32, t_dev_us & _U32, x_m, v_mps, F_N, current_A, status
    )
    if channels:
        if len(channels) > MAX_CHANNELS:
            raise ValueError(f"at most {MAX_CHANNELS} channels in a SAMPLE_X, got {len(channels)}")
        return encode_frame(FrameType.SAMPLE_X, seq, payload + struct.pack(f"<{len(channels)}f", *channels))
    return encode_frame(FrameType.SAMPLE, seq, payload)


def encode_channel_query(seq: int) -> bytes:
    """CHANNEL_QUERY frame (11 bytes)."""
    return encode_frame(FrameType.CHANNEL_QUERY, seq, b"")


def encode_channel_list(seq: int, echo_seq: int, names: tuple[str, ...]) -> bytes:
    """CHANNEL_LIST frame: echo_seq, then the names, comma-separated ASCII."""
    text = ",".join(names).encode("ascii")
    if len(text) + 4 > MAX_PAYLOAD or len(names) > MAX_CHANNELS:
        raise ValueError(f"channel names too long for one frame: {names!r}")
    return encode_frame(FrameType.CHANNEL_LIST, seq, _SEQ.pack(echo_seq & _U32) + text)


def encode_error(seq: int, echo_seq: int, code: int, detail: int = 0) -> bytes:
    """ERROR frame (17 bytes)."""
    return encode_frame(FrameType.ERROR, seq, _ERROR_PAYLOAD.pack(echo_seq & _U32, code, detail))


def encode(frame: Frame) -> bytes:
    """Encode any decoded frame object back to bytes (round-trip helper)."""
    if isinstance(frame, SetpointFrame):
        return encode_setpoint(*frame)
    if isinstance(frame, SampleFrame):
        return encode_sample(*frame)
    if isinstance(frame, ErrorFrame):
        return encode_error(*frame)
    if isinstance(frame, ChannelQueryFrame):
        return encode_channel_query(frame.seq)
    if isinstance(frame, ChannelListFrame):
        return encode_channel_list(*frame)
    if isinstance(frame, ForeignFrame):
        return encode_frame(frame.ftype, frame.seq, frame.payload, frame.version)
    raise TypeError(f"not a frame: {frame!r}")


class SetpointEncoder:
    """Allocation-free SETPOINT encoding for the 1 kHz hot path.

    The constant header bytes are written once; each call packs seq and
    payload into the same preallocated buffer and appends the CRC. The
    returned bytearray is reused: send it before the next call.
    """

    __slots__ = ("_buf", "_body")

    def __init__(self) -> None:
        self._buf = bytearray(SETPOINT_FRAME_SIZE)
        _HEADER.pack_into(
            self._buf, 0, PREAMBLE, PROTOCOL_VERSION, FrameType.SETPOINT, _SETPOINT_PAYLOAD.size, 0
        )
        self._body = memoryview(self._buf)[: SETPOINT_FRAME_SIZE - CRC_SIZE]

    def encode(
        self,
        seq: int,
        current_A: float,
        flags: int = SetpointFlag.ENABLE,
        watchdog_ms: int = DEFAULT_WATCHDOG_MS,
    ) -> bytearray:
        buf = self._buf
        _SETPOINT_VAR.pack_into(buf, _SEQ_OFFSET, seq & _U32, current_A, flags, watchdog_ms)
        _CRC.pack_into(buf, SETPOINT_FRAME_SIZE - CRC_SIZE, crc_hqx(self._body, CRC_INIT))
        return buf


# --- decoding ----------------------------------------------------------------
def _parse(buf: bytes | bytearray, i: int, end: int) -> Frame | None:
    """Fields of the CRC-valid frame buf[i:end]; None for an unknown type of our version."""
    version = buf[i + 2]
    ftype = buf[i + 3]
    seq = _SEQ.unpack_from(buf, i + _SEQ_OFFSET)[0]
    p = i + HEADER_SIZE
    if version != PROTOCOL_VERSION:
        return ForeignFrame(version, ftype, seq, bytes(buf[p : end - CRC_SIZE]))
    if ftype == FrameType.SAMPLE:
        return SampleFrame(seq, *_SAMPLE_PAYLOAD.unpack_from(buf, p))
    if ftype == FrameType.SETPOINT:
        return SetpointFrame(seq, *_SETPOINT_PAYLOAD.unpack_from(buf, p))
    if ftype == FrameType.ERROR:
        return ErrorFrame(seq, *_ERROR_PAYLOAD.unpack_from(buf, p))
    plen = end - CRC_SIZE - p
    if ftype == FrameType.SAMPLE_X and plen >= _SAMPLE_PAYLOAD.size and (plen - _SAMPLE_PAYLOAD.size) % 4 == 0:
        n = (plen - _SAMPLE_PAYLOAD.size) // 4
        return SampleFrame(seq, *_SAMPLE_PAYLOAD.unpack_from(buf, p),
                           struct.unpack_from(f"<{n}f", buf, p + _SAMPLE_PAYLOAD.size))
    if ftype == FrameType.CHANNEL_QUERY:
        return ChannelQueryFrame(seq)
    if ftype == FrameType.CHANNEL_LIST and plen >= 4:
        text = bytes(buf[p + 4:end - CRC_SIZE]).decode("ascii", "replace")
        return ChannelListFrame(seq, _SEQ.unpack_from(buf, p)[0], tuple(n for n in text.split(",") if n))
    return None


def decode_frame(data: bytes | bytearray | memoryview) -> Frame:
    """Decode exactly one complete frame.

    Raises :class:`FrameError` (short, preamble, length, CRC, unknown type)
    or :class:`ProtocolVersionError` (CRC-valid frame of another version).
    """
    raw = bytes(data)
    n = len(raw)
    if n < _MIN_FRAME:
        raise FrameError(f"frame too short: {n} bytes, minimum {_MIN_FRAME}")
    if raw[:2] != PREAMBLE:
        raise FrameError(f"bad preamble {raw[:2].hex(' ')}, expected a5 5a")
    version, ftype, plen = raw[2], raw[3], raw[4]
    if n != HEADER_SIZE + plen + CRC_SIZE:
        raise FrameError(f"frame is {n} bytes but header declares a {plen}-byte payload")
    crc_rx = raw[-2] | (raw[-1] << 8)
    crc_calc = crc_hqx(raw[:-2], CRC_INIT)
    if crc_rx != crc_calc:
        raise FrameError(f"CRC mismatch: frame has 0x{crc_rx:04X}, computed 0x{crc_calc:04X}")
    if version != PROTOCOL_VERSION:
        raise ProtocolVersionError(PROTOCOL_VERSION, version)
    expected = _PAYLOAD_LEN.get(ftype)
    if expected is not None and plen != expected:
        raise FrameError(f"type 0x{ftype:02X} needs a {expected}-byte payload, got {plen}")
    frame = _parse(raw, 0, n)
    if frame is None:  # an unknown type, or a variable-length one of a wrong length
        raise FrameError(f"unknown frame type 0x{ftype:02X}" if expected is None and ftype not in _VARIABLE
                         else f"type 0x{ftype:02X}: bad payload length {plen}")
    return frame


_VARIABLE = (FrameType.SAMPLE_X, FrameType.CHANNEL_LIST)
