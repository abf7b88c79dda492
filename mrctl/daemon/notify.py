"""systemd notification: READY, STATUS, WATCHDOG, STOPPING (sd_notify protocol).

No libsystemd dependency: the protocol is one datagram per message.
"""

from __future__ import annotations

import os
import socket


class Notifier:
    """Sends sd_notify datagrams to $NOTIFY_SOCKET; a no-op without it.

    Why not python-systemd: it is a C extension not on PyPI wheels for every
    platform, and the protocol is one datagram per message."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        path = env.get("NOTIFY_SOCKET")
        self.addr: str | bytes | None = None
        if path:
            self.addr = ("\0" + path[1:]) if path.startswith("@") else path
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        self.watchdog_s: float | None = None
        if usec and usec.isdigit() and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) / 1e6
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return self.addr is not None

    def send(self, *lines: str) -> bool:
        if self.addr is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.sendto("\n".join(lines).encode(), self.addr)
            return True
        except OSError:
            return False

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
