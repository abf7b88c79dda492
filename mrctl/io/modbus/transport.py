"""Modbus byte transports: a serial line (raw fd or pyserial URL) and a TCP socket.

Each moves bytes with one absolute deadline (``time.monotonic()`` s) and
raises only :class:`~mrctl.io.base.LinkTimeout` (a write blocked past it)
or :class:`~mrctl.io.base.Disconnected` (the port/connection is gone); what
the bytes mean is the link's business (:mod:`mrctl.io.modbus.link`).

* :class:`FdIO`: a tty (or pty) by its file descriptor, non-blocking, with
  ``select`` + ``os.read``. Why not pyserial's ``read()``: its timeout is per
  call and changing it costs a tcsetattr; with our own deadline one
  exact-length read is one select plus one read.
* :class:`PySerialIO`: pyserial URL handlers without a file descriptor
  (``socket://``, ``loop://``, ...).
* :class:`TcpIO`: a non-blocking TCP socket with ``select``. Python's own
  socket timeouts go through poll() with a millisecond timeout rounded up,
  which would turn a 0.5 ms deadline into 1 ms; select takes microseconds.

With ``spin`` a transport waits for input by polling (select with timeout
0) instead of sleeping in select(): a sleeping thread wakes up to ~1.5 ms
late on a VM (docs/performance.md). ``wake_ns`` (device pacing) first
sleeps until that ``monotonic_ns`` time: nothing can arrive earlier.
"""

from __future__ import annotations

import os
import select
import socket
import time
from typing import Any, Mapping

from mrctl.io.base import Disconnected, LinkTimeout, sleep_until_ns

__all__ = ["FdIO", "PySerialIO", "TcpIO", "open_serial_port", "open_rtu"]


def open_serial_port(url: str, *, baudrate: int, parity: str = "E", stopbits: float = 1, **kwargs: Any) -> Any:
    """pyserial ``serial_for_url`` (8 data bits), with one pty workaround.

    Linux ptys accept PARENB the first time a pty is configured but reject
    it with EINVAL on every later open (seen with pyserial 3.5). A pty has
    no line, so parity means nothing there: on ``/dev/pts/*`` a failed open
    is retried with parity N. Real ports get exactly what was asked for.
    """
    import serial

    try:
        return serial.serial_for_url(url, baudrate=baudrate, parity=parity, stopbits=stopbits, bytesize=8, **kwargs)
    except (serial.SerialException, OSError):
        if parity == "N" or not os.path.realpath(str(url)).startswith("/dev/pts/"):
            raise
        return serial.serial_for_url(url, baudrate=baudrate, parity="N", stopbits=stopbits, bytesize=8, **kwargs)


# --------------------------------------------------------------------------
# serial lines
class FdIO:
    """Serial line over a raw fd: select + os.read with an absolute deadline.

    Why not pyserial's read(): its timeout is per call and changing it costs
    a tcsetattr; with our own deadline one exact-length read is one select
    plus one read, and overshoot is bounded by the scheduler, not a slice.
    """

    def __init__(self, fd: int, owner: Any = None, spin: bool = False) -> None:
        self.fd = fd
        self.owner = owner  # pyserial object that owns fd (closed with us), or None
        #: wait for input by polling (select with timeout 0), never sleeping in
        #: select: see the link's ``spin_wait``
        self.spin = spin
        os.set_blocking(fd, False)

    def write(self, data: bytes | bytearray, deadline: float) -> None:
        fd = self.fd
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                n = 0
            except OSError as e:
                raise Disconnected(f"write failed: {e}") from e
            view = view[n:]
            if view:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not select.select([], [fd], [], remaining)[1]:
                    raise LinkTimeout("write blocked past the deadline")

    def read(self, n: int, deadline: float, max_n: int = 0, wake_ns: int = 0) -> bytes:
        """At least ``n`` bytes (fewer only if the deadline passed), at most
        ``max(n, max_n)``. ``wake_ns``: sleep until this ``monotonic_ns`` time
        before waiting (nothing can be there earlier)."""
        fd = self.fd
        out = b""
        clock = time.monotonic
        want = max(n, max_n)
        spin = self.spin
        if wake_ns:
            sleep_until_ns(wake_ns)
        try:
            while len(out) < n:
                remaining = deadline - clock()
                if remaining < 0:
                    remaining = 0
                if not select.select([fd], [], [], 0.0 if spin else remaining)[0]:
                    if remaining > 0 and spin:
                        continue
                    break
                try:
                    chunk = os.read(fd, want - len(out))
                except BlockingIOError:  # spurious readiness
                    continue
                if not chunk:  # readable but nothing: device gone (as pyserial)
                    raise Disconnected("device reports readiness to read but returned no data")
                out += chunk
        except OSError as e:
            raise Disconnected(f"read failed: {e}") from e
        return out

    def flush_input(self) -> int:
        n = 0
        try:
            while select.select([self.fd], [], [], 0)[0]:
                chunk = os.read(self.fd, 4096)
                if not chunk:
                    break
                n += len(chunk)
        except OSError:
            pass
        return n

    def close(self) -> None:
        if self.owner is not None:
            try:
                self.owner.close()
            except Exception:  # noqa: BLE001
                pass


