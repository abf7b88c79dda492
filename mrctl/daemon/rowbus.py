"""The row bus: the run log's rows, handed block by block to live consumers.

Live consumers (the UDP stream, :mod:`mrctl.daemon.stream`; ``mrctl tap``
clients, :mod:`mrctl.daemon.tap`) get the rows the loop already packs for
the run log, never anything computed per tick for them:

* with a run log, the recorder calls :meth:`RowBus.publish` at each block
  hand-over (``Recorder.on_block``, once per ``block_ticks`` rows);
* without one, :meth:`RowBus.record` packs the rows itself, the recorder's
  way (one ``struct.pack_into`` into a preallocated block), and only while
  something consumes them: the service installs it as the controller's
  ``record`` when a stream is configured or a tap connects.

:meth:`publish` copies the block's rows (one ``memcpy``, a few µs per
block) and appends the copy to each sink's bounded backlog; that is all it
does in the loop thread at a hand-over. The formatting (JSON, CSV) and the
sending happen in :meth:`work`: in the loop's idle time when the loop is
host-paced (``FixedRateLoop(background=…)``, after the run log's own
formatting), as the run log does, because a second thread running Python
code takes the GIL from the loop (docs/design.md, *Threads*); with device
pacing there is no idle time, so a worker thread calls it, yielding the GIL
after every chunk, while the loop sleeps in its exchange.

A sink is anything with ``feed(block, rows, row0)`` (loop thread, O(1),
never blocks: a sink that falls behind drops whole blocks and counts
them), ``work(until_ns, clock, pause) -> bool`` (more to do?),
``finish(reason)`` and a ``done`` attribute. Sinks are added and removed by
other threads under a lock the loop never takes: the loop only reads the
``_sinks`` tuple, replaced whole.
"""

from __future__ import annotations

import struct
import threading
import time
from array import array
from collections.abc import Sequence
from typing import Any, Callable, Protocol

#: far in the future: the worker thread works until there is nothing left
_NEVER = 1 << 62


class Sink(Protocol):
    done: bool

    def feed(self, block: array, rows: int, row0: int) -> None: ...

    def work(self, until_ns: int, clock: Callable[[], int], pause: Callable[[], object] | None) -> bool: ...

    def finish(self, reason: str) -> None: ...


