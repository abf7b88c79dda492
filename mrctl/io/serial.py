"""SerialLink: the compact binary protocol (mrctl.io.protocol) over pyserial.

One exchange per tick = one SETPOINT out, one SAMPLE back. The port is
opened with ``serial.serial_for_url`` so a device path (``/dev/ttyACM0``),
``socket://host:port`` (device behind a TCP bridge or a simulator) and
``loop://`` all work unchanged. Lifecycle, error counting, device pacing and
the device-clock unwrap are :class:`~mrctl.io.base.Link`'s; this module
supplies the bytes of one tick (:meth:`SerialLink._transact`).

Timing: the reply must arrive within ``timeout_s`` of sending the request.
pyserial only has a per-read timeout, and changing ``port.timeout`` on POSIX
costs a tcsetattr per call, so the port's read timeout is fixed (0 with
``spin_wait``, else a short ``poll_s`` slice) and the exchange loops on its
own monotonic deadline. An exchange therefore returns within ``timeout_s +
poll_s`` (plus scheduling).

Default ``timeout_s`` = wire time of request + reply at the configured baud
plus 250 µs for device turnaround and OS latency, but at least 0.5 ms
(921600 Bd: ≈ 0.84 ms). That leaves little of a 1 ms tick for anything else
at 921600 Bd; 2 Mbaud is comfortable (see docs/protocol.md).
"""

from __future__ import annotations

import time
from typing import Any, Mapping

import serial  # pyserial

from mrctl.io.base import (
    CounterUnwrap,
    DeviceError,
    Disconnected,
    FrameError,
    Link,
    LinkTimeout,
    Sample,
    serial_device_key,
    sleep_until_ns,
)
from mrctl.io.protocol import (
    ChannelListFrame,
    encode_channel_query,
    DEFAULT_WATCHDOG_MS,
    EXCHANGE_BYTES,
    PROTOCOL_VERSION,
    SAMPLE_FRAME_SIZE,
    SETPOINT_FRAME_SIZE,
    ErrorCode,
    ErrorFrame,
    ForeignFrame,
    FrameDecoder,
    ProtocolVersionError,
    SampleFrame,
    SetpointEncoder,
    SetpointFlag,
    SetpointFrame,
    encode_setpoint,
    exchange_wire_time_s,
)

__all__ = ["SerialLink", "default_reply_timeout_s", "DEFAULT_BAUD"]

DEFAULT_BAUD = 921600
#: Allowance on top of wire time for device turnaround + OS/driver latency.
TURNAROUND_ALLOWANCE_S = 250e-6
MIN_REPLY_TIMEOUT_S = 0.5e-3

_U32 = 0xFFFFFFFF
_ENABLE = int(SetpointFlag.ENABLE)
_SYNC = int(SetpointFlag.SYNC)
_CHANNELS = int(SetpointFlag.CHANNELS)
_CLEAR = int(SetpointFlag.CLEAR_FAULTS)


def default_reply_timeout_s(baud: float) -> float:
    """Per-tick reply timeout: wire time + 250 µs turnaround, at least 0.5 ms."""
    return max(MIN_REPLY_TIMEOUT_S, exchange_wire_time_s(baud) + TURNAROUND_ALLOWANCE_S)


