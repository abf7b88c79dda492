"""Fake TCP peers for bench/ and tests/: a port nobody listens on, and a
server that answers every connection with the same bytes (a mute Dask
scheduler, an HTTP server where a scheduler was expected, random bytes)."""

from __future__ import annotations

import contextlib
import socket
import threading

__all__ = ["ReplyingServer", "free_port"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on (bound, then closed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ReplyingServer:
    """A TCP server on loopback answering each connection with ``reply``
    once it has read what the client sent first (or waited 1 s for it);
    None: never a byte. Every connection is held open until :meth:`close`,
    which also closes the listening socket. A context manager."""

    def __init__(self, reply: bytes | None) -> None:
        self.reply = reply
        self._sock = socket.socket()
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(8)
        self.port: int = self._sock.getsockname()[1]
        self.address = f"tcp://127.0.0.1:{self.port}"  #: as ``mrctl sweep --scheduler`` takes it
        self._held: list[socket.socket] = []
        self._lock = threading.Lock()
        self._closed = False
        threading.Thread(target=self._run, name="replying-server", daemon=True).start()

    def _run(self) -> None:
        while True:
            try:
                c, _ = self._sock.accept()
            except OSError:  # closed
                return
            with self._lock:
                if self._closed:
                    c.close()
                    return
                self._held.append(c)
            if self.reply is not None:
                with contextlib.suppress(OSError):
                    c.settimeout(1.0)
                    with contextlib.suppress(OSError):
                        c.recv(65536)
                    c.sendall(self.reply)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            held, self._held = self._held, []
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the accept
        self._sock.close()
        for c in held:
            c.close()

    def __enter__(self) -> "ReplyingServer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