class RowBus:
    """Fan-out of packed run-log blocks (``columns`` float64 per row) to sinks.

    ``block_ticks``: rows per block when the bus packs rows itself.
    ``defer``: sinks work in the loop's idle time (:meth:`work`, host
    pacing); otherwise :meth:`start_worker` starts a thread for it.
    Threads: :meth:`record`, :meth:`publish`, :meth:`flush`, :meth:`work`
    belong to the loop thread (or whoever owns it once it has stopped);
    :meth:`add`, :meth:`remove`, :meth:`stats` to any thread.
    """

    def __init__(self, columns: Sequence[str], block_ticks: int = 256, *, defer: bool = True,
                 clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.columns = tuple(columns)
        self.ncols = len(self.columns)
        self.defer = defer
        self.clock = clock
        self.block_ticks = max(1, int(block_ticks))
        self._rb = 8 * self.ncols
        self._pack = struct.Struct("=" + "d" * self.ncols).pack_into
        self._buf = array("d", bytes(self._rb * self.block_ticks))
        self._off = 0
        self._end = self._rb * self.block_ticks
        self._row = 0  # row index of the own block's first row
        self._sinks: tuple[Any, ...] = ()
        self._lock = threading.Lock()  # add/remove only; never taken by the loop thread
        self._wake = threading.Event()
        self._worker: threading.Thread | None = None
        self._closing = False
        self.rows_published = 0  # rows handed to at least one sink
        self.blocks_published = 0
        self.errors = 0  # exceptions caught in publish/work (a bug in a sink; the loop runs on)
        self.last_error: str | None = None

    # -- loop thread ------------------------------------------------------------
    def record(self, *values: float) -> None:
        """One tick's row, when there is no run log (the controller's ``record``)."""
        off = self._off
        self._pack(self._buf, off, *values)
        off += self._rb
        if off < self._end:
            self._off = off
        else:
            self._off = 0
            self.publish(self._buf, self.block_ticks, self._row)
            self._row += self.block_ticks

    def flush(self) -> None:
        """Publish the partly filled own block (at the end of the run)."""
        n = self._off // self._rb
        if n:
            self._off = 0
            self.publish(self._buf, n, self._row)
            self._row += n

    def reset(self) -> None:
        """Forget the rows of the own block (before the controller records into it again)."""
        self._off = 0

    def publish(self, block: array, rows: int, row0: int) -> None:
        """A block of ``rows`` rows, the first being row ``row0`` of the run.
        Copies them for each live sink; never blocks, never raises."""
        sinks = self._sinks
        if not sinks or rows <= 0:
            return
        try:
            data = block[: rows * self.ncols]  # a copy: the block goes on to be formatted and reused
            for s in sinks:
                if not s.done:
                    s.feed(data, rows, row0)
            self.rows_published += rows
            self.blocks_published += 1
            if self._worker is not None:
                self._wake.set()
        except Exception as exc:  # noqa: BLE001 - observability must never take the loop down
            self._error(exc)

    def work(self, until_ns: int) -> None:
        """Let the sinks format and send until ``until_ns`` (the loop's idle time)."""
        sinks = self._sinks
        if not sinks:
            return
        clock = self.clock
        try:
            for s in sinks:
                if not s.done:
                    s.work(until_ns, clock, None)
                if clock() >= until_ns:
                    return
        except Exception as exc:  # noqa: BLE001
            self._error(exc)

    def _error(self, exc: BaseException) -> None:
        self.errors += 1
        if self.last_error is None:
            self.last_error = f"{type(exc).__name__}: {exc}"

    # -- any thread ---------------------------------------------------------------
    def add(self, sink: Any) -> None:
        with self._lock:
            self._sinks = (*self._sinks, sink)
            if not self.defer and self._worker is None and not self._closing:
                self.start_worker()  # device pacing: only once something consumes rows

    def remove(self, sink: Any) -> None:
        with self._lock:
            self._sinks = tuple(s for s in self._sinks if s is not sink)

    @property
    def sinks(self) -> tuple[Any, ...]:
        return self._sinks

    def start_worker(self) -> None:
        """Device pacing: a thread does the sinks' work while the loop waits on
        its device; started by the first :meth:`add`, from a thread that is not
        the loop's (before RT setup, or the status thread's: it must not inherit
        SCHED_FIFO or the loop's CPU)."""
        if self._worker is None:
            self._worker = threading.Thread(target=self._run_worker, name="mrctl-rows", daemon=True)
            self._worker.start()

    def _run_worker(self) -> None:
        pause = time.sleep  # sleep(0) after each chunk: hand the GIL back to the loop
        while not self._closing:
            self._wake.wait()
            self._wake.clear()
            try:
                for s in self._sinks:
                    if not s.done:
                        s.work(_NEVER, self.clock, lambda: pause(0))
            except Exception as exc:  # noqa: BLE001
                self._error(exc)

    def close(self, reason: str = "the run ended", budget_s: float = 1.0) -> None:
        """The run is over: stop the worker, let the sinks send what they hold
        (for at most ``budget_s``), then tell each one the run ended."""
        self._closing = True
        if self._worker is not None:
            self._wake.set()
            self._worker.join(timeout=2.0)
        deadline = self.clock() + int(budget_s * 1e9)
        for s in self._sinks:
            try:
                while not s.done and self.clock() < deadline and s.work(deadline, self.clock, None):
                    pass
                s.finish(reason)
            except Exception as exc:  # noqa: BLE001
                self._error(exc)

    def stats(self) -> dict[str, Any]:
        return {"rows": self.rows_published, "blocks": self.blocks_published, "sinks": len(self._sinks),
                "errors": self.errors, "last_error": self.last_error}
