"""``mrctl tap``: the next N rows of a running daemon, as CSV, over the status socket.

Like LinuxCNC's halsampler: a user who may connect to the status socket
(0660, group ``mrctl`` under systemd) sees a service's live rows without
reading its files. The status socket's protocol gains one request: the
client sends one JSON line ``{"tap": N, "columns": [...], "trigger":
"F>500", "pre": 100}`` (``N`` null: until the client leaves); the daemon
answers one JSON line (``{"ok": true, "columns": [...], ...}`` or
``{"error": "..."}``), then the CSV (header, rows in the run log's own
formats), then one line ``# end: REASON`` (``complete``, ``the run
ended``, ``dropped: …``). A client that sends nothing gets the status
reply, as before.

The rows come from the row bus (:mod:`mrctl.daemon.rowbus`), block by
block (256 rows at 1 kHz), starting with the first block handed over after
the request: "the next N rows". They are formatted where the run log is,
in the loop's idle time; the tap's own thread only sends bytes. A client
that reads too slowly (4 MiB unsent, or a send blocked 2 s) is dropped,
never waited for. At most :data:`MAX_TAPS` at once.

A trigger (``fault``, i.e. ``fault>0``, or ``COLUMN>VALUE`` /
``COLUMN<VALUE``) starts the capture at the next rising edge of the
condition (false, then true), with ``pre`` rows before it, taken from the
blocks seen since the request, as halscope does.
"""

from __future__ import annotations

import json
import queue
import re
import select
import socket
import struct
import threading
import time
from array import array
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, BinaryIO, Callable

from mrctl.runlog.format import row_format

MAX_TAPS = 4
MAX_UNSENT_BYTES = 4 << 20
SEND_TIMEOUT_S = 2.0
_CHUNK = 8


@dataclass(frozen=True)
class Trigger:
    column: str
    op: str  # ">" or "<"
    value: float

    def __str__(self) -> str:
        return f"{self.column}{self.op}{self.value:g}"


def parse_trigger(text: str, columns: Sequence[str]) -> Trigger:
    """``fault`` or ``COLUMN>VALUE`` / ``COLUMN<VALUE``; ValueError otherwise."""
    t = str(text).strip()
    if t == "fault":
        return Trigger("fault", ">", 0.0)
    m = re.fullmatch(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*([<>])\s*(\S+)\s*", t)
    if not m:
        raise ValueError(f"trigger {text!r}: use fault, COLUMN>VALUE or COLUMN<VALUE (e.g. F>500)")
    col, op, val = m.groups()
    if col not in columns:
        raise ValueError(f"trigger {text!r}: no column {col!r}; the run log has {', '.join(columns)}")
    try:
        value = float(val)
    except ValueError:
        raise ValueError(f"trigger {text!r}: {val!r} is not a number") from None
    return Trigger(col, op, value)


@dataclass(frozen=True)
class TapRequest:
    rows: int | None
    columns: tuple[str, ...]
    trigger: Trigger | None = None
    pre: int = 0


def parse_request(req: Mapping[str, Any], columns: Sequence[str]) -> TapRequest:
    """A client's request line (already JSON-decoded); ValueError saying what is wrong."""
    n = req.get("tap")
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"tap: the number of rows must be a positive integer or null, got {n!r}")
    cols = req.get("columns") or list(columns)
    if not isinstance(cols, list) or not all(isinstance(c, str) for c in cols):
        raise ValueError("columns: must be a list of column names")
    unknown = [c for c in cols if c not in columns]
    if unknown:
        raise ValueError(f"columns: unknown {', '.join(unknown)}; the run log has {', '.join(columns)}")
    trig = req.get("trigger")
    trigger = parse_trigger(trig, columns) if trig is not None else None
    pre = req.get("pre", 0)
    if isinstance(pre, bool) or not isinstance(pre, int) or not 0 <= pre <= 1_000_000:
        raise ValueError(f"pre: rows before the trigger, 0-1000000, got {pre!r}")
    if pre and trigger is None:
        raise ValueError("pre: only with a trigger")
    return TapRequest(n, tuple(c for c in columns if c in cols), trigger, pre)


