"""Signals before and after the loop: a stop is honoured from the first
instruction of ``mrctl run``, and never leaves the device or a file half done.

The loop's own handlers (SIGINT/SIGTERM stop it, SIGHUP asks for a reload)
exist only while it runs (:mod:`mrctl.daemon.service`). Before that, the
default action of SIGTERM and SIGHUP would kill the process wherever it is:
no 0 A on a link just opened, an empty run log left behind that refuses the
next run. So ``mrctl run`` installs :func:`install_startup` first thing:

* SIGINT/SIGTERM raise :class:`StopSignal` in the main thread, which unwinds
  the start-up through its ``ExitStack`` (0 A if the link is open, the run
  log this run created removed); the run exits 0, like a stop of the loop.
  Inside :func:`deferred` (a file created and its clean-up not yet
  registered, a link opened and its 0 A not yet registered) the stop is
  held and raised at the section's end;
* SIGHUP is remembered (:func:`take_hup`): the start-up reads the config
  anyway; one that came after the read becomes a reload once the loop runs.

After the loop, :func:`install_late` keeps a second signal from cutting the
final sidecar short: it is noted and ignored (the shutdown is under way).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Any, Iterator

from mrctl.util import interrupt

__all__ = ["StopSignal", "install_startup", "install_late", "deferred", "take_hup", "restore", "STOP_SIGNALS"]

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignal(KeyboardInterrupt):
    """SIGINT or SIGTERM during start-up (a KeyboardInterrupt, so that no
    ``except Exception`` on the way swallows it)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


_state: dict[str, Any] = {"depth": 0, "pending": None, "hup": False}


def _on_stop(signum: int, _frame: Any) -> None:
    if _state["depth"] > 0:
        _state["pending"] = _state["pending"] or signum
        return
    raise StopSignal(signum)


def _on_hup(_signum: int, _frame: Any) -> None:
    _state["hup"] = True


def _on_late(signum: int, _frame: Any) -> None:
    if signum == signal.SIGHUP:
        _state["hup"] = True


def install_startup() -> dict[int, Any]:
    """Install the start-up handlers (main thread only); returns the ones they
    replace, for :func:`restore` (none if they are in place already: the
    CLI installs them before anything else, the service again). Forgets a
    stop an earlier offline command in this process noted
    (:mod:`mrctl.util.interrupt`): the loop's law faults are never a stop."""
    interrupt.forget()
    if signal.getsignal(signal.SIGTERM) is _on_stop or threading.current_thread() is not threading.main_thread():
        return {}  # in place already, or a service run from a thread (tests): signals are not its to handle
    _state.update(depth=0, pending=None, hup=False)
    old = {s: signal.signal(s, _on_stop) for s in STOP_SIGNALS}
    old[signal.SIGHUP] = signal.signal(signal.SIGHUP, _on_hup)
    return old


def install_late() -> None:
    """After the loop: a further SIGINT/SIGTERM/SIGHUP is ignored while the run
    log and sidecar are finished."""
    if threading.current_thread() is not threading.main_thread():
        return
    for s in (*STOP_SIGNALS, signal.SIGHUP):
        signal.signal(s, _on_late)


def restore(old: dict[int, Any]) -> None:
    """Put back the handlers :func:`install_startup` replaced."""
    for s, h in old.items():
        signal.signal(s, h)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """A stop that arrives inside is raised at the end (not in the middle of
    creating a resource and registering its clean-up)."""
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
    pending = _state["pending"]
    if pending is not None and _state["depth"] == 0:
        _state["pending"] = None
        raise StopSignal(pending)


def take_hup() -> bool:
    """Whether a SIGHUP came since the last call (and forget it)."""
    hup, _state["hup"] = _state["hup"], False
    return bool(hup)
