"""The serial protocol's streaming decoder: arbitrary chunks in, whole valid frames out.

Frame layout, CRC and the frame types are :mod:`mrctl.io.protocol.frames`'s;
this module finds frames in a byte stream that may hold noise, partial
frames, false preambles and frames of other versions (docs/protocol.md §3).
"""

from __future__ import annotations

from binascii import crc_hqx

from mrctl.io.protocol.frames import (
    _PAYLOAD_LEN,
    CRC_INIT,
    CRC_SIZE,
    HEADER_SIZE,
    MAX_PAYLOAD,
    PREAMBLE,
    PROTOCOL_VERSION,
    SAMPLE_FRAME_SIZE,
    ForeignFrame,
    Frame,
    _parse,
)

__all__ = ["FrameDecoder"]

_OK, _INCOMPLETE, _BAD_HEADER, _BAD_CRC = range(4)


class FrameDecoder:
    """Streaming decoder: feed arbitrary chunks, get whole valid frames.

    Resynchronisation: scan for the preamble; check the header (version ≠ 0,
    payload_len ≤ MAX_PAYLOAD and, for our version and a known type, exactly
    the type's length); wait for the declared length; check the CRC. On any
    failure skip ONE byte and rescan, so a frame hidden behind a false
    preamble is still found. While a candidate is incomplete, a complete
    valid frame starting inside it wins (a garbage header with a long length
    cannot hold back a real frame already in the buffer).

    Never raises. Frames of our version and an unknown type are CRC-checked
    and dropped (``unknown_frames``); CRC-valid frames of another version are
    returned as :class:`ForeignFrame` so the caller can report a version
    mismatch. The buffer never holds more than one candidate (≤ 75 bytes)
    plus the last chunk.
    """

    __slots__ = (
        "_buf",
        "frames",
        "crc_errors",
        "header_errors",
        "bytes_discarded",
        "unknown_frames",
        "foreign_frames",
    )

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames = 0  #: valid frames returned
        self.crc_errors = 0  #: candidates with a plausible header that failed the CRC
        self.header_errors = 0  #: preambles followed by an impossible header
        self.bytes_discarded = 0  #: bytes not part of any returned frame
        self.unknown_frames = 0  #: CRC-valid frames of our version, unknown type (dropped)
        self.foreign_frames = 0  #: CRC-valid frames of another version (returned)

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Drop buffered bytes (counted as discarded); keep counters."""
        self.bytes_discarded += len(self._buf)
        self._buf.clear()

    def bytes_needed(self, expected_size: int = SAMPLE_FRAME_SIZE) -> int:
        """Minimum bytes to read before the next frame can complete (≥ 1).

        Used for exact-length reads: with an empty buffer that is the size of
        the frame we expect; mid-frame, the rest of the declared length.
        """
        buf = self._buf
        n = len(buf)
        if n >= 5 and buf[0] == 0xA5 and buf[1] == 0x5A:
            total = HEADER_SIZE + buf[4] + CRC_SIZE
        else:
            total = expected_size
        return total - n if total > n else 1

    def _probe(self, buf: bytearray, i: int, n: int) -> tuple[int, int]:
        """Classify the candidate at buf[i] (which holds the preamble)."""
        if n - i < 5:
            return _INCOMPLETE, 0
        version = buf[i + 2]
        plen = buf[i + 4]
        if version == 0 or plen > MAX_PAYLOAD:
            return _BAD_HEADER, 0
        if version == PROTOCOL_VERSION:
            expected = _PAYLOAD_LEN.get(buf[i + 3])
            if expected is not None and plen != expected:
                return _BAD_HEADER, 0
        end = i + HEADER_SIZE + plen + CRC_SIZE
        if end > n:
            return _INCOMPLETE, end
        if crc_hqx(buf[i : end - CRC_SIZE], CRC_INIT) != buf[end - 2] | (buf[end - 1] << 8):
            return _BAD_CRC, end
        return _OK, end

    def _lookahead(self, buf: bytearray, start: int, n: int) -> int:
        """Index of the first complete valid frame at or after ``start``, or -1."""
        j = buf.find(PREAMBLE, start)
        while j >= 0:
            if self._probe(buf, j, n)[0] == _OK:
                return j
            j = buf.find(PREAMBLE, j + 1)
        return -1

    def feed(self, data: bytes | bytearray | memoryview = b"") -> list[Frame]:
        """Append ``data`` and return every frame now complete, in order."""
        buf = self._buf
        if data:
            buf += data
        out: list[Frame] = []
        n = len(buf)
        pos = 0
        discarded = 0
        while pos < n:
            i = buf.find(PREAMBLE, pos)
            if i < 0:
                # Keep a trailing 0xA5: it may be the first preamble byte.
                keep = 1 if buf[n - 1] == 0xA5 else 0
                discarded += n - keep - pos
                pos = n - keep
                break
            discarded += i - pos
            pos = i
            kind, end = self._probe(buf, i, n)
            if kind == _OK:
                frame = _parse(buf, i, end)
                if frame is None:
                    self.unknown_frames += 1
                    discarded += end - i
                else:
                    if isinstance(frame, ForeignFrame):
                        self.foreign_frames += 1
                    out.append(frame)
                pos = end
            elif kind == _INCOMPLETE:
                j = self._lookahead(buf, i + 1, n)
                if j < 0:
                    break  # wait for more bytes
                discarded += j - i
                pos = j
            else:
                if kind == _BAD_CRC:
                    self.crc_errors += 1
                else:
                    self.header_errors += 1
                discarded += 1
                pos = i + 1
        if pos:
            del buf[:pos]
        self.bytes_discarded += discarded
        self.frames += len(out)
        return out