class TapSink:
    """A row-bus sink that formats CSV for one tap client (see the module docstring)."""

    def __init__(self, all_columns: Sequence[str], req: TapRequest, formats: Mapping[str, str]) -> None:
        cols = tuple(all_columns)
        self.req = req
        self.columns = req.columns
        self.ncols = len(cols)
        self._rb = 8 * len(cols)
        pattern = "".join("d" if c in req.columns else "8x" for c in cols)
        row = row_format(self.columns, {c: formats.get(c, "%r") for c in self.columns}, require_core=False)
        self._fmts = {m: (struct.Struct("=" + pattern * m).unpack_from, row * m) for m in range(1, _CHUNK + 1)}
        self._tcol = cols.index(req.trigger.column) if req.trigger else -1
        self._armed = req.trigger is not None
        self._prev = True  # a trigger needs the condition false first, then true
        self._hist: deque[list[Any]] = deque()  # blocks seen while armed (for pre)
        self._pending: deque[list[Any]] = deque()
        self.out: queue.SimpleQueue = queue.SimpleQueue()  # bytes, then None at the end
        self.produced = 0  # bytes put on out (the working thread)
        self.consumed = 0  # bytes sent (the tap's thread)
        self.rows_out = 0
        self.trigger_row: int | None = None
        self.done = False
        self.end_reason: str | None = None

    # -- loop thread ------------------------------------------------------------
    def feed(self, block: array, rows: int, row0: int) -> None:
        if self.produced - self.consumed > MAX_UNSENT_BYTES:
            self._end("dropped: the tap client reads too slowly")
            return
        self._pending.append([block, rows, row0, 0])

    def work(self, until_ns: int, clock: Callable[[], int], pause: Callable[[], object] | None) -> bool:
        pend = self._pending
        while pend and not self.done:
            if self._armed:
                self._scan(pend[0])
                if clock() >= until_ns:
                    break
                continue
            job = pend[0]
            data, n, _, i = job
            m = min(_CHUNK, n - i)
            if self.req.rows is not None:
                m = min(m, self.req.rows - self.rows_out)
            unpack, fmt = self._fmts[m]
            text = (fmt % unpack(data, i * self._rb)).encode("ascii")
            self.out.put(text)
            self.produced += len(text)
            self.rows_out += m
            i += m
            if i >= n:
                pend.popleft()
            else:
                job[3] = i
            if self.req.rows is not None and self.rows_out >= self.req.rows:
                self._end("complete")
            if pause is not None:
                pause()
            if clock() >= until_ns:
                break
        return bool(pend) and not self.done

    def _scan(self, job: list[Any]) -> None:
        """Look for the trigger's rising edge in the first waiting block."""
        data, n, row0, i = job
        trig = self.req.trigger
        assert trig is not None
        col = data[self._tcol::self.ncols]
        prev, val, above = self._prev, trig.value, trig.op == ">"
        for j in range(i, n):
            x = col[j]
            cur = x > val if above else x < val
            if cur and not prev:
                self._fire(job, j)
                return
            prev = cur
        self._prev = prev
        self._pending.popleft()
        self._hist.append(job)
        while len(self._hist) > 1 and sum(b[1] for b in self._hist) - self._hist[0][1] >= self.req.pre:
            self._hist.popleft()

    def _fire(self, job: list[Any], j: int) -> None:
        data, n, row0, _ = job
        self._armed = False
        self.trigger_row = row0 + j
        start = self.trigger_row - self.req.pre
        earlier = [b for b in self._hist if b[2] + b[1] > start]
        self._hist.clear()
        job[3] = max(0, start - row0)
        for b in reversed(earlier):
            b[3] = max(0, start - b[2])
            self._pending.appendleft(b)
        if earlier:
            job[3] = 0

    # -- any thread ---------------------------------------------------------------
    def _end(self, reason: str) -> None:
        if not self.done:
            self.end_reason = reason
            self.done = True
            self.out.put(None)

    def finish(self, reason: str) -> None:
        self._end(reason)

    def cancel(self, reason: str) -> None:
        """The tap's thread: the client left or cannot keep up."""
        self._end(reason)


def _peer_left(conn: socket.socket) -> bool:
    try:
        r, _, _ = select.select([conn], [], [], 0)
        return bool(r) and conn.recv(1, socket.MSG_PEEK) == b""
    except OSError:
        return True


