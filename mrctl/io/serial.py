"""SerialLink: the compact binary protocol (mrctl.io.protocol) over pyserial.

One :meth:`SerialLink.exchange` per tick = one SETPOINT out, one SAMPLE back.
The port is opened with ``serial.serial_for_url`` so a device path
(``/dev/ttyACM0``), ``socket://host:port`` (device behind a TCP bridge or a
simulator) and ``loop://`` all work unchanged.

Timing: the reply must arrive within ``timeout_s`` of sending the request.
pyserial only has a per-read timeout, and changing ``port.timeout`` on POSIX
costs a tcsetattr per call, so the port's read timeout is fixed at a short
``poll_s`` slice and the exchange loops on its own monotonic deadline. An
exchange therefore returns within ``timeout_s + poll_s`` (plus scheduling).

Default ``timeout_s`` = wire time of request + reply at the configured baud
plus 250 µs for device turnaround and OS latency, but at least 0.5 ms
(921600 Bd: ≈ 0.84 ms). That leaves little of a 1 ms tick for anything else
at 921600 Bd; 2 Mbaud is comfortable (see docs/protocol.md).
"""

from __future__ import annotations

import math
import time
from typing import Any, Mapping

import serial  # pyserial

from mrctl.io.base import DeviceError, Disconnected, FrameError, LinkTimeout, Sample, sleep_until_ns
from mrctl.io.base import serial_device_key  # device ownership (hardening)
from mrctl.io.protocol import (
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
    exchange_wire_time_s,
    encode_setpoint,
)

__all__ = ["SerialLink", "default_reply_timeout_s", "DEFAULT_BAUD"]

DEFAULT_BAUD = 921600
#: Allowance on top of wire time for device turnaround + OS/driver latency.
TURNAROUND_ALLOWANCE_S = 250e-6
MIN_REPLY_TIMEOUT_S = 0.5e-3

_U32 = 0xFFFFFFFF
_HALF_U32 = 1 << 31


_ENABLE = int(SetpointFlag.ENABLE)


def default_reply_timeout_s(baud: float) -> float:
    """Per-tick reply timeout: wire time + 250 µs turnaround, at least 0.5 ms."""
    return max(MIN_REPLY_TIMEOUT_S, exchange_wire_time_s(baud) + TURNAROUND_ALLOWANCE_S)


