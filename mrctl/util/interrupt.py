"""A user's stop of an offline command (Ctrl-C, or SIGTERM where the command
runs until stopped), told apart from a law that raises KeyboardInterrupt.

The law guards turn whatever a law raises into a law fault, a plugin's
``KeyboardInterrupt`` or ``SystemExit`` too: a law never takes the loop
down. Python's own SIGINT handler raises
``KeyboardInterrupt`` wherever the main thread is, inside a law's call as
well, where the interpreted build (and any plugin law in the compiled one)
spends much of a tick. A Ctrl-C landing there was a law fault: ``mrctl
simulate`` ended with "law raised KeyboardInterrupt", a sweep recorded its
point as a fault and went on. The command line's handlers note the signal
before they raise; the offline loop's guard (:mod:`mrctl.core.offline`,
which ``simulate`` and ``sweep`` run) lets a noted one through.

``mrctl run`` has its own handlers (:mod:`mrctl.daemon.signals`; the loop's
stop is a flag, never an exception inside a law): the daemon's guard never
asks, and its start-up handlers forget a note an earlier command in the
same process left (:func:`forget`), so a law's own KeyboardInterrupt there
is always the law's fault.
"""

from __future__ import annotations

import signal
import threading
from typing import Any

__all__ = ["forget", "install", "on_stop", "user_stopped"]

_state = {"signum": 0}


def on_stop(signum: int, _frame: Any) -> None:
    """The handler: note the signal, then stop the command as Ctrl-C does."""
    _state["signum"] = signum
    raise KeyboardInterrupt(signal.Signals(signum).name)


def user_stopped() -> bool:
    """Whether a stop signal came through :func:`on_stop` in this command."""
    return _state["signum"] != 0


def forget() -> None:
    """No stop noted (a command starting, or the daemon's start-up)."""
    _state["signum"] = 0


def install(sigterm: bool = False) -> None:
    """:func:`on_stop` for SIGINT (unless the process was started with it
    ignored, as a shell's background job is), and for SIGTERM when asked;
    forgets an earlier command's signal. Main thread only; elsewhere nothing."""
    forget()
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, on_stop)
    if sigterm:
        signal.signal(signal.SIGTERM, on_stop)
