"""What a run offers live observers: the row bus, the UDP stream, taps.

Built by the service after the recorder (:meth:`Observe.attach`):

* with a run log, the recorder's block hand-over feeds the row bus
  (``Recorder.on_block``); without one, the controller records into the
  bus itself, but only while something consumes rows (a stream, or at
  least one tap): a run nobody watches does no per-tick work for this;
* host pacing: the bus's sinks work in the loop's idle time, after the run
  log's formatting; device pacing: in the bus's worker thread;
* the status server hands tap requests to :class:`mrctl.daemon.tap.TapServer`.

Figures for ``mrctl status`` and the sidecar: :meth:`Observe.stats`.
Docs: docs/observe.md.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from typing import Any, Callable

from mrctl.daemon.rowbus import RowBus
from mrctl.daemon.stream import UdpStream, resolve
from mrctl.daemon.tap import TapServer
from mrctl.errors import BadInput
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS


def stream_settings(cfg: Any, url: str | None, every: int | None,
                    columns: Sequence[str] | None) -> tuple[str, int, tuple[str, ...] | None] | None:
    """The stream to send, options over the config's ``stream`` section; None
    if off. BadInput (exit 2, before the device is touched) if it cannot be."""
    sec = cfg.get("stream") if hasattr(cfg, "get") else None
    url = url if url is not None else (sec.get("url") if sec is not None else None)
    if not url:
        return None
    every = every if every is not None else (sec.get("every") if sec is not None else 1) or 1
    if every < 1:
        raise BadInput(f"--stream-every: must be >= 1, got {every}")
    cols = columns if columns is not None else (sec.get("columns") if sec is not None else None)
    resolve(url)  # BadInput: malformed, or the host does not resolve
    return url, int(every), tuple(cols) if cols else None


def _chain(first: Callable[[int], object], second: Callable[[int], object]) -> Callable[[int], None]:
    def background(until_ns: int) -> None:
        first(until_ns)
        second(until_ns)

    return background


class Observe:
    """The run's live consumers (see the module docstring)."""

    def __init__(self, columns: Sequence[str], formats: Mapping[str, str], *, block_ticks: int, defer: bool,
                 stream: tuple[str, int, tuple[str, ...] | None] | None, epoch0: Callable[[], float],
                 info: Callable[[], dict[str, Any]]) -> None:
        self.bus = RowBus(columns, block_ticks, defer=defer)
        self.stream: UdpStream | None = None
        if stream is not None:
            url, every, cols = stream
            self.stream = UdpStream(url, columns, cols, every, epoch0=epoch0, formats=formats)
        self.taps = TapServer(self.bus, formats, info, on_count=self._taps_changed)
        self._ctl: Any = None
        self._own_rows = False  # the controller records into the bus (no run log)

    @classmethod
    def for_run(cls, cfg: Any, ctl: Any, loop: Any, rec: Any, stream: tuple[str, int, tuple[str, ...] | None] | None,
                clock_ns: Callable[[], int], name: str, warn: Callable[[str], None]) -> Observe:
        """The service's: built after the recorder, attached, before RT setup.
        A stream whose socket cannot be made is reported, and the run goes on
        without it (the host resolved at start-up)."""
        kw: dict[str, Any] = dict(
            block_ticks=min(256, max(1, int(cfg.rate_hz * cfg.record.flush_interval_s))),
            defer=cfg.loop.pacing == "host", epoch0=epoch_of_start(loop, clock_ns),
            info=lambda: {"rate_hz": loop.rate_hz, "experiment": name, "pid": os.getpid()})
        try:
            obs = cls(RUN_COLUMNS, RUN_FORMATS, stream=stream, **kw)
        except OSError as exc:
            warn(f"stream {stream[0] if stream else ''}: {exc.strerror or exc}; running without it")
            obs = cls(RUN_COLUMNS, RUN_FORMATS, stream=None, **kw)
        obs.attach(ctl, loop, rec)
        return obs

    def attach(self, ctl: Any, loop: Any, rec: Any) -> None:
        """Wire the bus to the recorder (or the controller) and the loop.
        Call before RT setup: a stream's worker thread must not inherit it."""
        self._ctl = ctl
        if rec is not None:
            rec.on_block = self.bus.publish
        else:
            self._own_rows = True
        if self.stream is not None:
            self.bus.add(self.stream)
            if self._own_rows:
                ctl.record = self.bus.record
        if self.bus.defer:  # else the bus starts its worker thread when a sink comes
            loop.background = _chain(loop.background, self.bus.work) if loop.background else self.bus.work

    def _taps_changed(self, n: int) -> None:
        """Without a run log or a stream, rows are packed only while a tap is connected."""
        if self._own_rows and self.stream is None and self._ctl is not None:
            if n and self._ctl.record is None:
                self.bus.reset()  # nothing left from an earlier tap
                self._ctl.record = self.bus.record
            elif not n:
                self._ctl.record = None

    def handle_request(self, conn: Any, req: dict[str, Any]) -> bool:
        """The status server's request hook."""
        return self.taps.handle(conn, req)

    def stats(self) -> dict[str, Any]:
        d: dict[str, Any] = {"taps": self.taps.stats()}
        if self.stream is not None:
            d["stream"] = self.stream.stats()
        if self.bus.errors:
            d["rowbus"] = self.bus.stats()
        return d

    def close(self, rec: Any, budget_s: float = 1.0) -> dict[str, Any]:
        """At the end, the loop stopped: hand over the last rows, let the
        stream send them, end every tap. Returns the final :meth:`stats`."""
        if rec is not None:
            rec.flush()  # the partial block: to the log's writer, and through on_block to the bus
        else:
            self.bus.flush()
        self.bus.close("the run ended", budget_s)
        self.taps.wait(timeout_s=1.0)
        return self.stats()


def epoch_of_start(loop: Any, clock_ns: Callable[[], int]) -> Callable[[], float]:
    """Unix time of the loop's deadline 0, asked once the loop has started."""
    def epoch0() -> float:
        t0 = loop.t_start_ns if loop.t_start_ns is not None else clock_ns()
        return time.time() - (clock_ns() - t0) * 1e-9

    return epoch0
