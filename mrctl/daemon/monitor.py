"""The monitor thread: everything slow that watches the loop from outside.

It shows the live progress line (sized to the terminal, so it never
wraps), sends systemd ``STATUS=`` and ``WATCHDOG=1`` (the watchdog only
while the loop's tick counter advances, i.e. from a healthy loop), runs
config reloads off the loop (SIGHUP only sets an event), and calls a
``watch`` hook every poll (the service warns there when the run log starts
losing rows). It never touches the link or the laws directly.

A reload runs in a thread of its own (one at a time; a SIGHUP meanwhile is
kept for when it ends): however long it takes, and whatever a plugin does
in it (``SystemExit``, an import that never returns), the monitor goes on
polling, warning and feeding the watchdog, and later reloads still run.
Nothing the hooks raise stops the monitor.
"""

from __future__ import annotations

import shutil
import threading
import time
from typing import Callable, TextIO

from mrctl.daemon.notify import Notifier


class Monitor:
    """Polls the running service every 50 ms from its own thread."""

    def __init__(self, notifier: Notifier, ticks: Callable[[], int], live_line: Callable[[], str],
                 reload: Callable[[], None], err: TextIO, live: bool,
                 watch: Callable[[], None] | None = None) -> None:
        self.notifier = notifier
        self.ticks = ticks
        self.live_line = live_line
        self.reload = reload
        self.err = err
        self.live = live
        self.watch = watch
        self.reload_event = threading.Event()
        self._reloader: threading.Thread | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mrctl-monitor", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        n = self.notifier
        wd = n.watchdog_s
        last_ticks = -1
        last_wd = 0.0
        last_live = 0.0
        is_tty = self.err.isatty() if hasattr(self.err, "isatty") else False
        while not self._stop.wait(0.05):
            now = time.monotonic()
            if self.reload_event.is_set() and not self.reloading():
                self.reload_event.clear()
                self._reloader = threading.Thread(target=self._reload_once, name="mrctl-reload", daemon=True)
                self._reloader.start()
            if self.watch is not None:
                try:
                    self.watch()
                except BaseException:  # noqa: BLE001 - a report must never stop the watchdog
                    pass
            ticks = self.ticks()
            if wd is not None and now - last_wd >= wd / 2:
                if ticks > last_ticks:  # the loop is alive: only then feed the watchdog
                    n.send("WATCHDOG=1")
                    last_wd = now
                last_ticks = ticks
            if now - last_live >= (0.5 if is_tty else 5.0):
                last_live = now
                try:
                    line = self.live_line()
                except BaseException as exc:  # noqa: BLE001 - the watchdog above goes on regardless
                    line = f"(live line failed: {type(exc).__name__})"
                if n.enabled:
                    n.send(f"STATUS={line}")
                if self.live:
                    self._show(line, is_tty)
        if self.live and is_tty:
            self._show(self.live_line(), is_tty)  # the final state, not the last one drawn (83 % at the end)
            print(file=self.err, flush=True)

    def reloading(self) -> bool:
        """Whether a reload is running now."""
        return self._reloader is not None and self._reloader.is_alive()

    def _reload_once(self) -> None:
        try:
            self.reload()
        except BaseException:  # noqa: BLE001 - the service reports its own failures; this thread just ends
            pass

    def _show(self, line: str, is_tty: bool) -> None:
        if is_tty:
            # one column short of the width: a full line would wrap on some terminals
            width = max(20, shutil.get_terminal_size((80, 24)).columns - 1)
            print("\r" + fit_line(line, width).ljust(width), end="", file=self.err, flush=True)
        else:
            print(line, file=self.err, flush=True)


def fit_line(line: str, width: int) -> str:
    """``line`` cut to ``width`` between fields (at a `` | `` or, failing
    that, a space), never inside a number."""
    if len(line) <= width:
        return line
    for sep in (" | ", " "):
        i = line.rfind(sep, 0, width + len(sep))  # a separator that starts within the width
        if 0 < i <= width:
            return line[:i].rstrip()
    return line[:width]


def live_line(ticks: int, total: int | None, rate_hz: float, I_A: float, state: str, link_errors: int,
              log_losing: bool, timing: str) -> str:
    """The live line, most important first (a narrow terminal cuts the end):
    progress, elapsed and remaining time, current, safety state, link
    errors, the log's trouble, timing."""
    elapsed = ticks / rate_hz if rate_hz else 0.0
    if total:
        frac = min(1.0, ticks / total)
        left = max(0.0, (total - ticks) / rate_hz) if rate_hz else 0.0
        head = f"[{'#' * int(frac * 10):<10}] {100 * frac:3.0f}% elapsed {elapsed:.1f} s, {left:.1f} s left"
    else:
        head = f"elapsed {elapsed:.1f} s ({ticks} ticks)"
    log = " LOG LOSING ROWS" if log_losing else ""
    return f"{head} | I {I_A:.3f} A {state} link_err {link_errors}{log} | {timing}"