class SerialLink(Link):
    """:class:`~mrctl.io.base.Link` over a serial port (or any pyserial URL).

    Error mapping per exchange:

    * no usable reply by the deadline and nothing discarded → :class:`LinkTimeout`
    * no usable reply and corrupt bytes/frames were discarded → :class:`FrameError`
    * device sent ERROR for this request → :class:`DeviceError` (``code`` =
      :class:`~mrctl.io.protocol.ErrorCode`)
    * device speaks another version → :class:`ProtocolVersionError` (a FrameError; fatal)
    * port gone (``SerialException``/``OSError``) → :class:`Disconnected`; the
      port is closed and :meth:`open` may be called again to reconnect.

    A SAMPLE whose echoed host seq is not this request's (a late reply to an
    earlier tick) is discarded and counted in ``stale_replies``; our own
    SETPOINT coming back (``loop://``, RS-485 echo) is counted in ``echoes``.
    """

    kinds = ("serial",)
    COUNTERS = Link.COUNTERS + (
        "echoes", "crc_errors", "header_errors", "bytes_discarded", "unknown_frames", "foreign_frames",
        "device_clock_resets",
    )

    def __init__(
        self,
        url: str,
        baudrate: int = DEFAULT_BAUD,
        *,
        timeout_s: float | None = None,
        poll_s: float | None = None,
        write_timeout_s: float | None = None,
        watchdog_ms: int = DEFAULT_WATCHDOG_MS,
        safe_on_close: bool = True,
        serial_kwargs: Mapping[str, Any] | None = None,
        spin_wait: bool = True,
    ) -> None:
        """
        url: device path or pyserial URL. baudrate: Bd (nominal for USB-CDC).
        timeout_s: reply deadline per exchange (default :func:`default_reply_timeout_s`).
        poll_s: per-read slice; bounds deadline overshoot (default timeout/4,
            within [100 µs, 20 ms]).
        write_timeout_s: max time a write may block (default max(timeout_s, 5 ms)).
        watchdog_ms: device watchdog requested in every SETPOINT (0..255; 0 =
            device default).
        safe_on_close: send a disabled 0 A SETPOINT before closing the port.
        spin_wait: wait for the reply by polling the port without blocking
            (busy for one round trip, ~0.1–0.3 ms) instead of sleeping in
            select(): a sleeping thread wakes up to ~1.5 ms late on a VM
            (docs/performance.md), which would cost the tick its reply.
        """
        if not 0 <= watchdog_ms <= 255:
            raise ValueError(f"watchdog_ms must be 0..255, got {watchdog_ms!r}")
        super().__init__(
            float(timeout_s) if timeout_s is not None else default_reply_timeout_s(baudrate),
            safe_on_close=safe_on_close,
        )
        self.url = url
        self.baudrate = int(baudrate)
        self.poll_s = (
            float(poll_s)
            if poll_s is not None
            else min(self.timeout_s, max(self.timeout_s / 4, 100e-6), 20e-3)
        )
        self.write_timeout_s = (
            float(write_timeout_s) if write_timeout_s is not None else max(self.timeout_s, 5e-3)
        )
        self.watchdog_ms = int(watchdog_ms)
        self._serial_kwargs = dict(serial_kwargs or {})
        self.spin_wait = spin_wait
        self._sync_flag = 0  # SYNC while device-paced
        self._chan_flag = 0  # CHANNELS once the device has listed its channels
        self._clear_flag = 0  # CLEAR_FAULTS until an exchange carrying it is answered
        self._chan_names: tuple[str, ...] = ()
        self._port: Any = None
        self._seq = 0
        self._enc = SetpointEncoder()
        self._dec = FrameDecoder()
        self._clock = CounterUnwrap(1 << 32)  # the device's µs clock

    @classmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "SerialLink":
        """From the validated ``backend`` section (type serial)."""
        return cls(cfg.url, cfg.baudrate, timeout_s=cfg.timeout_s, watchdog_ms=cfg.watchdog_ms,
                   spin_wait=cfg.spin_wait)

    @classmethod
    def wire_time_s(cls, cfg: Any) -> float | None:
        """One SETPOINT + one SAMPLE at ``cfg.baudrate`` (8N1)."""
        return exchange_wire_time_s(cfg.baudrate)

    # -- counters kept by the frame decoder ---------------------------------
    crc_errors = property(lambda self: self._dec.crc_errors)
    header_errors = property(lambda self: self._dec.header_errors)
    bytes_discarded = property(lambda self: self._dec.bytes_discarded)
    unknown_frames = property(lambda self: self._dec.unknown_frames)
    foreign_frames = property(lambda self: self._dec.foreign_frames)

    # -- lifecycle --------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._port is not None

    def _open_transport(self) -> None:
        try:
            port = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=0 if self.spin_wait else self.poll_s,  # 0: read() never blocks
                write_timeout=self.write_timeout_s,
                **{"exclusive": True, **self._serial_kwargs},  # flock: one owner per port
            )
            # Bytes from before we opened belong to nobody.
            port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as e:
            raise Disconnected(f"cannot open {self.url}: {e}") from e
        self._dec.reset()
        self._port = port

    def _send_safe(self) -> None:
        """A disabled 0 A SETPOINT, flushed; no reply awaited."""
        self._seq = (self._seq + 1) & _U32
        self._port.write(encode_setpoint(self._seq, 0.0, 0, self.watchdog_ms))
        self._port.flush()

    def _close_transport(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - closing must not fail on a dead port
                pass

    def device_key(self) -> str | None:
        return serial_device_key(self.url)

    def describe(self) -> str:
        wire_us = exchange_wire_time_s(self.baudrate) * 1e6
        return (
            f"serial {self.url} @ {self.baudrate} Bd, protocol v{PROTOCOL_VERSION}: "
            f"{SETPOINT_FRAME_SIZE}+{SAMPLE_FRAME_SIZE}={EXCHANGE_BYTES} B/tick "
            f"({wire_us:.0f} µs on the wire), reply timeout {self.timeout_s * 1e3:.3g} ms, "
            f"device watchdog {self.watchdog_ms} ms"
        )

    def _set_sync(self, on: bool) -> None:
        self._sync_flag = _SYNC if on else 0

    def request_clear_faults(self) -> bool:
        """CLEAR_FAULTS in the next SETPOINT (until one carrying it is answered):
        the device clears its latched status bits (WATCHDOG_TRIPPED, ESTOP once
        its input closed, RX_ERROR; docs/protocol.md)."""
        self._clear_flag = _CLEAR
        return True

    # -- the tick ---------------------------------------------------------
    def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Sample:
        """Send ``current_A`` (A) as a SETPOINT, return the matching SAMPLE."""
        port = self._port
        seq = self._seq = (self._seq + 1) & _U32
        frame = self._enc.encode(
            seq, current_A, (_ENABLE if self.enabled else 0) | self._sync_flag | self._chan_flag | self._clear_flag,
            self.watchdog_ms)
        dec = self._dec
        crc0 = dec.crc_errors
        disc0 = dec.bytes_discarded
        try:
            port.write(frame)
            if wake_ns:  # device pacing: the reply comes one device period after the last
                sleep_until_ns(wake_ns)
            reply = self._await_reply(port, seq, deadline)
        except serial.SerialTimeoutException as e:
            raise LinkTimeout(f"{self.url}: write blocked > {self.write_timeout_s * 1e3:.3g} ms") from e
        except (serial.SerialException, OSError) as e:
            raise Disconnected(f"{self.url}: {e}") from e
        if reply is not None:
            self._clear_flag = 0
            if reply.channels:  # SAMPLE_X: the extra channels, into the laws' dict in place
                ch = self.channels
                for name, value in zip(self._chan_names, reply.channels):
                    ch[name] = value
            return Sample(reply.seq, self._clock(reply.t_dev_us) * 1e-6, reply.x_m, reply.v_mps,
                          reply.F_N, reply.status, reply.current_A)
        ms = (self.timeout_s + self._pace_extra_s) * 1e3
        if dec.crc_errors != crc0 or dec.bytes_discarded != disc0:
            raise FrameError(
                f"{self.url}: no valid reply to seq {seq} within {ms:.3g} ms; "
                f"discarded {dec.bytes_discarded - disc0} bytes, {dec.crc_errors - crc0} CRC errors"
            )
        raise LinkTimeout(f"{self.url}: no reply to seq {seq} within {ms:.3g} ms")

    def request_channels(self, timeout_s: float = 0.1) -> tuple[str, ...]:
        """Ask the device for its extra channels (CHANNEL_QUERY, docs/protocol.md
        §2.5); from then on every SETPOINT asks for them (the CHANNELS flag)
        and :attr:`channels` follows each SAMPLE_X. A device without channels
        (an ERROR, or no answer) leaves them empty. Start-up only, not per tick."""
        port, dec = self._port, self._dec
        if port is None:
            raise Disconnected(f"{self.url}: not open")
        seq = self._seq = (self._seq + 1) & _U32
        names: tuple[str, ...] = ()
        try:
            port.write(encode_channel_query(seq))
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline and not names:
                for f in dec.feed(port.read(dec.bytes_needed(SAMPLE_FRAME_SIZE)) or b""):
                    if isinstance(f, ChannelListFrame) and f.echo_seq == seq:
                        names = f.names
                    elif isinstance(f, ErrorFrame) and f.echo_seq == seq:
                        deadline = 0.0  # UNKNOWN_TYPE: an older device
                if self.spin_wait:  # read() does not block: do not spin for 100 ms
                    time.sleep(1e-4)
        except (serial.SerialException, OSError) as e:
            raise Disconnected(f"{self.url}: {e}") from e
        self._chan_names = names
        self._chan_flag = _CHANNELS if names else 0
        self.channels = dict.fromkeys(names, float("nan"))
        return names

    def _await_reply(self, port: Any, seq: int, deadline: float) -> SampleFrame | None:
        """Read until the SAMPLE answering ``seq`` (None at the deadline)."""
        dec = self._dec
        clock = time.monotonic
        while True:
            data = port.read(dec.bytes_needed(SAMPLE_FRAME_SIZE))
            if data:
                reply = None
                for f in dec.feed(data):
                    r = self._accept(f, seq)
                    if r is not None:
                        if reply is None:
                            reply = r
                        else:
                            self.stale_replies += 1  # duplicate answer
                if reply is not None:
                    return reply
            if clock() >= deadline:
                return None

    def _accept(self, f: object, seq: int) -> SampleFrame | None:
        """The reply to ``seq``, or None after counting/discarding ``f``."""
        if isinstance(f, SampleFrame):
            if f.echo_seq == seq:
                return f
            self.stale_replies += 1
            return None
        if isinstance(f, ErrorFrame):
            if f.code == ErrorCode.BAD_VERSION:
                raise ProtocolVersionError(PROTOCOL_VERSION, f.detail)
            # A NAK names the offending request, except BAD_CRC: the device
            # can't trust a corrupt seq, so it echoes the last good one (ours - 1).
            if f.echo_seq == seq or (f.code == ErrorCode.BAD_CRC and f.echo_seq == (seq - 1) & _U32):
                try:
                    name = ErrorCode(f.code).name
                except ValueError:
                    name = f"0x{f.code:02X}"
                raise DeviceError(f.code, f"{self.url}: device NAK {name} for seq {seq}")
            self.stale_replies += 1
            return None
        if isinstance(f, ForeignFrame):
            raise ProtocolVersionError(PROTOCOL_VERSION, f.version)
        if isinstance(f, SetpointFrame):
            self.echoes += 1
        return None

