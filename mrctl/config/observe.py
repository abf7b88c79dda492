"""The experiment's ``stream`` section: a live copy of the run log's rows.

``mrctl run --stream udp://HOST:PORT`` (or ``stream.url``) sends each row
of the run log as one JSON datagram, the form PlotJuggler's UDP server
reads (docs/observe.md). Checked here with key paths, like every key; the
sending is :mod:`mrctl.daemon.stream`.
"""

from __future__ import annotations

import ipaddress
from typing import Any
from urllib.parse import urlsplit

from mrctl.runlog.format import RUN_COLUMNS
from mrctl.util.schema import Custom, Num, Section, short_repr

#: the default PlotJuggler UDP server port
PLOTJUGGLER_PORT = 9870


def parse_stream_url(url: str) -> tuple[str, int]:
    """``udp://HOST:PORT`` (IPv6 as ``udp://[::1]:9870``) → (host, port);
    ValueError saying what is wrong."""
    if not isinstance(url, str) or not url:
        raise ValueError("must be a string udp://HOST:PORT")
    parts = urlsplit(url)
    if parts.scheme != "udp":
        raise ValueError(f"only udp://HOST:PORT is supported, got {short_repr(url)}")
    if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username or parts.password:
        raise ValueError(f"udp://HOST:PORT takes nothing else, got {short_repr(url)}")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"bad port in {short_repr(url)}") from None
    if not parts.hostname or port is None or not 1 <= port <= 65535:
        raise ValueError(f"needs a host and a port 1-65535, e.g. udp://127.0.0.1:{PLOTJUGGLER_PORT}; got {short_repr(url)}")
    why = host_problem(parts.hostname)
    if why:
        raise ValueError(f"host {short_repr(parts.hostname)}: {why}")
    return parts.hostname, port


def host_problem(host: str) -> str | None:
    """Why ``host`` cannot name a machine (an empty or over-long label, which
    the resolver would raise UnicodeError for), or None: an IP literal or a
    name of 1-63 character labels, at most 253 characters in all."""
    try:
        ipaddress.ip_address(host.split("%", 1)[0])
        return None
    except ValueError:
        pass
    try:
        ascii_name = host.encode("idna").decode("ascii")
    except UnicodeError as exc:
        return f"not a valid host name ({exc})"
    labels = ascii_name.rstrip(".").split(".")
    if not ascii_name or len(ascii_name) > 253 or any(not 1 <= len(label) <= 63 for label in labels):
        return "not a valid host name (every dot-separated label needs 1-63 characters)"
    return None


def parse_columns(value: Any) -> tuple[str, ...]:
    """Run-log column names (a list, or ``"a,b,c"``); ValueError naming the unknown ones."""
    names = [c.strip() for c in value.split(",")] if isinstance(value, str) else value
    if not isinstance(names, (list, tuple)) or not names or not all(isinstance(c, str) and c for c in names):
        raise ValueError("must be a non-empty list of run-log column names")
    unknown = [c for c in names if c not in RUN_COLUMNS]
    if unknown:
        raise ValueError(f"unknown column(s) {', '.join(unknown)}; the run log has {', '.join(RUN_COLUMNS)}")
    if len(set(names)) != len(names):
        raise ValueError("a column is named twice")
    return tuple(names)


def _url_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    try:
        parse_stream_url(value)
    except ValueError as exc:
        return None, [f"{path}: {exc}"]
    return value, []


def _columns_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    try:
        return parse_columns(value), []
    except ValueError as exc:
        return None, [f"{path}: {exc}"]


def stream_section() -> Section:
    """The ``stream`` section of the experiment schema."""
    return Section({
        "url": Custom(_url_check, default=None,
                      doc="udp://HOST:PORT: send every run-log row as one JSON datagram with a `timestamp` "
                          "(PlotJuggler's UDP server, JSON protocol; docs/observe.md); null = off. "
                          "`mrctl run --stream` overrides it"),
        "every": Num(default=1, integer=True, min=1, max=1_000_000,
                     doc="send every Nth row (decimation; 10 = 100 rows/s at 1 kHz)"),
        "columns": Custom(_columns_check, default=None,
                          doc="run-log columns to send, e.g. [F_des, F, I]; null = all "
                              "(`timestamp` is always sent)"),
    }, doc="live stream of the run log's rows (mrctl run)")
