"""Several daemons on one machine: where each one's status socket is, and ``mrctl ls``.

A daemon is addressed by its status socket (:mod:`mrctl.daemon.status`):

* under systemd, ``$RUNTIME_DIRECTORY/status.sock``: ``/run/mrctl/status.sock``
  for ``mrctl.service``, ``/run/mrctl/NAME/status.sock`` for ``mrctl@NAME``;
* otherwise in this user's private directory ``$TMPDIR/mrctl-UID/``:
  ``status.sock`` for the first ``mrctl run``, ``NAME.sock`` for
  ``mrctl run --instance NAME``, and ``run-PID.sock`` for a second run
  started without a name while the first one serves ``status.sock`` (it
  says so: ``mrctl status --instance run-PID``), rather than running without
  a status socket.

:func:`list_daemons` asks every socket of those directories that answers
(a stale socket of a daemon that died is left out); ``mrctl ls`` prints it.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path
from typing import Any

from mrctl.daemon.status import StatusError, socket_alive, default_status_socket, query_status
from mrctl.errors import BadInput
from mrctl.util.files import check_private_dir, per_user_dir

__all__ = ["SYSTEM_DIR", "check_instance", "client_socket", "server_socket", "list_daemons", "format_daemons"]

#: systemd's RuntimeDirectory=mrctl (mrctl.service) and mrctl/%i (mrctl@.service)
SYSTEM_DIR = Path("/run/mrctl")

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}")


def check_instance(name: str) -> str:
    """``name`` if it can name a daemon (letters, digits, ``_.@-``, at most
    64, not ``status``); ``BadInput`` otherwise (it becomes a file name)."""
    if not _NAME.fullmatch(name) or name == "status":
        raise BadInput(f"--instance: {name!r} is not a daemon name (letters, digits and _.@- only, at most 64, "
                       f"not 'status')")
    return name


def _user_socket(name: str) -> Path:
    return per_user_dir() / f"{name}.sock"


def client_socket(socket: str | None, instance: str | None) -> str:
    """The socket ``mrctl status``/``tap``/``exporter`` ask: ``--socket``;
    ``--instance NAME`` (this user's ``NAME.sock`` if there is one, else
    systemd's ``/run/mrctl/NAME/status.sock``); or the default, and when
    nothing serves the default but exactly one other daemon runs that this
    user can ask (its own, or a service's in ``/run/mrctl``), that one."""
    if socket:
        return socket
    if instance is not None:
        check_instance(instance)
        mine = _user_socket(instance)
        return str(mine) if os.path.lexists(mine) else str(SYSTEM_DIR / instance / "status.sock")
    default = default_status_socket(check=True)
    if os.environ.get("RUNTIME_DIRECTORY") or socket_alive(default):
        return default
    running = [d for d in list_daemons() if d.get("answering")]  # the system's mrctl.service too
    return running[0]["socket"] if len(running) == 1 else default


def server_socket(explicit: str | None, instance: str | None) -> tuple[str, str | None]:
    """Where ``mrctl run`` serves its status, and a notice to print if it is
    not where ``mrctl status`` looks first (a second unnamed run)."""
    if explicit:
        return explicit, None
    if instance is not None and not os.environ.get("RUNTIME_DIRECTORY"):
        return str(_user_socket(check_instance(instance))), None
    default = default_status_socket()
    if os.environ.get("RUNTIME_DIRECTORY") or not socket_alive(default):
        return default, None
    name = f"run-{os.getpid()}"
    path = str(_user_socket(name))
    return path, (f"{default} is another mrctl's: status of this one at {path} "
                  f"(mrctl status --instance {name}; mrctl ls lists them; --instance NAME names a run)")


def _candidates(system: bool) -> list[tuple[str | None, Path]]:
    """(instance, socket) of every socket that may be a daemon's."""
    out: list[tuple[str | None, Path]] = []
    d = per_user_dir()
    try:
        check_private_dir(d)
        for p in sorted(d.glob("*.sock")):
            out.append((None if p.name == "status.sock" else p.stem, p))
    except OSError:
        pass  # none, or not ours alone: nothing to trust there
    rd = os.environ.get("RUNTIME_DIRECTORY")
    if rd:
        p = Path(rd.split(":")[0]) / "status.sock"
        if p not in [q for _, q in out]:
            out.append((None, p))
    if system:
        for p in [SYSTEM_DIR / "status.sock", *sorted(SYSTEM_DIR.glob("*/status.sock"))]:
            if os.path.lexists(p) and p not in [q for _, q in out]:
                out.append((None if p.parent == SYSTEM_DIR else p.parent.name, p))
    return out


def list_daemons(system: bool = True, timeout_s: float = 1.0) -> list[dict[str, Any]]:
    """Every daemon this user can see: instance, config, experiment, pid,
    socket, uptime (s), safety state, law, rate. A socket whose daemon is
    gone (refused) is left out; one that cannot be asked (no permission, no
    reply) is listed with ``answering: False`` and the reason."""
    found: list[dict[str, Any]] = []
    for name, path in _candidates(system):
        entry: dict[str, Any] = {"instance": name, "socket": str(path)}
        try:
            st = query_status(str(path), timeout_s)
        except StatusError as exc:
            if str(exc).startswith("no mrctl running"):  # gone, or its socket left behind
                continue
            entry.update(answering=False, error=str(exc))
            found.append(entry)
            continue
        entry.update(answering=True, pid=st.get("pid"), config=st.get("config_file"),
                     experiment=st.get("experiment"), uptime_s=st.get("uptime_s"),
                     state=st.get("safety_state"), law=st.get("law"), rate_hz=st.get("rate_hz"))
        if entry["instance"] is None and st.get("instance"):
            entry["instance"] = st["instance"]
        found.append(entry)
    return found


def _uptime(s: Any) -> str:
    if not isinstance(s, (int, float)):
        return "-"
    return time.strftime("%H:%M:%S", time.gmtime(s)) if s < 86400 else f"{s / 86400:.1f} d"


def format_daemons(found: list[dict[str, Any]]) -> str:
    """``mrctl ls``'s table (one line per daemon), or a line saying there is none."""
    if not found:
        return f"no mrctl running (looked in {per_user_dir()} and {SYSTEM_DIR})"
    rows = [("INSTANCE", "PID", "UPTIME", "STATE", "CONFIG", "SOCKET")]
    for d in found:
        rows.append((d.get("instance") or "-", str(d.get("pid") or "-"), _uptime(d.get("uptime_s")),
                     str(d.get("state") or ("?" if d.get("answering") else "not answering")),
                     str(d.get("config") or d.get("error") or "-"), d["socket"]))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)) + "  " + r[-1] for r in rows)
