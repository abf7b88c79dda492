"""The live UDP stream: each run-log row as one JSON datagram (PlotJuggler).

PlotJuggler's UDP server (Streaming → UDP Server, protocol JSON) parses
each datagram as one JSON object, flattens it into series named ``/<key>``
and, with "use field [timestamp] if available" ticked, takes the top-level
number ``timestamp`` (seconds) as the sample's time. It reads one object
per datagram (an array would become series ``[0]/F``, ``[1]/F``… sharing
one time), so every row is its own datagram, ~300 bytes for all columns.
A value that cannot be written in JSON (NaN, inf) is sent as ``null``,
which PlotJuggler skips: a datagram that does not parse would make it stop
its server.

``timestamp`` is the tick's deadline in Unix time (the run's start plus the
row's ``t``), so runs and restarts line up with other sources; ``t`` is the
run time. Rows are sent from a :class:`mrctl.daemon.rowbus.RowBus` block,
in the loop's idle time, through a non-blocking connected UDP socket:
a datagram the kernel has no room for (``EAGAIN``/``ENOBUFS``) or that it
refuses (``ECONNREFUSED``: nobody listens on the port, an ICMP error
reported on a later send) is counted and dropped, never waited for.
Datagrams lost by the receiver (its buffer full) are invisible here.
"""

from __future__ import annotations

import json
import socket
import struct
from array import array
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any, Callable

from mrctl.config.observe import parse_stream_url
from mrctl.errors import BadInput

#: rows formatted and sent between two looks at the clock
CHUNK_ROWS = 8
#: rows a stream may hold back before it drops new blocks (~16 s at 1 kHz)
MAX_BACKLOG_ROWS = 16384


def resolve(url: str) -> tuple[int, Any]:
    """(address family, socket address) of ``udp://HOST:PORT``; BadInput if
    it is malformed or the host does not resolve (checked at start-up)."""
    try:
        host, port = parse_stream_url(url)
    except ValueError as exc:
        raise BadInput(f"--stream: {exc}") from None
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    except (OSError, UnicodeError) as exc:  # UnicodeError: a label the IDNA codec refuses
        raise BadInput(f"--stream {url}: cannot resolve {host!r}: {getattr(exc, 'strerror', None) or exc}") from None
    family, _, _, _, addr = infos[0]
    return family, addr


def json_row_format(columns: Sequence[str], formats: Mapping[str, str]) -> str:
    """The ``%``-template of one row: ``{"timestamp":%.6f,"c1":fmt,...}``."""
    parts = ['"timestamp":%.6f'] + [f"{json.dumps(c)}:{formats.get(c, '%.9g')}" for c in columns]
    return "{" + ",".join(parts) + "}"


def _json_safe(text: str) -> str:
    """NaN and infinities (which ``%g`` writes as nan, inf, -inf) as null."""
    return text.replace(":nan", ":null").replace(":-inf", ":null").replace(":inf", ":null")


class UdpStream:
    """A :class:`~mrctl.daemon.rowbus.RowBus` sink sending rows as JSON datagrams.

    ``all_columns``: the bus's columns (must contain ``t``); ``columns``:
    the ones to send (None = all); ``every``: send rows whose index is a
    multiple of it; ``epoch0()``: Unix time of t = 0, asked once, at the
    first row sent.
    """

    def __init__(self, url: str, all_columns: Sequence[str], columns: Sequence[str] | None = None, every: int = 1,
                 *, epoch0: Callable[[], float], formats: Mapping[str, str] | None = None,
                 max_backlog_rows: int = MAX_BACKLOG_ROWS) -> None:
        cols = tuple(all_columns)
        sel = tuple(columns) if columns else cols
        if "t" not in cols:
            raise ValueError("the rows need a t column")
        unknown = [c for c in sel if c not in cols]
        if unknown:
            raise ValueError(f"unknown column(s) {unknown}")
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.url = url
        self.every = int(every)
        self.columns = tuple(c for c in cols if c in sel)  # the row's order
        fields = [j for j, c in enumerate(cols) if c in sel or c == "t"]
        self._tpos = fields.index(cols.index("t"))
        self._t_sent = "t" in sel
        self._unpack = struct.Struct("=" + "".join("d" if j in fields else "8x" for j in range(len(cols)))).unpack_from
        self._rb = 8 * len(cols)
        self._fmt = json_row_format(self.columns, formats or {})
        self._epoch0 = epoch0
        self._e0: float | None = None
        self.max_backlog_rows = max_backlog_rows
        family, addr = resolve(url)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            sock.connect(addr)  # connected: no address per send, and ICMP errors are reported
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self._pending: deque[list[Any]] = deque()
        self.done = False
        # counters: fed/dropped written by the loop thread, the rest by whoever works
        self.rows_fed = 0
        self.rows_done = 0
        self.rows_behind = 0  # dropped because the stream had fallen behind (backlog full)
        self.datagrams = 0  # sent
        self.no_room = 0  # EAGAIN / ENOBUFS: the kernel had no room, dropped
        self.refused = 0  # ECONNREFUSED: nobody listening (ICMP port unreachable)
        self.errors = 0  # any other send error
        self.last_error: str | None = None

    # -- loop thread -----------------------------------------------------------
    def feed(self, block: array, rows: int, row0: int) -> None:
        if self.rows_fed - self.rows_done - self.rows_behind + rows > self.max_backlog_rows:
            self.rows_behind += rows
            self.rows_fed += rows
            return
        self.rows_fed += rows
        self._pending.append([block, rows, row0, (-row0) % self.every])

    def work(self, until_ns: int, clock: Callable[[], int], pause: Callable[[], object] | None) -> bool:
        pend = self._pending
        if not pend:
            return False
        if self._e0 is None:
            self._e0 = float(self._epoch0())
        e0, unpack, fmt, rb, every, tpos = self._e0, self._unpack, self._fmt, self._rb, self.every, self._tpos
        send = self._sock.send
        keep_t = self._t_sent
        while pend:
            job = pend[0]
            data, n, _, i = job
            stop = min(n, i + CHUNK_ROWS * every)
            while i < stop:
                v = unpack(data, i * rb)
                args = (e0 + v[tpos],) + (v if keep_t else v[:tpos] + v[tpos + 1:])
                text = fmt % args
                if "nan" in text or "inf" in text:  # only a value can: no run-log column name has them
                    text = _json_safe(text)
                try:
                    send(text.encode("ascii"))
                    self.datagrams += 1
                except (BlockingIOError, InterruptedError):
                    self.no_room += 1
                except ConnectionRefusedError:
                    self.refused += 1
                except OSError as exc:
                    if exc.errno == 105:  # ENOBUFS
                        self.no_room += 1
                    else:
                        self.errors += 1
                        self.last_error = f"{type(exc).__name__}: {exc.strerror or exc}"
                i += every
            if i >= n:
                pend.popleft()
                self.rows_done += n
            else:
                job[3] = i
            if pause is not None:
                pause()
            if clock() >= until_ns:
                break
        return bool(pend)

    # -- end ------------------------------------------------------------------------
    def finish(self, reason: str) -> None:
        self.done = True
        self._pending.clear()
        self._sock.close()

    def stats(self) -> dict[str, Any]:
        return {"url": self.url, "every": self.every, "columns": list(self.columns),
                "datagrams": self.datagrams, "dropped": self.no_room + self.refused + self.errors,
                "no_room": self.no_room, "refused": self.refused, "errors": self.errors,
                "rows_behind": self.rows_behind, "backlog_rows": self.rows_fed - self.rows_done - self.rows_behind,
                "last_error": self.last_error}
