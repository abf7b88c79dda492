"""The status socket: ``mrctl status`` asks a running daemon for its live state.

Server side (a thread of the daemon): each connection gets one JSON line
and is closed. Client side (``mrctl status``, hil_sim's harnesses): one
connect, one read. The socket is created 0660 under a umask, so it is
never briefly wider.
"""

from __future__ import annotations

import json
import os
import socket
import threading
from pathlib import Path
from typing import Any, Callable

from mrctl.util.jsonutil import jsonable


def default_status_socket() -> str:
    """$RUNTIME_DIRECTORY (systemd RuntimeDirectory=) or a per-user temp path."""
    rd = os.environ.get("RUNTIME_DIRECTORY")
    if rd:
        return str(Path(rd.split(":")[0]) / "status.sock")
    return f"/tmp/mrctl-{os.getuid()}/status.sock"


class StatusServer:
    """Answers each connection with one JSON line of live state, then closes."""

    def __init__(self, path: str, snapshot: Callable[[], dict[str, Any]]) -> None:
        self.path = path
        self.snapshot = snapshot
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        p = Path(self.path)
        p.parent.mkdir(parents=True, exist_ok=True, mode=0o770)
        if p.is_socket() or p.exists():
            if not p.is_socket():
                raise OSError(f"status socket path exists and is not a socket: {p}")
            if _socket_alive(str(p)):
                raise OSError(f"another mrctl is serving status at {p}")
            p.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o117)  # the socket is born 0660, never briefly wider
        try:
            sock.bind(str(p))
        finally:
            os.umask(old)
        os.chmod(p, 0o660)
        sock.listen(8)
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="mrctl-status", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            with conn:
                try:
                    conn.settimeout(1.0)
                    conn.sendall((json.dumps(jsonable(self.snapshot(), nonfinite="null")) + "\n").encode())
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()
            try:
                os.unlink(self.path)
            except OSError:
                pass


def _socket_alive(path: str) -> bool:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(0.5)
    try:
        s.connect(path)
        return True
    except OSError:
        return False
    finally:
        s.close()


def query_status(path: str, timeout_s: float = 2.0) -> dict[str, Any]:
    """Client side of ``mrctl status``; raises OSError with a clear message."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        try:
            s.connect(path)
        except FileNotFoundError:
            raise OSError(f"no mrctl running (no status socket at {path})") from None
        except ConnectionRefusedError:
            raise OSError(f"no mrctl running (stale status socket at {path})") from None
        chunks = []
        while True:
            b = s.recv(65536)
            if not b:
                break
            chunks.append(b)
    finally:
        s.close()
    return json.loads(b"".join(chunks).decode())
