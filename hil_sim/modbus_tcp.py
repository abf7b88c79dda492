"""Modbus TCP servers of the simulated bench (the device: :mod:`hil_sim.modbus_device`).

Two ways to serve, the same behaviour on the wire: :class:`ModbusTcpInline`
polled from hil_sim's clock thread while it spins (the default: a reply
never waits for a thread wake-up), and :func:`serve_modbus_tcp`, one thread
per connection (``--serve thread``). Both take up to 16 clients (mbpoll can
poll alongside the loop) and apply the reply faults and the ``disconnect``
window.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections import deque
from typing import Any, Callable

from hil_sim.faults import FaultBit
from hil_sim.modbus_device import Deferred, ModbusDevice
from hil_sim.modbus_wire import FAULT_POLL_S, IDLE_POLL_S, mbap_frame_length
from hil_sim.state import DeviceState
from mrctl.io.registers import RegisterMap
from mrctl.io.base import FrameError

__all__ = ["ModbusTcpInline", "serve_modbus_tcp", "serve_modbus_tcp_inline"]

_MAX_CLIENTS = 16
_DISCONNECT = int(FaultBit.DISCONNECT)


def serve_modbus_tcp(
    state: DeviceState,
    host: str,
    port: int,
    register_map: RegisterMap | None,
    stop: threading.Event,
    ready: Callable[[str], None] | None = None,
    *,
    fc23: bool = True,
    max_clients: int = _MAX_CLIENTS,
    on_device: Callable[[ModbusDevice], None] | None = None,
) -> None:
    """Serve Modbus TCP on (host, port) until ``stop`` is set.

    ``port`` 0 picks a free port; ``ready`` gets ``"modbus-tcp HOST:PORT"``
    with the real port once listening. One thread per connection (mbpoll can
    poll alongside the loop); at most ``max_clients`` at once, further
    connections are closed on accept. On stop every connection is closed
    (clients see Disconnected) before returning.

    The ``disconnect`` fault closes every client connection and the listening
    socket (new connections are refused) until the window ends, then listens
    again on the same port.
    """
    dev = ModbusDevice(state, register_map, fc23=fc23)
    if on_device is not None:
        on_device(dev)
    poll_s = FAULT_POLL_S if state.faults else IDLE_POLL_S
    lsock: socket.socket | None = socket.create_server((host, port))
    lsock.settimeout(poll_s)
    actual = lsock.getsockname()[1]
    conns: dict[threading.Thread, socket.socket] = {}

    def drop_all() -> None:
        for t, conn in conns.items():
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for t in conns:
            t.join(1.0)
        conns.clear()

    try:
        if ready is not None:
            ready(f"modbus-tcp {host}:{actual}")
        while not stop.is_set():
            if state.fault_bits & _DISCONNECT:
                if lsock is not None:
                    dev.fault_counts["disconnects"] += 1
                    lsock.close()
                    lsock = None
                    drop_all()
                stop.wait(FAULT_POLL_S)
                continue
            if lsock is None:  # the disconnect window is over: listen again
                lsock = socket.create_server((host, actual))
                lsock.settimeout(poll_s)
            try:
                conn, _addr = lsock.accept()
            except (socket.timeout, InterruptedError):
                continue
            except OSError:
                if stop.is_set():
                    break
                raise
            for t in [t for t in conns if not t.is_alive()]:
                del conns[t]
            if len(conns) >= max_clients:
                conn.close()
                continue
            t = threading.Thread(target=_tcp_connection, args=(dev, conn, stop), name="modbus-tcp-conn", daemon=True)
            conns[t] = conn
            t.start()
    finally:
        if lsock is not None:
            lsock.close()
        drop_all()


def _tcp_connection(dev: ModbusDevice, conn: socket.socket, stop: threading.Event) -> None:
    state = dev.state
    delayed: deque[tuple[float, bytes]] = deque()  # (due monotonic s, bytes): delay_replies
    try:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        poll_s = FAULT_POLL_S if state.faults else IDLE_POLL_S
        conn.settimeout(poll_s)
        buf = bytearray()
        while not stop.is_set():
            if state.fault_bits & _DISCONNECT:
                return  # the listener closes the rest
            if delayed:
                now = time.monotonic()
                while delayed and delayed[0][0] <= now:
                    conn.sendall(delayed.popleft()[1])
                conn.settimeout(max(1e-4, min(poll_s, delayed[0][0] - now)) if delayed else poll_s)
            try:
                chunk = conn.recv(4096)
            except socket.timeout:
                continue
            if not chunk:
                return
            buf += chunk
            while True:
                try:
                    total = mbap_frame_length(buf)
                except FrameError:
                    dev.frames_dropped += 1
                    return  # unsynchronisable stream: drop the connection
                if not total:
                    break
                frame = bytes(buf[:total])
                del buf[:total]
                resp = dev.handle_tcp_frame(frame)
                if resp is None:
                    continue
                if isinstance(resp, Deferred):  # SYNC: the clock sends it after its tick

                    def owed_reply(r: Deferred = resp) -> None:
                        out = dev.reply_now(r.build(), True, delayed)  # (a deque append is thread-safe)
                        if out is not None:
                            conn.sendall(out)

                    resp.owed.attach(owed_reply)
                    continue
                out = dev.reply_now(resp, True, delayed)
                if out is not None:
                    conn.sendall(out)
                elif delayed:
                    conn.settimeout(max(1e-4, min(poll_s, delayed[0][0] - time.monotonic())))
    except OSError:
        return
    finally:
        try:
            conn.close()
        except OSError:
            pass



class ModbusTcpInline:
    """Modbus TCP served from the clock thread's spin phase (``--serve inline``).

    The threaded server answers each request only once its connection thread
    has woken up and taken the GIL from the spinning clock; on this VM that
    often took longer than the rest of the period, so a device-paced (SYNC)
    request missed its tick (docs/performance.md). Here the clock itself
    polls the listening socket and every connection (one ``poll(0)`` system
    call per pass), parses, answers, and sends SYNC replies right after the
    tick that applies them: no thread hand-off anywhere.

    Same behaviour as :func:`serve_modbus_tcp` otherwise: up to
    ``max_clients`` connections, reply faults (drop, delay, corrupt,
    garbage), the ``disconnect`` window (all connections and the listener
    closed, then listening again on the same port). A client that does not
    read its replies (socket buffer full) is disconnected, since the clock
    must never block on it.
    """

    def __init__(self, state: DeviceState, host: str, port: int, register_map: RegisterMap | None = None,
                 *, fc23: bool = True, max_clients: int = _MAX_CLIENTS, device: Any = None) -> None:
        #: ``device``: another register space with ModbusDevice's face (hil_sim/labjack_t7.py)
        self.dev = device if device is not None else ModbusDevice(state, register_map, fc23=fc23)
        self.state = state
        self.host = host
        self.max_clients = max_clients
        self._poller = select.poll()
        self._lsock: socket.socket | None = None
        self.port = port
        self._listen()
        self.port = self._lsock.getsockname()[1]  # type: ignore[union-attr]
        #: fd -> [socket, receive buffer, delayed replies deque[(due monotonic s, bytes)]]
        self._conns: dict[int, list[Any]] = {}
        self._n_delayed = 0
        self._down = False  # inside a disconnect window
        #: a device that restarts (the emulated T7's watchdog reset) drops every connection, as its network does
        self._generation = getattr(self.dev, "generation", 0)

    def _listen(self) -> None:
        s = socket.create_server((self.host, self.port))
        s.setblocking(False)
        self._lsock = s
        self._poller.register(s.fileno(), select.POLLIN)

    def poll_once(self) -> None:
        """Serve whatever has arrived, without blocking. Never raises for a
        client's doing (a bad stream or a dead peer closes that connection)."""
        fbits = self.state.fault_bits
        if fbits & _DISCONNECT or self._down:
            if self._disconnect_window(fbits):
                return
        gen = getattr(self.dev, "generation", 0)
        if gen != self._generation:
            self._generation = gen
            for fd in list(self._conns):
                self._drop(fd)
        if self._n_delayed:
            self._flush_delayed()
        lsock = self._lsock
        lfd = lsock.fileno() if lsock is not None else -1
        for fd, ev in self._poller.poll(0):
            if fd == lfd:
                self._accept()
            else:
                self._receive(fd)

    def _disconnect_window(self, fbits: int) -> bool:
        """Close everything when the window opens, listen again when it ends;
        True = no link right now."""
        if fbits & _DISCONNECT:
            if not self._down:
                self._down = True
                self.dev.fault_counts["disconnects"] += 1
                for fd in list(self._conns):
                    self._drop(fd)
                if self._lsock is not None:
                    self._poller.unregister(self._lsock.fileno())
                    self._lsock.close()
                    self._lsock = None
            return True
        self._down = False
        self._listen()
        return False

    def _accept(self) -> None:
        assert self._lsock is not None
        while True:
            try:
                conn, _addr = self._lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # e.g. ECONNABORTED: the client gave up before we took it
            if len(self._conns) >= self.max_clients:
                conn.close()
                continue
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conns[conn.fileno()] = [conn, bytearray(), deque()]
            self._poller.register(conn.fileno(), select.POLLIN)

    def _drop(self, fd: int) -> None:
        c = self._conns.pop(fd, None)
        if c is None:
            return
        self._n_delayed -= len(c[2])
        try:
            self._poller.unregister(fd)
        except (KeyError, ValueError):
            pass
        try:
            c[0].close()
        except OSError:
            pass

    def _receive(self, fd: int) -> None:
        c = self._conns.get(fd)
        if c is None:
            return
        conn, buf = c[0], c[1]
        try:
            chunk = conn.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(fd)
            return
        if not chunk:
            self._drop(fd)
            return
        buf += chunk
        dev = self.dev
        while True:
            try:
                total = mbap_frame_length(buf)
            except FrameError:
                dev.frames_dropped += 1
                self._drop(fd)  # unsynchronisable stream: drop the connection
                return
            if not total:
                return
            frame = bytes(buf[:total])
            del buf[:total]
            resp = dev.handle_tcp_frame(frame)
            if resp is None:
                continue
            if isinstance(resp, Deferred):  # SYNC: the clock sends it after its tick
                resp.owed.attach(lambda fd=fd, r=resp: self._reply(fd, r.build()))
                continue
            if not self._reply(fd, resp):
                return

    def _reply(self, fd: int, adu: bytes) -> bool:
        """One response through the reply faults, then out; False if the
        connection is gone."""
        c = self._conns.get(fd)
        if c is None:
            return False  # the connection went away while the reply was owed
        q = c[2]
        n_queued = len(q)
        out = self.dev.reply_now(adu, True, q)
        self._n_delayed += len(q) - n_queued
        return True if out is None else self._send(fd, out)

    def _send(self, fd: int, data: bytes) -> bool:
        c = self._conns.get(fd)
        if c is None:
            return False  # the connection went away while the reply was owed
        try:
            n = c[0].send(data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError:
            self._drop(fd)
            return False
        if n != len(data):  # the client is not reading: it can't be waited for
            self._drop(fd)
            return False
        return True

    def _flush_delayed(self) -> None:
        now = time.monotonic()
        for fd in list(self._conns):
            q = self._conns[fd][2]
            while q and q[0][0] <= now:
                self._n_delayed -= 1
                if not self._send(fd, q.popleft()[1]):
                    break

    def close(self) -> None:
        """Close every connection (clients see Disconnected) and the listener."""
        for fd in list(self._conns):
            self._drop(fd)
        if self._lsock is not None:
            try:
                self._poller.unregister(self._lsock.fileno())
            except (KeyError, ValueError):
                pass
            self._lsock.close()
            self._lsock = None


def serve_modbus_tcp_inline(
    state: DeviceState,
    host: str,
    port: int,
    register_map: RegisterMap | None,
    stop: threading.Event,
    ready: Callable[[str], None] | None = None,
    *,
    fc23: bool = True,
    max_clients: int = _MAX_CLIENTS,
    on_device: Callable[[ModbusDevice], None] | None = None,
    pause_s: float = 1e-4,
) -> None:
    """:class:`ModbusTcpInline` polled in a loop until ``stop`` (a drop-in for
    :func:`serve_modbus_tcp`, for tests and benchmarks without a bench clock;
    ``pause_s`` between polls, 0 = spin a core as hil_sim's clock does)."""
    srv = ModbusTcpInline(state, host, port, register_map, fc23=fc23, max_clients=max_clients)
    if on_device is not None:
        on_device(srv.dev)
    try:
        if ready is not None:
            ready(f"modbus-tcp {host}:{srv.port}")
        poll = srv.poll_once
        while not stop.is_set():
            poll()
            if pause_s:
                time.sleep(pause_s)
    finally:
        srv.close()
