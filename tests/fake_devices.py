"""Fake devices for the tests: a TCP port that notices every connection."""

from __future__ import annotations

import socket
import threading


class Listener:
    """A TCP port that counts connections and bytes: a device that notices everything."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.connections = 0
        self.bytes = 0
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.connections += 1
            conn.settimeout(0.2)
            try:
                data = conn.recv(4096)
                self.bytes += len(data)
            except OSError:
                pass
            conn.close()

    def close(self) -> None:
        self._stop.set()
        self._th.join(2)
        self.sock.close()
