"""Feedback on long fits: a tqdm progress bar, or plain lines without tqdm.

tqdm is optional (``pip install 'mrctl[identify]'`` brings it); without it
the bar becomes a line on stderr every 10 % of the work, so a fit never
fails for want of a progress bar.
"""

from __future__ import annotations

import sys
import time
from typing import Any

__all__ = ["Bar", "make_bar"]


class Bar:
    """A progress bar that does nothing (``enabled=False``) or prints lines."""

    def __init__(self, total: int, desc: str, enabled: bool = True, stream: Any = None) -> None:
        self.total = max(int(total), 1)
        self.desc = desc
        self.enabled = enabled
        self.n = 0
        self.stream = stream
        self._next = 0.1
        self._t0 = time.perf_counter()

    def update(self, n: int = 1, **postfix: Any) -> None:
        self.n += n
        if not self.enabled:
            return
        done = self.n / self.total
        if done >= self._next:
            self._next = (int(done * 10) + 1) / 10.0
            extra = ", ".join(f"{k} {v}" for k, v in postfix.items())
            print(f"{self.desc}: {min(done, 1.0):4.0%} ({time.perf_counter() - self._t0:.1f} s)"
                  + (f" {extra}" if extra else ""), file=self.stream or sys.stderr, flush=True)

    def set_description(self, desc: str) -> None:
        self.desc = desc

    def close(self) -> None:
        pass


class _Tqdm(Bar):
    def __init__(self, total: int, desc: str, stream: Any = None) -> None:
        super().__init__(total, desc, True, stream)
        from tqdm import tqdm

        self._bar = tqdm(total=self.total, desc=desc, file=stream or sys.stderr, leave=True,
                         bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}]{postfix}")

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


def make_bar(total: int, desc: str, enabled: bool = True, stream: Any = None) -> Bar:
    """A tqdm bar when enabled, on a terminal, and tqdm is installed; else
    plain lines (a log or a pipe gets a line every 10 %, not a redrawn bar)
    or nothing."""
    out = stream or sys.stderr
    if enabled and not (hasattr(out, "isatty") and out.isatty()):
        return Bar(total, desc, True, stream)
    if enabled:
        try:
            import tqdm  # noqa: F401
        except ImportError:
            return Bar(total, desc, True, stream)
        return _Tqdm(total, desc, stream)
    return Bar(total, desc, False, stream)
