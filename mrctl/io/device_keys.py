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


def _local_addresses() -> frozenset[str]:
    """Every address of this host's own interfaces (normalised as :func:`normal_ip`
    does): the host name's addresses, and each interface's through a UDP
    socket bound to it (no packet is sent). Read at each lock, never cached:
    interfaces come and go."""
    found: set[str] = set()
    names = {socket.gethostname(), socket.getfqdn()}
    try:
        names |= {name for _i, name in socket.if_nameindex()}  # interface names resolve on some systems
    except OSError:
        pass
    for name in names:
        try:
            for info in socket.getaddrinfo(name, None):
                found.add(str(info[4][0]).split("%", 1)[0].lower())
        except (OSError, UnicodeError):
            pass
    found |= _interface_addresses()
    return frozenset(found)


def _interface_addresses() -> set[str]:
    """The IPv4 and IPv6 addresses the kernel lists for this host's interfaces
    (/proc/net/if_inet6 and the routing socket's view through ``ip``-free
    reads): what a device served on this host can be reached at."""
    out: set[str] = set()
    try:
        with open("/proc/net/if_inet6", encoding="ascii") as f:
            for line in f:
                hexaddr = line.split()[0]
                out.add(str(ipaddress.IPv6Address(int(hexaddr, 16))))
    except (OSError, ValueError, IndexError):
        pass
    try:  # IPv4: the kernel's local routing table lists every address of every interface
        with open("/proc/net/fib_trie", encoding="ascii") as f:
            prev = ""
            for line in f:
                text = line.strip()
                if text.startswith("/32 host LOCAL") and prev.startswith("|-- "):
                    out.add(prev[4:].strip())
                prev = text
    except OSError:
        pass
    return out


def _is_local(ip: str) -> bool:
    """``ip`` reaches this host: an unspecified address (0.0.0.0, ::, a server's
    "every interface"), a loopback one (127/8, ::1), or one of its interfaces'."""
    try:
        addr = ipaddress.ip_address(ip.split("%", 1)[0])
    except ValueError:
        return False
    if addr.is_unspecified or addr.is_loopback:
        return True
    return str(addr) in _local_addresses()


def network_device_key(kind: str, host: str, port: int, unit: int | None = None) -> str:
    """``"tcp IP:PORT"``: the device endpoint, whatever name a config gives it
    (:func:`normal_ip`; every spelling of this host itself is ``"tcp
    local:PORT"``: 0.0.0.0, ::, localhost, 127/8, ::1 and the addresses of its
    own interfaces reach one device served here) and whatever protocol speaks to it (``kind`` is not
    part of the key: a Modbus TCP link and a serial-over-TCP URL to one
    endpoint reach one device). ``unit`` (``" unit N"``) only for a Modbus
    TCP gateway, whose unit ids are separate devices behind one endpoint; a
    device answering TCP directly ignores the unit id, so any unit id there
    is the same device."""
    ip = normal_ip(host, int(port))
    if _is_local(ip):  # a device served on this host: 0.0.0.0, ::, localhost, 127/8, its own addresses
        where = f"local:{int(port)}"
    else:
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