class PySerialIO:
    """Fallback for pyserial URL handlers without a file descriptor (socket://, loop://...)."""

    def __init__(self, port: Any, poll_s: float) -> None:
        self.port = port
        self.poll_s = poll_s

    def write(self, data: bytes | bytearray, deadline: float) -> None:
        import serial

        try:
            self.port.write(bytes(data))
        except serial.SerialTimeoutException as e:
            raise LinkTimeout(f"write blocked: {e}") from e
        except (serial.SerialException, OSError) as e:
            raise Disconnected(f"write failed: {e}") from e

    def read(self, n: int, deadline: float, max_n: int = 0, wake_ns: int = 0) -> bytes:
        import serial

        if wake_ns:
            sleep_until_ns(wake_ns)
        out = b""
        try:
            while len(out) < n:
                out += self.port.read(n - len(out))
                if len(out) < n and time.monotonic() >= deadline:
                    break
        except (serial.SerialException, OSError) as e:
            raise Disconnected(f"read failed: {e}") from e
        return out

    def flush_input(self) -> int:
        try:
            n = self.port.in_waiting
            self.port.reset_input_buffer()
            return int(n)
        except Exception:  # noqa: BLE001
            return 0

    def close(self) -> None:
        try:
            self.port.close()
        except Exception:  # noqa: BLE001
            pass


def open_rtu(url: str | int, *, baudrate: int, parity: str, stopbits: float, timeout_s: float, spin: bool,
             serial_kwargs: Mapping[str, Any] | None = None) -> FdIO | PySerialIO:
    """The serial line of an RTU link: ``url`` an open fd (not closed by us),
    a device path or a pyserial URL. Raises :class:`Disconnected` if it cannot."""
    if isinstance(url, int):
        try:
            os.fstat(url)
        except OSError as e:
            raise Disconnected(f"fd {url}: {e}") from e
        return FdIO(url, spin=spin)
    import serial

    try:
        port = open_serial_port(
            url,
            baudrate=baudrate,
            parity=parity,
            stopbits=stopbits,
            timeout=min(max(timeout_s / 4, 100e-6), 20e-3),
            write_timeout=max(timeout_s, 5e-3),
            **dict(serial_kwargs or {}),
        )
        port.reset_input_buffer()
    except (serial.SerialException, OSError, ValueError) as e:
        raise Disconnected(f"cannot open {url}: {e}") from e
    try:
        fd = port.fileno()
    except Exception:  # noqa: BLE001 - URL handlers have no fd
        fd = None
    return FdIO(fd, owner=port, spin=spin) if isinstance(fd, int) else PySerialIO(port, port.timeout)


# --------------------------------------------------------------------------
# TCP
class TcpIO:
    """A connected TCP socket (any object with ``send``, ``recv``, ``fileno``,
    ``close``), set non-blocking by :meth:`connect`; ``where`` names it in messages."""

    def __init__(self, sock: Any, spin: bool = False, where: str = "") -> None:
        self.sock = sock
        self.fds = [sock.fileno()]
        self.spin = spin
        self.where = where

    @classmethod
    def connect(cls, host: str, port: int, timeout_s: float, spin: bool = False) -> "TcpIO":
        """Connect with TCP_NODELAY. Raises :class:`Disconnected` if it cannot."""
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as e:  # refused, unreachable, timeout (socket.timeout is an OSError)
            raise Disconnected(f"cannot connect to {host}:{port}: {e}") from e
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            pass
        sock.setblocking(False)
        return cls(sock, spin, f"{host}:{port}")

    def write(self, data: bytes | bytearray, deadline: float) -> None:
        sock = self.sock
        try:
            try:
                sent = sock.send(data)
            except BlockingIOError:
                sent = 0
            if sent == len(data):  # always for ~30 bytes on a healthy socket
                return
            view = memoryview(data)[sent:]
            while view:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not select.select([], self.fds, [], remaining)[1]:
                    raise LinkTimeout(f"{self.where}: send blocked past the deadline")
                try:
                    view = view[sock.send(view):]
                except BlockingIOError:
                    pass
        except OSError as e:  # reset, broken pipe, ...
            raise Disconnected(f"{self.where}: {e}") from e

    def recv(self, deadline: float, wake_ns: int = 0) -> bytes:
        """The next chunk received (≥ 1 byte), or b"" once the deadline passed."""
        if wake_ns:
            sleep_until_ns(wake_ns)
        sock = self.sock
        fds = self.fds
        spin = self.spin
        clock = time.monotonic
        try:
            while True:
                remaining = deadline - clock()
                if not select.select(fds, (), (), 0.0 if spin else (remaining if remaining > 0 else 0))[0]:
                    if spin and remaining > 0:
                        continue
                    return b""
                try:
                    chunk = sock.recv(4096)
                except BlockingIOError:  # spurious readiness
                    continue
                if not chunk:
                    raise Disconnected(f"{self.where}: connection closed by peer")
                return chunk
        except OSError as e:  # reset, ...
            raise Disconnected(f"{self.where}: {e}") from e

    def drain(self) -> int:
        """Discard whatever is queued now; the number of bytes dropped."""
        n = 0
        try:
            while True:
                chunk = self.sock.recv(4096)
                if not chunk:
                    break
                n += len(chunk)
        except OSError:
            pass
        return n

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass
