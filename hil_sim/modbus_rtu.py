"""Modbus RTU servers of the simulated bench (the device: :mod:`hil_sim.modbus_device`).

:class:`ModbusRtuInline` serves a tty without ever blocking: hil_sim's clock
thread polls it while it spins (``--serve inline``, the default), and
:func:`serve_modbus_rtu` polls it from a thread after each ``select()``
wake-up (``--serve thread``). Requests of known length (FC1-6, FC16, FC23)
are taken as soon as they are complete, junk is hunted through
(:func:`rtu_feed`); anything else is delimited by line silence.
"""

from __future__ import annotations

import os
import select
import threading
import time
from collections import deque
from typing import Any, Callable

from hil_sim.faults import FaultBit
from hil_sim.modbus_device import Deferred, ModbusDevice
from hil_sim.modbus_wire import FAULT_POLL_S, IDLE_POLL_S, rtu_request_length
from hil_sim.state import DeviceState
from mrctl.io.modbus import crc16_modbus, open_serial_port
from mrctl.io.registers import RegisterMap

__all__ = ["ModbusRtuInline", "rtu_feed", "rtu_silence_s", "serve_modbus_rtu"]

_DISCONNECT = int(FaultBit.DISCONNECT)
_IGNORE = int(FaultBit.IGNORE_WRITES)


def rtu_silence_s(baudrate: int, parity: str = "E", stopbits: float = 1) -> float:
    """The RTU end-of-frame silence: 3.5 characters, at least 1 ms (ptys and
    USB adapters deliver bytes in bursts)."""
    bits = 1 + 8 + (0 if str(parity).upper() == "N" else 1) + int(stopbits + 0.5)
    return max(3.5 * bits / baudrate, 1e-3)


def serve_modbus_rtu(
    state: DeviceState,
    port_path: str | int,
    baudrate: int,
    register_map: RegisterMap | None,
    stop: threading.Event,
    ready: Callable[[str], None] | None = None,
    *,
    fc23: bool = True,
    parity: str = "E",
    stopbits: float = 1,
    endpoint: Any = None,
    on_device: Callable[[ModbusDevice], None] | None = None,
) -> None:
    """Serve Modbus RTU on a tty until ``stop`` is set.

    ``endpoint``: the :class:`hil_sim.pty_endpoint.PtyEndpoint` whose master fd
    ``port_path`` is; needed for the ``disconnect`` fault (pty hung up, then a
    new one linked at the same path).

    ``port_path``: a tty path (opened with pyserial at ``baudrate``, 8
    data bits, ``parity``/``stopbits``), or an open fd (int, e.g. a pty
    master; set non-blocking, not closed here). Requests are delimited by
    their known length (FC1-6, FC16, FC23; junk is hunted through, see
    :func:`rtu_feed`); other function codes by 3.5 characters of line
    silence (at least 1 ms, since ptys and USB adapters deliver bytes in
    bursts). The loop is :class:`ModbusRtuInline` polled after each
    ``select()`` wake-up. If the tty goes away, serving stops and the call
    waits for ``stop``. On a pty (``/dev/pts/*``) a parity the
    kernel refuses on reopen falls back to N (see
    :func:`mrctl.io.modbus.open_serial_port`).
    """
    dev = ModbusDevice(state, register_map, fc23=fc23)
    if on_device is not None:
        on_device(dev)
    owner: Any = None
    if isinstance(port_path, int):
        fd = port_path
    else:
        owner = open_serial_port(port_path, baudrate=baudrate, parity=str(parity).upper(), stopbits=stopbits, timeout=0)
        fd = owner.fileno()
    os.set_blocking(fd, False)
    try:
        if ready is not None:
            ready(f"modbus-rtu {port_path} @ {baudrate} Bd")
        _rtu_loop(ModbusRtuInline(dev, fd, rtu_silence_s(baudrate, parity, stopbits), endpoint,
                                  blocking_writes=True), stop)
    finally:
        if owner is not None:
            try:
                owner.close()
            except Exception:  # noqa: BLE001
                pass
    stop.wait()


def _crc_ok(buf: bytes | bytearray, start: int, n: int) -> bool:
    end = start + n
    return crc16_modbus(memoryview(buf)[start : end - 2]) == buf[end - 2] | buf[end - 1] << 8


def _find_frame(buf: bytearray, start: int) -> int:
    """Index ≥ start of the first complete, CRC-valid, known-length request in buf, or -1."""
    n_buf = len(buf)
    for i in range(start, n_buf - 3):
        n = rtu_request_length(memoryview(buf)[i:])
        if n is not None and n > 0 and i + n <= n_buf and _crc_ok(buf, i, n):
            return i
    return -1


def rtu_feed(dev: ModbusDevice, buf: bytearray) -> list[bytes]:
    """Consume every complete request at the front of ``buf``; return the replies.

    Requests of known length are taken as soon as they are complete. A CRC
    failure drops one byte and hunts on (junk before a frame costs nothing
    but the junk); an incomplete candidate yields to a complete valid frame
    found further on (a false header can't hold back a real request). An
    unknown function code waits for line silence (the caller then passes the
    whole buffer to ``dev.handle_rtu_frame``), unless a valid known frame
    follows it. Never raises.
    """
    out: list[bytes] = []
    while len(buf) >= 4:
        n = rtu_request_length(buf)
        if n is None:
            break
        if n > 0:
            if len(buf) < n:
                j = _find_frame(buf, 1)
                if j < 0:
                    break  # wait for the rest
                dev.bytes_discarded += j
                del buf[:j]
                continue
            if _crc_ok(buf, 0, n):
                frame = bytes(buf[:n])
                del buf[:n]
                resp = dev.handle_rtu_frame(frame)
                if resp is not None:
                    out.append(resp)
                continue
            dev.crc_errors += 1
            dev.bytes_discarded += 1
            del buf[:1]
            continue
        j = _find_frame(buf, 1)  # unknown function code
        if j < 0:
            break
        dev.bytes_discarded += j
        del buf[:j]
    return out


