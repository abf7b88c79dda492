"""Serial transport: the framed binary protocol (docs/protocol.md) on a pty.

:class:`SerialDevice` serves the protocol on the master fd of a pty
(:class:`hil_sim.pty_endpoint.PtyEndpoint`) from its own thread (the
device's "UART interrupt"), or inline from the clock: it decodes SETPOINT frames with
:class:`~mrctl.io.protocol.FrameDecoder`, hands each to
:meth:`DeviceState.set_setpoint` (which restarts the watchdog) and replies
at once with a SAMPLE built from :meth:`DeviceState.latest_sample`, echoing
the host's seq. The reply never waits for the clock: it carries the latest
*completed* measurement, as the protocol requires.

Device-side obligations implemented here (the clock thread does the rest,
see :mod:`hil_sim.bench`):

* ERROR ``BAD_VERSION`` (detail = 1) for a CRC-valid frame of another
  version; nothing applied.
* ERROR ``BAD_CRC`` (echo = last good host seq) when a candidate frame fails
  its CRC; the applied current is not changed.
* ERROR ``UNKNOWN_TYPE`` for a valid v1 frame that is not a SETPOINT.
* ``RX_ERROR`` in the reply status, latched from the first corrupt or
  discarded input until a SETPOINT with ``CLEAR_FAULTS``.
* ``CURRENT_CLAMPED`` in the reply to an out-of-range or non-finite setpoint.

SAMPLE ``seq`` is the device tick index k of the measurement (mod 2**32),
not a count of frames sent: it is what aligns host logs with the truth log.
Two replies within one tick therefore carry the same seq, and a gap is the
number of device ticks between two requests.
"""

from __future__ import annotations

import errno
import os
import random
import select
import threading
import time
from collections import deque

from mrctl.io.base import Sample, Status
from mrctl.io.protocol import (
    PROTOCOL_VERSION,
    ChannelListFrame,
    ChannelQueryFrame,
    ErrorCode,
    ErrorFrame,
    ForeignFrame,
    FrameDecoder,
    SampleFrame,
    SetpointFlag,
    SetpointFrame,
    encode_channel_list,
    encode_error,
    encode_sample,
)

from hil_sim.bench import clamp_setpoint
from hil_sim.faults import FaultBit
from hil_sim.pty_endpoint import PtyEndpoint
from hil_sim.state import DeviceState

__all__ = ["SerialDevice"]

_U32 = 0xFFFFFFFF
_ENABLE = int(SetpointFlag.ENABLE)
_CLEAR = int(SetpointFlag.CLEAR_FAULTS)
_SYNC = int(SetpointFlag.SYNC)
_CHANNELS = int(SetpointFlag.CHANNELS)
_RX_ERROR = int(Status.RX_ERROR)
_CLAMPED = int(Status.CURRENT_CLAMPED)
_WATCHDOG_TRIPPED = int(Status.WATCHDOG_TRIPPED)
_DROP = int(FaultBit.DROP_REPLIES)
_DELAY = int(FaultBit.DELAY_REPLIES)
_CORRUPT = int(FaultBit.CORRUPT_CRC)
_GARBAGE = int(FaultBit.GARBAGE)
_DISCONNECT = int(FaultBit.DISCONNECT)
_IGNORE = int(FaultBit.IGNORE_WRITES)
_REPLY_FAULTS = _DROP | _DELAY | _CORRUPT | _GARBAGE
_POLL_S = 0.05  # how often the server looks at its stop event
_WRITE_BUDGET_S = 0.01  # how long a reply may wait for room in the pty buffer


