"""A device's identity for the daemon's ownership lock: the same device,
whatever name a user gives it (a symlinked port, localhost vs 127.0.0.1)."""

from __future__ import annotations

import os
import socket

__all__ = ["network_device_key", "serial_device_key"]


def network_device_key(kind: str, host: str, port: int, unit: int | None = None) -> str:
    """``"KIND IP:PORT[ unit N]"``: the host resolved, so that ``localhost`` and
    ``127.0.0.1`` are one device (the literal name if it does not resolve)."""
    try:
        ip = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][4][0]
    except (OSError, UnicodeError):
        ip = host.lower()
    where = f"[{ip}]:{port}" if ":" in ip else f"{ip}:{port}"
    return f"{kind} {where}" + (f" unit {unit}" if unit is not None else "")


def serial_device_key(url: str | int | None) -> str | None:
    """``"serial /real/path"`` for a port path (symlinks such as
    /dev/serial/by-id/… resolved), ``"tcp IP:PORT"`` for pyserial's
    ``socket://`` and ``rfc2217://`` URLs, None for anything else (an open
    fd, ``loop://``)."""
    if not isinstance(url, str) or not url:
        return None
    scheme, sep, rest = url.partition("://")
    if sep:
        if scheme not in ("socket", "rfc2217"):
            return None
        host, _, port = rest.split("/", 1)[0].split("?", 1)[0].rpartition(":")
        return network_device_key("tcp", host.strip("[]"), int(port)) if port.isdigit() else None
    return f"serial {os.path.realpath(url)}"
