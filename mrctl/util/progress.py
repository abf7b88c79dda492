"""Feedback on every long command (identify's fits, simulate's long runs, sweeps):
a tqdm progress bar on a terminal, or plain lines without one.

tqdm is optional (``pip install 'mrctl[identify]'`` brings it); without it,
or when stderr is a log or a pipe, the bar becomes a line on stderr every
10 % of the work (and every ``every_s`` between), so a command never
fails for want of a progress bar and a journal gets lines, not a redrawn
bar. ``delay_s``: nothing is shown before the work has taken that long, so
a command that may be quick (a short simulation) prints nothing extra.
"""

from __future__ import annotations

import sys
import time
from typing import Any

__all__ = ["Bar", "make_bar"]


class Bar:
    """A progress bar that does nothing (``enabled=False``) or prints lines."""

    def __init__(self, total: int, desc: str, enabled: bool = True, stream: Any = None, *, initial: int = 0,
                 unit: str = "", delay_s: float = 0.0, every_s: float = 0.0) -> None:
        self.total = max(int(total), 1)
        self.desc = desc
        self.enabled = enabled
        self.n = int(initial)
        self.stream = stream
        self.unit = unit
        self.delay_s = float(delay_s)
        self.every_s = float(every_s)
        self._next = (int(10 * self.n / self.total) + 1) / 10.0
        self._t0 = time.perf_counter()
        self._last = -float("inf")

    def update(self, n: int = 1, **postfix: Any) -> None:
        self.n += n
        if not self.enabled:
            return
        done = self.n / self.total
        now = time.perf_counter()
        step = done >= self._next or (self.every_s > 0 and now - self._last >= self.every_s)
        if step and now - self._t0 >= self.delay_s:
            self._next = (int(done * 10) + 1) / 10.0
            self._last = now
            extra = ", ".join(f"{k} {v}" for k, v in postfix.items())
            count = f" {self.n}/{self.total}{' ' + self.unit if self.unit else ''}" if self.unit else ""
            print(f"{self.desc}: {min(done, 1.0):4.0%}{count} ({now - self._t0:.1f} s)"
                  + (f" {extra}" if extra else ""), file=self.stream or sys.stderr, flush=True)

    def set_description(self, desc: str) -> None:
        self.desc = desc

    def close(self) -> None:
        pass


class _Tqdm(Bar):
    def __init__(self, total: int, desc: str, stream: Any = None, *, initial: int = 0, unit: str = "",
                 delay_s: float = 0.0) -> None:
        super().__init__(total, desc, True, stream, initial=initial, unit=unit, delay_s=delay_s)
        from tqdm import tqdm

        fmt = ("{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt}" + (" {unit}" if unit else "")
               + " [{elapsed}<{remaining}]{postfix}")
        self._bar = tqdm(total=self.total, initial=initial, desc=desc, file=stream or sys.stderr, leave=True,
                         unit=unit or "it", delay=delay_s, dynamic_ncols=True, bar_format=fmt)

    def update(self, n: int = 1, **postfix: Any) -> None:
        self.n += n
        if postfix:
            self._bar.set_postfix({k: v for k, v in postfix.items()}, refresh=False)
        self._bar.update(n)

    def set_description(self, desc: str) -> None:
        self._bar.set_description(desc)

    def close(self) -> None:
        if self._bar.n < self._bar.total:  # finished early (converged): show it complete
            self._bar.update(self._bar.total - self._bar.n)
        self._bar.close()


def make_bar(total: int, desc: str, enabled: bool = True, stream: Any = None, *, initial: int = 0,
             unit: str = "", delay_s: float = 0.0, every_s: float = 0.0) -> Bar:
    """A tqdm bar when enabled, on a terminal, and tqdm is installed; else
    plain lines (a log or a pipe gets a line every 10 %, and every
    ``every_s`` between) or nothing. ``initial``: work already done (a resumed
    sweep); ``unit``: what is counted (shown with the counts); ``delay_s``:
    shown only once the work has taken that long."""
    out = stream or sys.stderr
    kw = {"initial": initial, "unit": unit, "delay_s": delay_s}
    if enabled and not (hasattr(out, "isatty") and out.isatty()):
        return Bar(total, desc, True, stream, every_s=every_s, **kw)
    if enabled:
        try:
            import tqdm  # noqa: F401
        except ImportError:
            return Bar(total, desc, True, stream, every_s=every_s, **kw)
        return _Tqdm(total, desc, stream, **kw)
    return Bar(total, desc, False, stream, **kw)