class SerialDevice:
    """Serves the binary protocol on a (non-blocking) fd until ``stop`` is set.

    Link faults (:mod:`hil_sim.faults`) are applied from ``state.fault_bits``:
    replies dropped, delayed (a FIFO of timed replies, sent from
    :meth:`poll_once` / the serve loop), CRC-corrupted or preceded by junk;
    ``ignore_writes`` discards input unanswered; ``disconnect`` hangs up the
    pty (``endpoint``) and brings a new one up when the window ends.
    """

    def __init__(self, state: DeviceState, fd: int, stop: threading.Event, I_max_A: float = 2.0,
                 endpoint: PtyEndpoint | None = None, seed: int = 0) -> None:
        self.state = state
        self.fd = fd
        self.stop = stop
        self.I_max = I_max_A
        self.endpoint = endpoint
        self.dec = FrameDecoder()
        self._rx_error = False  # latched RX_ERROR
        self._clear_seq: int | None = None  # sample seq whose WATCHDOG bit a CLEAR_FAULTS masks
        self._last_good_seq = 0
        self.setpoints = 0
        self.replies = 0
        self.errors_sent = 0
        self.replies_dropped = 0
        self.bad_version = 0
        self.unknown_type = 0
        # faults
        self._delayed: deque[tuple[int, bytes]] = deque()
        self._rng = random.Random(seed)
        self._hung = False
        self.fault_counts = {"replies_dropped": 0, "replies_delayed": 0, "replies_corrupted": 0,
                             "garbage_bytes": 0, "bytes_ignored": 0, "hangups": 0}

    def counters(self) -> dict[str, int]:
        d = self.dec
        return {
            "setpoints": self.setpoints,
            "replies": self.replies,
            "errors_sent": self.errors_sent,
            "replies_dropped": self.replies_dropped,
            "crc_errors": d.crc_errors,
            "header_errors": d.header_errors,
            "bytes_discarded": d.bytes_discarded,
            "unknown_frames": d.unknown_frames,
            "bad_version": self.bad_version,
            "unknown_type": self.unknown_type,
            "faults": dict(self.fault_counts),
        }

    # -- I/O ------------------------------------------------------------------
    def serve(self) -> None:
        poller = select.poll()
        reg_fd = -1
        # with faults scheduled, look at the fault bits often (a disconnect or a
        # delayed reply must not wait for the 50 ms idle poll)
        idle_ms = 1 if self.state.faults else int(_POLL_S * 1000)
        while not self.stop.is_set():
            if self.state.fault_bits or self._hung or self._delayed:
                if self._fault_io(self.state.fault_bits):
                    self.stop.wait(0.001)
                    continue
            if reg_fd != self.fd:
                if reg_fd >= 0:
                    try:
                        poller.unregister(reg_fd)
                    except (KeyError, ValueError):
                        pass
                poller.register(self.fd, select.POLLIN)
                reg_fd = self.fd
            if not poller.poll(idle_ms if not self._delayed else 1):
                continue
            try:
                data = os.read(self.fd, 4096)
            except BlockingIOError:
                continue
            except OSError as e:
                if e.errno in (errno.EIO, errno.EBADF):  # no host has the tty open / fd just replaced
                    time.sleep(0.001)
                    continue
                raise
            if data:
                self.handle(data)

    def poll_once(self) -> None:
        """Serve whatever has arrived, without blocking (inline serving from the
        clock's spin phase: no thread hand-off, no wake-up latency)."""
        if self.state.fault_bits or self._hung or self._delayed:
            if self._fault_io(self.state.fault_bits):
                return
        try:
            data = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            if e.errno == errno.EIO:  # no host has the tty open right now
                return
            raise
        if data:
            self.handle(data)

    def _fault_io(self, fbits: int) -> bool:
        """Disconnect transitions and due delayed replies; True = no link right now."""
        if fbits & _DISCONNECT:
            if not self._hung:
                self._hung = True
                self._delayed.clear()  # in flight when the cable was pulled
                self.fault_counts["hangups"] += 1
                if self.endpoint is not None:
                    self.endpoint.hangup()
                    self.fd = -1
            return True
        if self._hung:
            self._hung = False
            self.dec.reset()
            if self.endpoint is not None:
                self.endpoint.reopen()
                self.fd = self.endpoint.master_fd
        if self._delayed:
            now = time.monotonic_ns()
            q = self._delayed
            while q and q[0][0] <= now:
                frame = q.popleft()[1]
                if not _write_all(self.fd, frame):
                    self.replies_dropped += 1
        return False

    def _send(self, frame: bytes) -> bool:
        fbits = self.state.fault_bits
        if fbits & _REPLY_FAULTS or self._delayed:
            return self._send_faulted(frame, fbits)
        if _write_all(self.fd, frame):
            return True
        self.replies_dropped += 1
        return False

    def _send_faulted(self, frame: bytes, fbits: int) -> bool:
        fc = self.fault_counts
        if fbits & _DROP:
            fc["replies_dropped"] += 1
            return False
        if fbits & _CORRUPT:
            frame = frame[:-1] + bytes((frame[-1] ^ 0xFF,))  # the CRC's high byte
            fc["replies_corrupted"] += 1
        if fbits & _GARBAGE:
            n = int(self.state.faults.param(_GARBAGE, "n_bytes") or 16) if self.state.faults else 16
            frame = self._rng.randbytes(n) + frame
            fc["garbage_bytes"] += n
        now = time.monotonic_ns()
        due = now
        if fbits & _DELAY:
            delay = (self.state.faults.param(_DELAY, "delay_s") or 0.0) if self.state.faults else 0.0
            due = now + int(delay * 1e9)
            fc["replies_delayed"] += 1
        if self._delayed or due > now:
            if self._delayed and self._delayed[-1][0] > due:
                due = self._delayed[-1][0]  # FIFO: never overtake an earlier reply
            self._delayed.append((due, frame))
            return True
        if _write_all(self.fd, frame):
            return True
        self.replies_dropped += 1
        return False

    # -- protocol ---------------------------------------------------------------
    def handle(self, data: bytes) -> None:
        """Feed received bytes; answer every complete frame."""
        if self.state.fault_bits & _IGNORE:
            # a dead device: the bytes are lost, nothing is applied or answered
            self.fault_counts["bytes_ignored"] += len(data)
            return
        dec = self.dec
        crc0, bad0 = dec.crc_errors, dec.bytes_discarded
        frames = dec.feed(data)
        if dec.bytes_discarded != bad0 or dec.crc_errors != crc0:
            self._rx_error = True
        if dec.crc_errors != crc0:
            self._error(self._last_good_seq, ErrorCode.BAD_CRC)
        for f in frames:
            if isinstance(f, SetpointFrame):
                self._setpoint(f)
            elif isinstance(f, ForeignFrame):
                self.bad_version += 1
                self._rx_error = True
                self._error(f.seq, ErrorCode.BAD_VERSION, PROTOCOL_VERSION)
            elif isinstance(f, ChannelQueryFrame):  # docs/protocol.md §2.5
                self._channel_list(f)
            elif isinstance(f, (SampleFrame, ErrorFrame, ChannelListFrame)):
                self.unknown_type += 1
                self._rx_error = True
                self._error(f.seq, ErrorCode.UNKNOWN_TYPE)

    def _setpoint(self, f: SetpointFrame) -> None:
        clear = bool(f.flags & _CLEAR)
        sync = f.flags & _SYNC
        self.setpoints += 1
        self._last_good_seq = f.seq
        if clear:
            self._rx_error = False
        # SYNC (device pacing): answered by the clock right after the tick that
        # applies this setpoint, with that tick's sample (docs/protocol.md §6.1)
        self.state.set_setpoint(f.current_A, bool(f.flags & _ENABLE), f.watchdog_ms, clear,
                                owe=(lambda: self._reply(f, None)) if sync else None)
        if sync:
            return
        s, ch = self.state.latest_sample_ex()
        if clear:
            self._clear_seq = s.seq
        self._reply(f, s, ch)

    def _reply(self, f: SetpointFrame, s: Sample | None, ch: tuple[float, ...] = ()) -> None:
        """SAMPLE answering ``f``: with ``s``, or the latest sample (SYNC);
        SAMPLE_X with the channels when ``f`` asks for them (CHANNELS)."""
        if s is None:
            s, ch = self.state.latest_sample_ex()
        status = s.status & ~_CLAMPED
        if clamp_setpoint(f.current_A, self.I_max)[1]:
            status |= _CLAMPED
        if self._rx_error:
            status |= _RX_ERROR
        if self._clear_seq == s.seq:
            status &= ~_WATCHDOG_TRIPPED  # cleared before this reply; the clock catches up next tick
        reply = encode_sample(s.seq, f.seq, round(s.t_dev_s * 1e6) & _U32, s.x_m, s.v_mps, s.F_N,
                              s.current_A, status, ch if f.flags & _CHANNELS else ())
        if self._send(reply):
            self.replies += 1

    def _channel_list(self, f: ChannelQueryFrame) -> None:
        """CHANNEL_LIST answering a CHANNEL_QUERY (names that do not fit one frame: INTERNAL)."""
        try:
            frame = encode_channel_list(self.state.latest_sample().seq, f.seq, self.state.channel_names)
        except ValueError:
            self._error(f.seq, ErrorCode.INTERNAL)
            return
        if self._send(frame):
            self.replies += 1

    def _error(self, echo_seq: int, code: int, detail: int = 0) -> None:
        s = self.state.latest_sample()
        if self._send(encode_error(s.seq, echo_seq, code, detail)):
            self.errors_sent += 1


def _write_all(fd: int, data: bytes) -> bool:
    """Write everything; False if the pty is full for too long or gone (a
    reply owed across a hang-up is lost, as on a pulled cable: never an
    exception, which in the clock thread would stop the bench)."""
    view = memoryview(data)
    deadline = None
    while view:
        try:
            view = view[os.write(fd, view):]
        except BlockingIOError:
            now = time.monotonic()
            if deadline is None:
                deadline = now + _WRITE_BUDGET_S
            elif now >= deadline:
                return False
            select.select([], [fd], [], deadline - now)
        except OSError:  # EBADF/EIO: hung up (the disconnect fault) or the host side gone
            return False
    return True
