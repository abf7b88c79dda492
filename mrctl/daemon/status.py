"""The status socket: ``mrctl status`` asks a running daemon for its live state.

Server side (a thread of the daemon): each connection gets one JSON line
and is closed. Client side (``mrctl status``, hil_sim's harnesses): one
connect, one read. The socket is created 0660 under a umask, so it is
never briefly wider.

A client may first send one JSON request line (``mrctl tap``,
:mod:`mrctl.daemon.tap`): the server waits up to 0.1 s for it, and a
request hook may take the connection over. ``mrctl status`` shuts its
sending side at once, so the reply is not delayed; a client that sends
nothing gets the status after 0.1 s.

Where: systemd's ``$RUNTIME_DIRECTORY``, else the per-user directory
``$TMPDIR/mrctl-<uid>`` (:func:`mrctl.util.files.private_dir`): created
0700, and neither the daemon nor ``mrctl status`` uses one that another
user owns or can write to (a local user who creates it first could plant a
socket there and show a spoofed state). A reply that is not a JSON object
is refused, never a traceback.

Scrapes cannot slow the loop: the snapshot (a 5000-tick timing summary
and its JSON) is computed at most once per :data:`REPLY_MAX_AGE_S` and the
same bytes go to every client asking meanwhile, and at most
:data:`MAX_REPLIES_PER_S` replies go out a second (a further client waits in
the listen backlog, the status thread sleeping, i.e. not holding the
interpreter). Eight scrapers in a tight loop then cost the loop what one
does (``bench/status_flood.py``).
"""

from __future__ import annotations

import json
import math
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable

from mrctl.errors import LinkFailure
from mrctl.util.files import check_private_dir, per_user_dir, private_dir
from mrctl.util.jsonutil import jsonable


class StatusError(LinkFailure, OSError):
    """No usable answer on the status socket: nothing running, or not mrctl
    (exit 3, the link-failure code: the link to the daemon); an OSError for
    callers that poll (hil_sim's harnesses)."""


def default_status_socket(check: bool = False) -> str:
    """$RUNTIME_DIRECTORY (systemd RuntimeDirectory=) or the per-user
    directory's socket; ``check``: refuse a per-user directory that is not
    ours alone (the client's side; the server creates it)."""
    rd = os.environ.get("RUNTIME_DIRECTORY")
    if rd:
        return str(Path(rd.split(":")[0]) / "status.sock")
    d = per_user_dir()
    if check and os.path.lexists(d):
        try:
            check_private_dir(d)
        except OSError as exc:
            raise StatusError(f"not asking: {exc}") from None
    return str(d / "status.sock")


#: how long the server waits for a request line before it answers with the status
REQUEST_WAIT_S = 0.1
#: a status reply is reused for this long (s): the loop's interpreter computes
#: at most 1 / REPLY_MAX_AGE_S snapshots a second, however many clients ask
REPLY_MAX_AGE_S = 0.2
#: replies sent per second at most; a client beyond waits its turn
MAX_REPLIES_PER_S = 50.0


class StatusServer:
    """Answers each connection with one JSON line of live state, then closes.

    ``requests(conn, request)``: called with a client's JSON request line;
    returns True if it took the connection over (then it closes it)."""

    def __init__(self, path: str, snapshot: Callable[[], dict[str, Any]],
                 requests: Callable[[socket.socket, dict[str, Any]], bool] | None = None) -> None:
        self.path = path
        self.snapshot = snapshot
        self.requests = requests
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._reply = b""
        self._reply_at = -math.inf
        self._next_reply_at = 0.0
        self.replies_built = 0  #: snapshots computed (tests, the bench)

    def reply(self, now: float) -> bytes:
        """The status line, rebuilt only when older than :data:`REPLY_MAX_AGE_S`."""
        if now - self._reply_at >= REPLY_MAX_AGE_S or not self._reply:
            self._reply = (json.dumps(jsonable(self.snapshot(), nonfinite="null")) + "\n").encode()
            self._reply_at = now
            self.replies_built += 1
        return self._reply

    def _pace(self) -> None:
        """Sleep until the next reply may go out (:data:`MAX_REPLIES_PER_S`)."""
        now = time.monotonic()
        wait = self._next_reply_at - now
        if wait > 0:
            self._stop.wait(wait)
            now += wait
        self._next_reply_at = max(now, self._next_reply_at) + 1.0 / MAX_REPLIES_PER_S

    def start(self) -> None:
        p = Path(self.path)
        if p.parent == per_user_dir():
            private_dir(p.parent)  # OSError: not ours alone; the service runs on without it
        else:
            p.parent.mkdir(parents=True, exist_ok=True, mode=0o770)
        if p.is_socket() or p.exists():
            if not p.is_socket():
                raise OSError(f"status socket path exists and is not a socket: {p}")
            if socket_alive(str(p)):
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
            req = _read_request(conn) if self.requests is not None else None
            if req is not None and self.requests is not None:
                try:
                    if self.requests(conn, req):
                        continue  # the hook owns the connection now
                except Exception:  # noqa: BLE001 - a bad request must not end the status thread
                    pass
            with conn:
                try:
                    self._pace()
                    conn.settimeout(1.0)
                    conn.sendall(self.reply(time.monotonic()))
                except OSError:
                    pass
                except Exception:  # noqa: BLE001 - a snapshot that fails must not end the status thread
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


