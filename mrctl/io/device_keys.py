"""A device's identity for the daemon's ownership lock: the same device,
whatever name a user gives it (a symlinked port, localhost vs 127.0.0.1)."""

from __future__ import annotations

import ipaddress
import os
import socket

__all__ = ["network_device_key", "serial_device_key", "normal_ip"]


def normal_ip(host: str, port: int) -> str:
    """The address a host name or literal reaches, in one spelling: names
    resolved (the literal, lower-cased, if it does not resolve), an
    IPv4-mapped IPv6 address (``::ffff:127.0.0.1``) as its IPv4 address,
    IPv6 compressed, without a zone for a global address."""
    try:
        ip = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][4][0]
    except (OSError, UnicodeError, ValueError):
        ip = host.strip("[]").lower()
    try:
        addr = ipaddress.ip_address(ip.split("%", 1)[0])
    except ValueError:
        return ip
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        return str(addr.ipv4_mapped)
    return str(addr) + (f"%{ip.split('%', 1)[1]}" if "%" in ip and addr.is_link_local else "")


def network_device_key(kind: str, host: str, port: int, unit: int | None = None) -> str:
    """``"tcp IP:PORT"``: the device endpoint, whatever name a config gives it
    (:func:`normal_ip`) and whatever protocol speaks to it (``kind`` is not
    part of the key: a Modbus TCP link and a serial-over-TCP URL to one
    endpoint reach one device). ``unit`` (``" unit N"``) only for a Modbus
    TCP gateway, whose unit ids are separate devices behind one endpoint; a
    device answering TCP directly ignores the unit id, so any unit id there
    is the same device."""
    ip = normal_ip(host, int(port))
    where = f"[{ip}]:{int(port)}" if ":" in ip else f"{ip}:{int(port)}"
    return f"tcp {where}" + (f" unit {unit}" if unit is not None else "")


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