class SerialLink:
    """:class:`mrctl.io.base.Link` over a serial port (or any pyserial URL).

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
        self.url = url
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s) if timeout_s is not None else default_reply_timeout_s(baudrate)
        if not self.timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.poll_s = (
            float(poll_s)
            if poll_s is not None
            else min(self.timeout_s, max(self.timeout_s / 4, 100e-6), 20e-3)
        )
        self.write_timeout_s = (
            float(write_timeout_s) if write_timeout_s is not None else max(self.timeout_s, 5e-3)
        )
        self.watchdog_ms = int(watchdog_ms)
        self.safe_on_close = safe_on_close
        #: False → SETPOINTs go out without ENABLE (device holds 0 A, output off).
        self.enabled = True
        self._serial_kwargs = dict(serial_kwargs or {})
        self.spin_wait = spin_wait
        # device pacing (set_device_paced): SYNC flag on, longer deadline
        self._sync_flag = 0
        self._base_timeout_s = self.timeout_s
        self._period_ns = 0
        self._sleep_margin_ns = 0
        self._t_reply_ns = 0  # monotonic ns of the last good reply (device pacing)
        self._port: Any = None
        self._seq = 0
        self._enc = SetpointEncoder()
        self._dec = FrameDecoder()
        self._t_last_us: int | None = None
        self._t_total_us = 0
        # counters (cumulative over reopen)
        self.exchanges = 0  #: successful exchanges
        self.timeouts = 0
        self.frame_errors = 0  #: exchanges that ended in FrameError
        self.stale_replies = 0
        self.device_errors = 0
        self.echoes = 0
        self.disconnects = 0
        self.device_clock_resets = 0  #: device time went backwards (device rebooted?)

    kinds = ("serial",)
    split = False
    host_clocked = False
    true_force_N = math.nan

    def begin_tick(self, k: int) -> None:
        pass

    @classmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "SerialLink":
        """From the validated ``backend`` section (type serial)."""
        return cls(cfg.url, cfg.baudrate, timeout_s=cfg.timeout_s, watchdog_ms=cfg.watchdog_ms,
                   spin_wait=cfg.spin_wait)

    @classmethod
    def wire_time_s(cls, cfg: Any) -> float | None:
        """One SETPOINT + one SAMPLE at ``cfg.baudrate`` (8N1)."""
        return exchange_wire_time_s(cfg.baudrate)

    # -- counters ---------------------------------------------------------
    @property
    def crc_errors(self) -> int:
        return self._dec.crc_errors

    @property
    def bytes_discarded(self) -> int:
        return self._dec.bytes_discarded

    def counters(self) -> dict[str, int]:
        """Snapshot of all counters, for logs/metrics (not for the hot path)."""
        d = self._dec
        return {
            "exchanges": self.exchanges,
            "timeouts": self.timeouts,
            "frame_errors": self.frame_errors,
            "crc_errors": d.crc_errors,
            "header_errors": d.header_errors,
            "bytes_discarded": d.bytes_discarded,
            "stale_replies": self.stale_replies,
            "device_errors": self.device_errors,
            "echoes": self.echoes,
            "unknown_frames": d.unknown_frames,
            "foreign_frames": d.foreign_frames,
            "disconnects": self.disconnects,
            "device_clock_resets": self.device_clock_resets,
        }

    # -- lifecycle --------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._port is not None

    def open(self) -> None:
        """Open the port (idempotent). Raises :class:`Disconnected` if it can't."""
        if self._port is not None:
            return
        try:
            port = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=0 if self.spin_wait else self.poll_s,  # 0: read() never blocks
                write_timeout=self.write_timeout_s,
                **{"exclusive": True, **self._serial_kwargs},  # flock: one owner (hardening)
            )
            # Bytes from before we opened belong to nobody.
            port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as e:
            raise Disconnected(f"cannot open {self.url}: {e}") from e
        self._dec.reset()
        self._t_last_us = None
        self._port = port

    def close(self) -> None:
        """Send a disabled 0 A setpoint (best effort), close the port. Idempotent."""
        port, self._port = self._port, None
        if port is None:
            return
        try:
            if self.safe_on_close:
                self._seq = (self._seq + 1) & _U32
                port.write(encode_setpoint(self._seq, 0.0, 0, self.watchdog_ms))
                port.flush()
        except Exception:  # noqa: BLE001 - closing must not fail on a dead port
            pass
        finally:
            try:
                port.close()
            except Exception:  # noqa: BLE001
                pass

    def __enter__(self) -> "SerialLink":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def device_key(self) -> str | None:  # device ownership (hardening)
        return serial_device_key(self.url)

    def describe(self) -> str:
        wire_us = exchange_wire_time_s(self.baudrate) * 1e6
        return (
            f"serial {self.url} @ {self.baudrate} Bd, protocol v{PROTOCOL_VERSION}: "
            f"{SETPOINT_FRAME_SIZE}+{SAMPLE_FRAME_SIZE}={EXCHANGE_BYTES} B/tick "
            f"({wire_us:.0f} µs on the wire), reply timeout {self.timeout_s * 1e3:.3g} ms, "
            f"device watchdog {self.watchdog_ms} ms"
        )

    # -- the tick ---------------------------------------------------------
    @property
    def device_paced(self) -> bool:
        """True while every SETPOINT carries SYNC (:meth:`set_device_paced`)."""
        return self._sync_flag != 0

    def set_device_paced(self, on: bool, period_s: float, spin_margin_s: float = 3e-4) -> None:
        """Device pacing (docs/protocol.md §6.1): every SETPOINT carries SYNC,
        so the device applies it at its next tick and answers after it; an
        exchange then blocks until the device's next tick, and the host loop
        runs at the device's rate with one tick of actuation latency.
        The reply deadline grows by one period. While waiting, the link
        sleeps until ``spin_margin_s`` before the reply is due (one period
        after the previous one), then polls: a sleeping thread wakes late on
        a VM, a spinning one costs a core."""
        if on and not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s!r}")
        self._sync_flag = int(SetpointFlag.SYNC) if on else 0
        self.timeout_s = self._base_timeout_s + (period_s if on else 0.0)
        self._period_ns = round(period_s * 1e9) if on else 0
        self._sleep_margin_ns = round(spin_margin_s * 1e9)
        self._t_reply_ns = 0

    def exchange(self, current_A: float) -> Sample:
        """Send ``current_A`` (A) as a SETPOINT, return the matching SAMPLE."""
        port = self._port
        if port is None:
            raise Disconnected(f"{self.url} is not open")
        if not math.isfinite(current_A):
            raise ValueError(f"current_A must be finite, got {current_A!r}")
        seq = self._seq = (self._seq + 1) & _U32
        frame = self._enc.encode(
            seq, current_A, (_ENABLE if self.enabled else 0) | self._sync_flag, self.watchdog_ms
        )
        dec = self._dec
        crc0 = dec.crc_errors
        disc0 = dec.bytes_discarded
        clock = time.monotonic
        deadline = clock() + self.timeout_s
        try:
            port.write(frame)
            if self._period_ns and self._t_reply_ns:
                # device pacing: the reply comes one device period after the last
                sleep_until_ns(self._t_reply_ns + self._period_ns - self._sleep_margin_ns)
            while True:
                n = dec.bytes_needed(SAMPLE_FRAME_SIZE)
                data = port.read(n)
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
                        self.exchanges += 1
                        if self._period_ns:
                            self._t_reply_ns = time.monotonic_ns()
                        return self._to_sample(reply)
                if clock() >= deadline:
                    break
        except serial.SerialTimeoutException as e:
            self.timeouts += 1
            raise LinkTimeout(f"{self.url}: write blocked > {self.write_timeout_s * 1e3:.3g} ms") from e
        except (serial.SerialException, OSError) as e:
            self.disconnects += 1
            self._drop_port()
            raise Disconnected(f"{self.url}: {e}") from e
        if dec.crc_errors != crc0 or dec.bytes_discarded != disc0:
            self.frame_errors += 1
            raise FrameError(
                f"{self.url}: no valid reply to seq {seq} within {self.timeout_s * 1e3:.3g} ms; "
                f"discarded {dec.bytes_discarded - disc0} bytes, "
                f"{dec.crc_errors - crc0} CRC errors"
            )
        self.timeouts += 1
        raise LinkTimeout(f"{self.url}: no reply to seq {seq} within {self.timeout_s * 1e3:.3g} ms")

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
            if f.echo_seq == seq or (
                f.code == ErrorCode.BAD_CRC and f.echo_seq == (seq - 1) & _U32
            ):
                self.device_errors += 1
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

    def _to_sample(self, f: SampleFrame) -> Sample:
        """Unwrap the 32-bit µs device clock into seconds."""
        t = f.t_dev_us
        last = self._t_last_us
        if last is None:
            self._t_total_us = t
        else:
            delta = (t - last) & _U32
            if delta < _HALF_U32:
                self._t_total_us += delta
            else:  # went backwards: device restarted its clock
                self.device_clock_resets += 1
                self._t_total_us = t
        self._t_last_us = t
        return Sample(
            f.seq, self._t_total_us * 1e-6, f.x_m, f.v_mps, f.F_N, f.status, f.current_A
        )

    def _drop_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001
                pass