def _read_request(conn: socket.socket) -> dict[str, Any] | None:
    """The client's request line (a JSON object), or None: it sent nothing
    within :data:`REQUEST_WAIT_S`, closed its side, or sent something else."""
    data = b""
    try:
        conn.settimeout(REQUEST_WAIT_S)
        while b"\n" not in data and len(data) < 4096:
            b = conn.recv(4096)
            if not b:
                break
            data += b
    except OSError:
        pass
    if not data.strip():
        return None
    try:
        req = json.loads(data.split(b"\n", 1)[0].decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):  # RecursionError: '[' * 200 000
        return None
    return req if isinstance(req, dict) else None


def socket_alive(path: str) -> bool:
    """True if a process accepts connections on the Unix socket ``path``
    (a daemon serves it; a socket file left by one that died refuses)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(0.5)
    try:
        s.connect(path)
        return True
    except OSError:
        return False
    finally:
        s.close()


def connect_status(path: str, timeout_s: float = 2.0) -> socket.socket:
    """A connection to the daemon's status socket; :class:`StatusError` saying
    why there is none."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(path)
    except FileNotFoundError:
        s.close()
        raise StatusError(f"no mrctl running (no status socket at {path})") from None
    except ConnectionRefusedError:
        s.close()
        raise StatusError(f"no mrctl running (stale status socket at {path})") from None
    except OSError as exc:
        s.close()
        raise StatusError(f"{path}: cannot connect: {exc.strerror or exc}") from None
    return s


def query_status(path: str, timeout_s: float = 2.0) -> dict[str, Any]:
    """Client side of ``mrctl status``: the daemon's state, a JSON object.
    :class:`StatusError` with a clear message otherwise."""
    s = connect_status(path, timeout_s)
    try:
        try:
            s.shutdown(socket.SHUT_WR)  # no request: the status, at once
        except OSError:
            pass
        chunks = []
        size = 0
        while size <= 1 << 20:
            try:
                b = s.recv(65536)
            except OSError as exc:
                raise StatusError(f"{path}: no reply: {exc.strerror or exc}") from None
            if not b:
                break
            chunks.append(b)
            size += len(b)
    finally:
        s.close()
    raw = b"".join(chunks)
    try:
        st = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):  # RecursionError: '[' * 200 000
        st = None
    if not isinstance(st, dict):
        shown = raw[:60].decode("utf-8", "replace").strip() or "nothing"
        raise StatusError(f"{path}: not a status reply from mrctl (got {shown!r})")
    return st


def _num(v: Any, fmt: str, scale: float = 1.0, unit: str = "") -> str:
    """A number as ``fmt`` (scaled, with its unit); anything else as it is."""
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return format(v * scale, fmt) + (f" {unit}" if unit else "")
    return "-" if v is None else str(v)


def format_status(st: dict[str, Any]) -> str:
    """``mrctl status``'s text: rounded to what the figures are worth, with units."""
    g = st.get
    t = g("timing") if isinstance(g("timing"), dict) else {}
    latch = f" ({g('latch_cause')})" if g("latch_cause") else ""
    lines = [
        f"{g('experiment')} (pid {g('pid')}): up {_num(g('uptime_s'), '.1f', unit='s')}, "
        f"{_num(g('rate_hz'), 'g', unit='Hz')}, {g('ticks')} ticks, law {g('law')}",
        f"current {_num(g('current_A'), '.4f', unit='A')}, F_des {_num(g('F_des_N'), '.1f', unit='N')}, "
        f"x {_num(g('x_m'), '.2f', 1e3, 'mm')}, v {_num(g('v_mps'), '.1f', 1e3, 'mm/s')}",
        f"safety {g('safety_state')}{latch} (fault {g('fault')}), link errors {g('link_errors')}",
    ]
    if g("latch_cause"):
        lines.append(f"  0 A, output disabled until `mrctl arm`: {g('fault_reason')}")
    if t:
        late = "/".join(_num(t.get(k), ".0f") for k in ("lateness_p50_us", "lateness_p99_us", "lateness_max_us"))
        lines.append(f"lateness p50/p99/max {late} µs, compute p99 {_num(t.get('compute_p99_us'), '.0f', unit='µs')}, "
                     f"overruns {t.get('overruns')}")
    rec = g("recorder")
    if isinstance(rec, dict):
        state = g("log") if isinstance(g("log"), str) else "ok"
        lines.append(f"log: {rec.get('rows_written')} rows written, {rec.get('dropped_rows')} lost"
                     + ("" if state == "ok" else f"; {state}"))
    acc = g("acceptance")
    if isinstance(acc, dict) and isinstance(acc.get("figures"), dict):
        from mrctl.runlog.acceptance import format_verdict

        try:
            lines.append("acceptance so far: " + format_verdict(acc))
        except (TypeError, ValueError, KeyError):
            lines.append(f"acceptance: {acc.get('verdict')}")
    stream, taps = g("stream"), g("taps")
    if isinstance(stream, dict):
        lines.append(f"stream {stream.get('url')}: {stream.get('datagrams')} datagrams sent, "
                     f"{stream.get('dropped')} dropped, {stream.get('rows_behind')} rows behind")
    if isinstance(taps, dict) and taps.get("active"):
        lines.append(f"taps: {taps.get('active')} connected")
    warnings = g("warnings")
    if isinstance(warnings, list):
        lines += [f"warning: {w}" for w in warnings[-3:]]
    return "\n".join(lines)
