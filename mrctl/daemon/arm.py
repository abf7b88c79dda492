"""``mrctl arm``: the explicit re-arm after a latched fault (an E-stop, the
device's watchdog, a link loss longer than ``safety.latch_after_s``).

Why a command and not a timer: after a latch the coil stays at 0 A with the
output disabled until an operator has looked at the bench and says so
(LinuxCNC's estop latch needs the same). The request travels over the status
socket, so whoever may tap the run may re-arm it (group ``mrctl`` under
systemd); SIGHUP never re-arms.

Server side: the status server's request hook (:meth:`ArmServer.handle`)
takes ``{"arm": true}``, sets the controller's flag (taken at the next tick
boundary: the device is asked to clear its latched status, the supervisor
waits for a good sample without the cause) and answers, from a thread of its
own, once the supervisor has re-armed or refused (``arm_state``).
Client side: :func:`arm`.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from typing import Any, Callable, Mapping

from mrctl.core.safety import ARM_DONE, ARM_PENDING, ARM_REFUSED
from mrctl.core.safety_config import ARM_WAIT_S
from mrctl.daemon.tap import reply_once

__all__ = ["ArmServer", "ArmRefused", "arm"]

#: the client waits this long for the daemon's answer (the supervisor's wait, plus a margin)
REPLY_TIMEOUT_S = ARM_WAIT_S + 2.0


class ArmRefused(Exception):
    """The daemon refused the re-arm (the cause is still there) or is not latched."""


class ArmServer:
    """Takes ``{"arm": true}`` requests on the status socket, one at a time."""

    def __init__(self, ctl: Any, sup: Any, report: Callable[[str, int], None]) -> None:
        self.ctl = ctl
        self.sup = sup
        self.report = report
        self._lock = threading.Lock()

    def handle(self, conn: socket.socket, req: Mapping[str, Any]) -> bool:
        """The status server's request hook: True if this connection is now ours."""
        if "arm" not in req:
            return False
        threading.Thread(target=self._serve, args=(conn,), name="mrctl-arm", daemon=True).start()
        return True

    def _serve(self, conn: socket.socket) -> None:
        from mrctl.util.journal import NOTICE, WARNING

        with self._lock:  # one re-arm at a time: each answer is about its own request
            sup = self.sup
            sup.arm_state = ARM_PENDING
            sup.arm_message = "asked"
            self.ctl.arm_request = True
            deadline = time.monotonic() + ARM_WAIT_S + 1.0
            while sup.arm_state == ARM_PENDING and time.monotonic() < deadline:
                time.sleep(0.005)
            state, msg = sup.arm_state, sup.arm_message
        if state == ARM_DONE:
            self.report(f"safety: mrctl arm: {msg}", NOTICE)
            reply_once(conn, {"armed": True, "message": msg})
        else:
            why = msg if state == ARM_REFUSED else "no answer from the loop (is it running?)"
            self.report(f"safety: mrctl arm {why}", WARNING)
            reply_once(conn, {"armed": False, "error": why})


def arm(path: str, connect: Callable[[str], socket.socket] | None = None) -> str:
    """Ask the daemon at ``path`` to re-arm; returns its message (also
    "nothing to re-arm" when it is not latched). Raises :class:`ArmRefused`
    when it refuses (the cause is still there), and
    :class:`mrctl.daemon.status.StatusError` when there is no daemon."""
    from mrctl.daemon.status import StatusError, connect_status

    s = (connect or connect_status)(path)
    try:
        s.sendall(b'{"arm": true}\n')
        s.settimeout(REPLY_TIMEOUT_S)
        try:
            line = s.makefile("rb").readline(1 << 16)
        except (socket.timeout, TimeoutError):
            raise StatusError(f"{path}: no answer to arm within {REPLY_TIMEOUT_S:g} s") from None
    finally:
        s.close()
    try:
        rep = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        rep = None
    if not isinstance(rep, dict) or "armed" not in rep:
        shown = line[:60].decode("utf-8", "replace").strip() or "nothing"
        raise StatusError(f"{path}: not an arm reply from mrctl (got {shown!r}); is the daemon older than "
                          "mrctl arm?")
    if not rep.get("armed"):
        raise ArmRefused(str(rep.get("error") or rep.get("message") or "refused"))
    return str(rep.get("message", "re-armed"))