class ModbusRtuInline:
    """Modbus RTU on a non-blocking tty fd, one :meth:`poll_once` at a time.

    Each poll: the ``disconnect`` window (pty hung up through ``endpoint``,
    a new one linked when it ends), due delayed replies, then whatever bytes
    have arrived (``ignore_writes`` discards them), every complete request
    answered (a SYNC reply is handed to the clock), and a buffer that has
    been silent for ``silence_s`` taken as one frame of an unknown function.

    ``blocking_writes``: wait until a reply is written whole (the threaded
    server). Off (inline), a reply the tty cannot take at once is cut short
    and counted in ``replies_cut``: the clock never waits on the host.
    """

    def __init__(self, dev: ModbusDevice, fd: int, silence_s: float, endpoint: Any = None,
                 blocking_writes: bool = False) -> None:
        self.dev = dev
        self.state = dev.state
        self.fd = fd
        self.silence_s = silence_s
        self.endpoint = endpoint
        self.blocking_writes = blocking_writes
        self.buf = bytearray()
        self.delayed: deque[tuple[float, bytes]] = deque()  # (due monotonic s, bytes): delay_replies
        self.down = False  #: inside a disconnect window
        self.gone = False  #: the tty went away for good (nothing to reopen): serving has stopped
        self.replies_cut = 0
        #: the last poll's read returned nothing (with select() saying readable: device gone)
        self.read_empty = True
        self._t_rx = 0.0  # monotonic s of the last bytes received
        os.set_blocking(fd, False)

    def wait_s(self, idle_s: float) -> float:
        """How long a threaded server may sleep in select() before the next poll is due."""
        wait = self.silence_s if self.buf else idle_s
        if self.delayed:
            wait = max(1e-4, min(wait, self.delayed[0][0] - time.monotonic()))
        return wait

    def poll_once(self) -> None:
        """Serve what has arrived, without blocking (unless ``blocking_writes``)."""
        self.read_empty = False
        if self.gone:
            return
        fbits = self.state.fault_bits
        if (fbits & _DISCONNECT or self.down) and self.endpoint is not None:
            if fbits & _DISCONNECT:
                if not self.down:
                    self.down = True
                    self.dev.fault_counts["disconnects"] += 1
                    self.delayed.clear()
                    self.buf.clear()
                    self.endpoint.hangup()
                return
            self.down = False
            self.endpoint.reopen()
            self.fd = self.endpoint.master_fd
        if self.delayed:
            now = time.monotonic()
            q = self.delayed
            while q and q[0][0] <= now:
                if not self._write(q.popleft()[1]):
                    return
        try:
            # b"" is no data too: a tty opened with VMIN 0 (pyserial, timeout 0) reads empty
            chunk = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            chunk = b""
        except OSError:  # the tty went away (a pty keeps its own slave fd open: not a host leaving)
            self.gone = True
            return
        self.read_empty = not chunk
        dev = self.dev
        buf = self.buf
        if chunk:
            self._t_rx = time.monotonic()
            if fbits & _IGNORE:
                dev.fault_counts["requests_ignored"] += 1
                buf.clear()
                return
            buf += chunk
            for resp in rtu_feed(dev, buf):
                if isinstance(resp, Deferred):  # SYNC: the clock sends it after its tick
                    resp.owed.attach(lambda r=resp: self._reply(r.build()))
                    continue
                if not self._reply(resp):
                    return
            if len(buf) > 1024:  # nothing valid in a whole kilobyte: start over
                dev.bytes_discarded += len(buf)
                buf.clear()
            return
        if buf and time.monotonic() - self._t_rx >= self.silence_s:
            # Line silence: what's buffered is a whole frame of an unknown
            # function (→ ILLEGAL_FUNCTION if its CRC is good) or junk.
            resp = dev.handle_rtu_frame(bytes(buf)) if rtu_request_length(buf) == -1 else None
            if resp is not None:
                self._reply(resp)
            else:
                dev.bytes_discarded += len(buf)
            buf.clear()

    def _reply(self, adu: bytes) -> bool:
        """One response through the reply faults, then out; False if the tty went away."""
        out = self.dev.reply_now(adu, False, self.delayed)
        return True if out is None else self._write(out)

    def _write(self, data: bytes) -> bool:
        """Send one reply; False (and ``gone``) if the tty went away."""
        if self.blocking_writes:
            if _write_all(self.fd, data):
                return True
            self.gone = True
            return False
        try:
            n = os.write(self.fd, data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError:
            self.gone = True
            return False
        if n < len(data):
            self.replies_cut += 1
        return True


def _rtu_loop(srv: ModbusRtuInline, stop: threading.Event) -> None:
    """The threaded server: sleep in select() until bytes, silence or a
    delayed reply are due, then poll."""
    idle_s = FAULT_POLL_S if srv.state.faults else IDLE_POLL_S
    while not stop.is_set() and not srv.gone:
        ready = False
        if srv.down:
            stop.wait(FAULT_POLL_S)
        else:
            try:
                ready = bool(select.select([srv.fd], [], [], srv.wait_s(idle_s))[0])
            except (OSError, ValueError):  # fd closed under us (a hang-up in progress)
                stop.wait(FAULT_POLL_S)
        srv.poll_once()
        if ready and srv.read_empty and not srv.down:
            srv.gone = True  # readable but empty: the device side is gone


def _write_all(fd: int, data: bytes) -> bool:
    """Write everything; False if the tty is gone."""
    view = memoryview(data)
    try:
        while view:
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                select.select([], [fd], [], IDLE_POLL_S)
                continue
            view = view[n:]
    except OSError:
        return False
    return True