class TapServer:
    """Serves tap requests on connections the status server hands over.

    ``bus``: the row bus; ``info()``: extra header fields (rate, experiment);
    ``on_count(n)``: called with the number of taps whenever it changes (the
    service makes the controller record rows only while something consumes
    them)."""

    def __init__(self, bus: Any, formats: Mapping[str, str], info: Callable[[], dict[str, Any]],
                 on_count: Callable[[int], None] | None = None, max_taps: int = MAX_TAPS) -> None:
        self.bus = bus
        self.formats = dict(formats)
        self.info = info
        self.on_count = on_count
        self.max_taps = max_taps
        self._lock = threading.Lock()
        self._active: set[TapSink] = set()
        self._threads: list[threading.Thread] = []
        self.served = 0
        self.dropped = 0

    @property
    def active(self) -> int:
        return len(self._active)

    def handle(self, conn: socket.socket, req: Mapping[str, Any]) -> bool:
        """The status server's request hook: True if this connection is now ours."""
        if "tap" not in req:
            return False
        try:
            r = parse_request(req, self.bus.columns)
        except ValueError as exc:
            reply_once(conn, {"error": str(exc)})
            return True
        with self._lock:
            if len(self._active) >= self.max_taps:
                reply_once(conn, {"error": f"{self.max_taps} taps are running already; try again later"})
                return True
            sink = TapSink(self.bus.columns, r, self.formats)
            self._active.add(sink)
            n = len(self._active)
        if self.on_count is not None:
            self.on_count(n)
        th = threading.Thread(target=self._serve, args=(conn, sink), name="mrctl-tap", daemon=True)
        self._threads = [t for t in self._threads if t.is_alive()] + [th]
        th.start()
        return True

    def wait(self, timeout_s: float) -> None:
        """Let the taps' threads send their last rows (at the end of the run)."""
        deadline = time.monotonic() + timeout_s
        for th in list(self._threads):
            th.join(max(0.0, deadline - time.monotonic()))

    def _serve(self, conn: socket.socket, sink: TapSink) -> None:
        try:
            conn.settimeout(SEND_TIMEOUT_S)
            head = {"ok": True, "columns": list(sink.columns), "rows": sink.req.rows,
                    "trigger": str(sink.req.trigger) if sink.req.trigger else None, "pre": sink.req.pre, **self.info()}
            conn.sendall((json.dumps(head) + "\n" + ",".join(sink.columns) + "\n").encode())
            self.bus.add(sink)
            while True:
                try:
                    chunk = sink.out.get(timeout=0.25)
                except queue.Empty:
                    if _peer_left(conn):
                        sink.cancel("the client left")
                        break
                    continue
                if chunk is None:
                    break
                conn.sendall(chunk)
                sink.consumed += len(chunk)
            if sink.end_reason != "the client left":
                conn.sendall(f"# end: {sink.end_reason}\n".encode())
        except OSError:  # a send blocked SEND_TIMEOUT_S, or the client reset
            sink.cancel("dropped: the tap client reads too slowly or left")
        finally:
            self.bus.remove(sink)
            with self._lock:
                self._active.discard(sink)
                n = len(self._active)
                self.served += 1
                self.dropped += bool(sink.end_reason and sink.end_reason.startswith("dropped"))
            conn.close()
            if self.on_count is not None:
                self.on_count(n)

    def stats(self) -> dict[str, Any]:
        return {"active": len(self._active), "served": self.served, "dropped": self.dropped}


def reply_once(conn: socket.socket, obj: dict[str, Any]) -> None:
    """One JSON line to a request of the status socket, then the connection closed
    (a tap refused, an arm answered): never raises."""
    try:
        conn.settimeout(1.0)
        conn.sendall((json.dumps(obj) + "\n").encode())
    except OSError:
        pass
    finally:
        conn.close()


# -- client side (mrctl tap) ------------------------------------------------------
#: seconds ``mrctl tap`` waits for the daemon's header (as ``mrctl status`` waits 2 s)
HEADER_TIMEOUT_S = 2.0


@dataclass
class TapResult:
    rows: int
    end: str  # the daemon's end reason ("complete", "the run ended", "dropped: …"), or "interrupted"
    header: dict[str, Any]


def tap(path: str, out: BinaryIO, rows: int | None = None, columns: Sequence[str] | None = None,
        trigger: str | None = None, pre: int = 0, connect: Callable[[str], socket.socket] | None = None) -> TapResult:
    """Ask the daemon at ``path`` for rows and write the CSV to ``out`` as it
    comes. Raises :class:`mrctl.daemon.status.StatusError` (exit 3) if there
    is no daemon or it refuses; KeyboardInterrupt passes through (the
    caller ends cleanly)."""
    from mrctl.daemon.status import StatusError, connect_status

    s = (connect or connect_status)(path)
    try:
        req = {"tap": rows, "columns": list(columns) if columns else None, "trigger": trigger, "pre": pre}
        s.sendall((json.dumps(req) + "\n").encode())
        s.settimeout(HEADER_TIMEOUT_S)  # the daemon answers at once, before any row
        f = s.makefile("rb")
        try:
            first = f.readline(1 << 16)
        except (socket.timeout, TimeoutError):
            raise StatusError(f"{path}: no answer within {HEADER_TIMEOUT_S:g} s (is an mrctl daemon serving "
                              f"it, or a busy or hung one?)") from None
        s.settimeout(None)  # then a trigger may wait long; Ctrl-C ends it
        try:
            head = json.loads(first.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):  # RecursionError: '[' * 200 000
            head = None
        if not isinstance(head, dict):
            shown = first[:60].decode("utf-8", "replace").strip() or "nothing"
            raise StatusError(f"{path}: not a tap reply from mrctl (got {shown!r}); "
                              "is the daemon older than mrctl tap?")
        if "error" in head:
            raise StatusError(f"tap refused: {head['error']}")
        n = -1  # the CSV header is not a row
        end = "the connection closed"
        for line in f:
            if line.startswith(b"#"):
                end = line[1:].decode("utf-8", "replace").strip().removeprefix("end:").strip()
                break
            out.write(line)
            n += 1
        out.flush()
        return TapResult(max(n, 0), end, head)
    finally:
        s.close()
