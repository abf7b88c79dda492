"""The run log's writer thread: format (when the loop did not), write, fsync, count.

Owned by :class:`mrctl.daemon.recorder.Recorder`, which hands it blocks (or
text the loop formatted in its idle time) through a ``queue.SimpleQueue``
and takes each block back through the free-list. Everything that can block
on the disk happens here, never in the loop thread.

Each block's text goes out with a **single** ``write()`` (a SIGKILL can
tear at most the file's last line), and the file is ``fsync``\\ ed at least
every ``flush_interval_s``. Errors (disk full, EIO, …) never reach the
loop: from the first error on, blocks are recycled but discarded, their
rows counted as lost (first and last tick index), and the error kept as
text for :meth:`Recorder.stats`, ``mrctl status`` and the sidecar. A
partial write keeps its complete lines.

When it formats (the loop had no idle time), it uses the run log's one
formatter (:class:`mrctl.runlog.rowtext.RowFormatter`): compiled, a whole
block in C with the GIL released (~0.45 µs a 15-column row); interpreted,
``%`` in chunks of ``chunk_rows`` rows (~3 µs a row) so that no single C
call holds the GIL for long, handing the GIL back after each chunk
(``time.sleep(0)``) instead of making the loop wait for the interpreter's
switch interval.

The writer is a SCHED_OTHER Python thread;
while it holds the GIL the loop thread can wait up to
``sys.getswitchinterval()`` (5 ms by default) for it. Set e.g.
``sys.setswitchinterval(2e-4)`` in the daemon, and construct the Recorder
(which starts its thread) *before* :func:`mrctl.daemon.rt.apply_rt`, so the writer
does not inherit SCHED_FIFO / the loop's CPU pinning.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from array import array
from collections import deque
from pathlib import Path
from typing import Any, BinaryIO

from mrctl.runlog.rowtext import RowFormatter

#: put on the queue to stop the writer after everything before it
STOP = object()


class LogWriter:
    """The writer thread and its counters (read from any thread: plain ints)."""

    def __init__(self, fh: BinaryIO, path: Path, q: queue.SimpleQueue, free: deque[array], *,
                 formatter: RowFormatter, chunk_rows: int, flush_interval_s: float) -> None:
        self.fh = fh
        self.path = path
        self.q = q
        self.free = free
        self.formatter = formatter
        self.chunk_rows = chunk_rows
        self.flush_interval_s = flush_interval_s
        self.rows_written = 0
        self.lost_rows = 0
        self.lost_first: int | None = None
        self.lost_last: int | None = None
        self.error: str | None = None
        self.exception: BaseException | None = None
        self.first_error_tick: int | None = None
        self.fsyncs = 0
        self.writes = 0
        self.max_write_s = 0.0
        self.max_fsync_s = 0.0
        self.thread = threading.Thread(target=self.run, name="mrctl-recorder", daemon=True)

    # -- I/O ---------------------------------------------------------------------
    def write_all(self, data: bytes) -> tuple[int, BaseException | None]:
        """Write ``data`` (normally in one write call); (bytes written, error)."""
        done = 0
        size = len(data)
        try:
            view = memoryview(data)
            while done < size:
                k = self.fh.write(view[done:] if done else data)
                if k is None:  # non-raw file object: assume it took everything
                    k = size - done
                if k <= 0:
                    raise OSError(f"write() returned {k} with {size - done} bytes left")
                done += k
        except Exception as exc:  # noqa: BLE001 - reported, never raised in the loop
            return done, exc
        return done, None

    def sync(self) -> None:
        flush = getattr(self.fh, "flush", None)
        if flush is not None:
            flush()
        try:
            fd = self.fh.fileno()
        except (AttributeError, OSError, ValueError):
            return  # injected file object without a descriptor
        os.fsync(fd)

    def format(self, buf: array, n: int) -> bytes:
        """The CSV text of a block's ``n`` rows, letting the loop run meanwhile."""
        rows = self.formatter.rows
        if self.formatter.compiled:
            return rows(buf, 0, n, release_gil=True)
        parts = []
        yield_gil = time.sleep
        for a in range(0, n, self.chunk_rows):
            parts.append(rows(buf, a, min(self.chunk_rows, n - a)))
            yield_gil(0)
        return b"".join(parts)

    # -- bookkeeping ---------------------------------------------------------------
    def lose(self, n: int, tick0: int) -> None:
        if n <= 0:
            return
        if self.lost_first is None:
            self.lost_first = tick0
        self.lost_last = tick0 + n - 1
        self.lost_rows += n

    def fail(self, exc: BaseException, tick: int | None = None) -> None:
        if self.error is None:
            self.exception = exc
            self.first_error_tick = tick
            self.error = f"{type(exc).__name__}: {exc} (writing {self.path})"

    # -- the thread ----------------------------------------------------------------
    def run(self) -> None:
        get = self.q.get
        free = self.free
        interval = self.flush_interval_s
        clock = time.monotonic
        last_sync = clock()
        dirty = False
        while True:
            if dirty and self.error is None:
                try:
                    item = get(timeout=max(0.0, last_sync + interval - clock()))
                except queue.Empty:
                    item = None
            else:
                item = get()
            if item is STOP:
                break
            if item is not None:
                buf, n, tick0 = item
                if self.error is not None:
                    self.lose(n, tick0)
                else:
                    dirty = self._write_block(buf, n, tick0) or dirty
                if not isinstance(buf, bytes):
                    free.append(buf)  # recycle: the loop may fill it again
            if dirty and self.error is None and clock() - last_sync >= interval:
                dirty = not self.timed_sync()
                last_sync = clock()
        if dirty and self.error is None:
            self.timed_sync()
        try:
            self.fh.close()
        except Exception as exc:  # noqa: BLE001
            self.fail(exc)

    def _write_block(self, buf: Any, n: int, tick0: int) -> bool:
        """One block; True if rows reached the file (to be fsynced)."""
        try:
            data = buf if isinstance(buf, bytes) else self.format(buf, n)
        except Exception as exc:  # noqa: BLE001
            self.fail(exc, tick0)
            self.lose(n, tick0)
            return False
        t0 = time.monotonic()
        done, exc = self.write_all(data)
        dt = time.monotonic() - t0
        self.writes += 1
        if dt > self.max_write_s:
            self.max_write_s = dt
        if exc is None:
            self.rows_written += n
            return True
        ok = data.count(b"\n", 0, done)  # a partial write keeps its complete lines
        self.rows_written += ok
        self.lose(n - ok, tick0 + ok)
        self.fail(exc, tick0 + ok)
        return ok > 0

    def timed_sync(self) -> bool:
        t0 = time.monotonic()
        try:
            self.sync()
        except Exception as exc:  # noqa: BLE001
            self.fail(exc)
            return False
        dt = time.monotonic() - t0
        self.fsyncs += 1
        if dt > self.max_fsync_s:
            self.max_fsync_s = dt
        return True
