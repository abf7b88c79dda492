"""Lossless, non-blocking run log for the 1 kHz control loop.

One CSV row per tick plus a JSON sidecar with the same stem (``run.csv`` →
``run.json``); the format is :mod:`mrctl.runlog.format` (docs/runlog.md).

Design — the loop thread never waits on the disk:

* The loop thread owns one **block**: a preallocated ``array('d')`` of
  ``block_ticks`` rows × C columns. :meth:`Recorder.record` packs the row
  into it with one ``struct.Struct.pack_into`` call and bumps a byte offset:
  no allocation per tick, no lock, no clock call (cost and alternatives
  measured: docs/design.md, *Run log*).
* A full block goes to the writer thread through a ``queue.SimpleQueue``
  (``put`` never blocks); the loop takes the next block from a **free-list**
  (``deque.pop``, atomic under the GIL). All blocks are allocated up front
  (``capacity_ticks`` rows), so the hand-over is bounded by construction.
* If the free-list is empty (writer stalled), the tick's row is **dropped**
  and counted (``overflow_rows``, first/last tick); ``record`` still returns
  at once, and recording resumes as soon as a block comes back.
* Blocks are at most ``rate_hz × flush_interval_s`` ticks long, so a partial
  block is never older than one flush interval while the loop runs (a tick
  count, not a clock read, bounds the data at risk); :meth:`Recorder.flush`
  hands one over on demand.
* The writer thread (:mod:`mrctl.daemon.logwriter`) writes each block with a
  single ``write()`` and fsyncs at least every ``flush_interval_s``: after a
  SIGKILL at most ``block_ticks`` ticks (≤ 1 s) plus the block being written
  are lost, and readers drop the torn last line. Its errors (disk full, EIO)
  never reach the loop: rows are counted as lost, reported by
  :meth:`Recorder.stats` while the run goes on and by the final sidecar.
* The CSV is created without following a symlink; the start-up sidecar
  reserves room on disk so the final one fits on a full disk
  (:mod:`mrctl.runlog.files`).

**Formatting in the loop's idle time** (``defer_format=True``, what
``mrctl run`` uses): a full block waits for :meth:`Recorder.format_pending`,
which the loop calls after each tick until it must start waiting for the
next deadline; the writer thread then only writes and fsyncs. If the loop
gets no idle time, waiting blocks go to the writer thread to be formatted
there, in order. Why: docs/design.md, *Run log*. The writer thread is
created before :func:`mrctl.daemon.rt.apply_rt` (:mod:`mrctl.daemon.logwriter`).
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import queue
import socket
import struct
import time
from array import array
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import mrctl.runlog.files as files
from mrctl.daemon.logwriter import STOP, LogWriter
from mrctl.runlog.format import CORE_COLUMNS, SIDECAR_FORMAT, describe_columns
from mrctl.runlog.read import read_run, read_sidecar, sidecar_path
from mrctl.runlog.rowtext import RowFormatter

__all__ = ["CORE_COLUMNS", "Recorder", "read_run", "read_sidecar", "sidecar_path"]

#: Rows formatted per call in the loop's idle time: ~15-25 µs of a 15-column
#: row format at a time, so the loop never waits long past its deadline
#: (the compiled formatter: ~0.45 µs a row; the interpreted one, ``%``: ~3 µs).
_CHUNK_ROWS = 8
_CHUNK_ROWS_COMPILED = 32


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


class Recorder:
    """Per-tick CSV run log; see the module docstring for the design.

    ``path``: the CSV (the sidecar is ``sidecar_path(path)``); the default
    ``opener`` (:func:`mrctl.runlog.files.create_log`) replaces an existing
    file without following a symlink, the CLI refuses one first unless
    ``--force``. ``columns`` start with :data:`CORE_COLUMNS` unless not
    ``require_core``; every value is stored as a float. ``meta`` goes to the
    sidecar as ``"meta"``, ``header`` (:func:`mrctl.runlog.format.sidecar_header`)
    to its top level. ``capacity_ticks`` rows can wait for the writer (whole
    blocks, at least two, of ``block_ticks`` rows, default ``min(256,
    rate_hz·flush_interval_s, capacity/2)``); the writer fsyncs at least every
    ``flush_interval_s``. ``fmt``: one ``%``-format (default ``'%r'``, exact)
    or ``{column: fmt}``. ``opener(path)`` returns a binary file with
    ``write``, ``close``, ``fileno`` (the daemon's, created before the link
    opened; tests' stalled or failing disks). ``defer_format``: blocks wait
    for :meth:`format_pending`. ``sidecar_reserve``: bytes the start-up
    sidecar takes on disk (room for the final one on a full disk).

    Raises at construction (before any tick) if the CSV or the sidecar cannot
    be created; after that, errors are only reported (:meth:`stats`).
    Threads: :meth:`record`, :meth:`flush` and :meth:`format_pending` belong
    to the loop thread; :meth:`close` to the thread that owns the loop, once
    it has stopped; :meth:`stats` to any thread.
    """

    __slots__ = (  # hot path first, then loop-thread state, then bookkeeping
        "_buf", "_off", "_end", "_rb", "_pack",
        "_tick", "_ov_rows", "_ov_first", "_ov_last", "_after_close", "_free", "_q", "_pending",
        "path", "sidecar", "columns", "meta", "rate_hz", "flush_interval_s", "block_ticks", "n_blocks",
        "capacity_ticks", "flush_every_ticks", "defer_format", "_fmt", "_chunk_rows",
        "_w", "_closed", "_close_stats", "_sidecar_base", "_sidecar_error", "on_block",
    )

    def __init__(
        self,
        path: str | os.PathLike[str],
        columns: Sequence[str],
        meta: Mapping[str, Any] | None = None,
        capacity_ticks: int = 8192,
        flush_interval_s: float = 1.0,
        *,
        rate_hz: float = 1000.0,
        block_ticks: int | None = None,
        fmt: str | Mapping[str, str] = "%r",
        require_core: bool = True,
        opener: Callable[[Path], BinaryIO] | None = None,
        defer_format: bool = False,
        header: Mapping[str, Any] | None = None,
        sidecar_reserve: int = files.SIDECAR_RESERVE_BYTES,
    ) -> None:
        cols = tuple(str(c) for c in columns)
        self._fmt = RowFormatter(cols, fmt, require_core)  # ValueError now, not in the writer later
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        if not (flush_interval_s > 0 and math.isfinite(flush_interval_s)):
            raise ValueError(f"flush_interval_s must be > 0, got {flush_interval_s!r}")
        if capacity_ticks < 2:
            raise ValueError(f"capacity_ticks must be >= 2, got {capacity_ticks!r}")

        p = Path(path)
        if p.suffix.lower() == ".json":
            raise ValueError(f"{p}: the run log is a CSV; .json is the sidecar's name")
        self.path = p
        self.sidecar = sidecar_path(p)
        self.columns = cols
        self.meta = dict(meta or {})
        self.rate_hz = float(rate_hz)
        self.flush_interval_s = float(flush_interval_s)
        self.flush_every_ticks = max(1, int(self.rate_hz * self.flush_interval_s))
        if block_ticks is None:
            block_ticks = min(256, self.flush_every_ticks, max(1, capacity_ticks // 2))
        if block_ticks < 1:
            raise ValueError(f"block_ticks must be >= 1, got {block_ticks!r}")
        # A block never spans more than one flush interval of ticks.
        self.block_ticks = min(int(block_ticks), self.flush_every_ticks)
        self.n_blocks = max(2, -(-int(capacity_ticks) // self.block_ticks))
        self.capacity_ticks = self.n_blocks * self.block_ticks

        self._chunk_rows = _CHUNK_ROWS_COMPILED if self._fmt.compiled else _CHUNK_ROWS
        self.defer_format = bool(defer_format)
        #: loop thread only: [block, rows, first tick, rows formatted, text parts]
        self._pending: deque[list] = deque()

        # Hot-path state.
        self._rb = 8 * len(cols)  # bytes per row
        self._pack = struct.Struct("=" + "d" * len(cols)).pack_into
        self._free: deque[array] = deque(
            array("d", bytes(self._rb * self.block_ticks)) for _ in range(self.n_blocks)
        )
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._buf: array | None = self._free.pop()
        self._off = 0
        self._end = self._rb * self.block_ticks
        self._tick = 0  # tick index of the current block's first row (or of the next tick)
        self._ov_rows = 0
        self._ov_first: int | None = None
        self._ov_last: int | None = None
        self._after_close = 0
        self._closed = False
        self._close_stats: dict[str, Any] | None = None
        self._sidecar_error: str | None = None
        #: on_block(block, rows, first tick): called in the loop thread at each hand-over, before the
        #: block is formatted (the live rows of :mod:`mrctl.daemon.rowbus`; it copies, never keeps it)
        self.on_block: Callable[[array, int, int], None] | None = None

        # Create the CSV with its header and the "incomplete" sidecar now, so
        # a bad path fails before the first tick.
        p.parent.mkdir(parents=True, exist_ok=True)
        fh = (opener or (lambda q: files.create_log(q, force=True)))(p)
        self._w = LogWriter(fh, p, self._q, self._free, formatter=self._fmt, chunk_rows=self._chunk_rows,
                            flush_interval_s=self.flush_interval_s)
        try:
            _, exc = self._w.write_all(self._fmt.header())
            if exc is not None:
                raise exc
            self._w.sync()
            files.fsync_dir(p.parent)
            self._sidecar_base = {
                "format": SIDECAR_FORMAT, "csv": p.name, **describe_columns(cols), **dict(header or {}),
                "rate_hz": self.rate_hz, "flush_interval_s": self.flush_interval_s,
                "capacity_ticks": self.capacity_ticks, "block_ticks": self.block_ticks,
                "host": socket.gethostname(), "pid": os.getpid(), "started_utc": _utc_now(), "meta": self.meta,
            }
            files.write_json(self.sidecar, {**self._sidecar_base, "complete": False}, reserve=sidecar_reserve)
        except BaseException:
            fh.close()
            raise
        self._w.thread.start()

    # -- loop thread ------------------------------------------------------
    def record(self, *values: float) -> None:
        """Log one tick's row (one float per column). Never blocks.

        Raises only on a caller bug (wrong number of values, non-numbers).
        """
        off = self._off
        if off < self._end:
            self._pack(self._buf, off, *values)
            self._off = off + self._rb
        else:
            self._record_slow(values)

    def _record_slow(self, values: tuple) -> None:
        """Block full (hand it over, take a free one) or none free (drop)."""
        if self._closed:
            self._after_close += 1
            return
        if self._buf is not None:
            self._handover()
        try:
            buf = self._free.pop()
        except IndexError:  # writer behind: drop this row, count it
            k = self._tick
            if self._ov_first is None:
                self._ov_first = k
            self._ov_last = k
            self._ov_rows += 1
            self._tick = k + 1
            return
        self._pack(buf, 0, *values)
        self._buf = buf
        self._off = self._rb
        self._end = self._rb * self.block_ticks

    def _handover(self) -> None:
        n = self._off // self._rb
        if self.on_block is not None:
            self.on_block(self._buf, n, self._tick)
        if self.defer_format:
            if self._pending:  # the loop had no idle time for the last one
                self._release_pending()
                self._q.put((self._buf, n, self._tick))
            else:
                self._pending.append([self._buf, n, self._tick, 0, []])
        else:
            self._q.put((self._buf, n, self._tick))
        self._tick += n
        self._buf = None
        self._off = 0
        self._end = 0  # next record() takes the slow path and fetches a block

    def flush(self) -> None:
        """Hand the partially filled block to the writer now. Never blocks.

        Call from the loop thread (e.g. before pausing); not needed while
        ticking, since blocks are at most one flush interval long.
        """
        if self._buf is not None and self._off > 0 and not self._closed:
            self._handover()
        self._release_pending()

    def _release_pending(self) -> None:
        """Hand every block still waiting to be formatted to the writer
        thread, oldest first (it formats them itself)."""
        pend = self._pending
        while pend:
            buf, n, tick0, _, _ = pend.popleft()
            self._q.put((buf, n, tick0))

    def format_pending(self, until_ns: int, clock: Callable[[], int] = time.monotonic_ns) -> None:
        """Format waiting rows, a chunk at a time, while ``clock() < until_ns``.

        For the loop thread's idle time (``defer_format=True``): a chunk
        (32 rows compiled, 8 interpreted) costs ~15-25 µs, so stop a little
        earlier than the moment the loop must start waiting. A finished
        block's text goes to the writer thread and the block back to the
        free list. The formatter keeps the GIL: handing it over here could
        cost the loop a cross-CPU wake-up (docs/design.md, "Threads").
        """
        pend = self._pending
        rows = self._fmt.rows
        chunk = self._chunk_rows
        while pend and clock() < until_ns:
            job = pend[0]
            buf, n, _, row, parts = job
            m = n - row if n - row < chunk else chunk
            parts.append(rows(buf, row, m))
            row += m
            if row < n:
                job[3] = row
                continue
            pend.popleft()
            self._q.put((b"".join(parts), n, job[2]))
            self._free.append(buf)

    # -- any thread ---------------------------------------------------------
    @property
    def error(self) -> str | None:
        """The writer's first error as text (``None`` while all is well)."""
        return self._w.error

    @property
    def ok(self) -> bool:
        """No writer error and no row dropped so far."""
        return self._w.error is None and self._ov_rows == 0 and self._w.lost_rows == 0

    def stats(self) -> dict[str, Any]:
        """Counters so far (a snapshot; cheap, safe from any thread).

        ``ticks``: record() calls; ``rows_written``: rows in the CSV;
        ``overflow_rows`` (+ first/last tick index): rows dropped because no
        buffer was free; ``lost_rows`` (+ first/last tick): rows buffered but
        discarded after a writer error; ``dropped_rows``: their sum;
        ``error``: the writer's first error or ``None``.
        """
        if self._close_stats is not None:
            return dict(self._close_stats)
        return self._stats()

    def _stats(self) -> dict[str, Any]:
        w = self._w
        ticks = self._tick + (self._off // self._rb if self._buf is not None else 0)
        return {
            "path": str(self.path), "sidecar": str(self.sidecar), "ticks": ticks,
            "rows_written": w.rows_written, "dropped_rows": self._ov_rows + w.lost_rows,
            "overflow_rows": self._ov_rows, "overflow_first_tick": self._ov_first,
            "overflow_last_tick": self._ov_last,
            "lost_rows": w.lost_rows, "lost_first_tick": w.lost_first, "lost_last_tick": w.lost_last,
            "error": w.error, "sidecar_error": self._sidecar_error, "rows_after_close": self._after_close,
            "capacity_ticks": self.capacity_ticks, "block_ticks": self.block_ticks,
            "blocks_free": len(self._free), "writes": w.writes, "fsyncs": w.fsyncs,
            "max_write_s": w.max_write_s, "max_fsync_s": w.max_fsync_s, "closed": self._closed,
        }

    # -- shutdown ---------------------------------------------------------
    def close(self, summary: Mapping[str, Any] | None = None, timeout: float | None = None,
              write_sidecar: bool = True) -> dict[str, Any]:
        """Drain every buffered row, stop the writer, finalize the sidecar
        (unless ``write_sidecar`` is false: the caller then calls
        :meth:`write_sidecar` itself, once it knows more).

        Idempotent (later calls return the same stats and ignore their
        arguments). Never raises for I/O problems: check ``stats["error"]``
        (CSV) and ``stats["sidecar_error"]``. ``timeout`` bounds the wait
        for the writer (None: wait until it has written everything); on
        expiry the sidecar stays ``"complete": false`` and ``error`` says so.
        """
        if self._close_stats is not None:
            return dict(self._close_stats)
        if not self._closed:
            if self._buf is not None and self._off > 0:
                self._handover()
            self._release_pending()
            self._closed = True
            self._buf = None
            self._off = self._end = 0
            self._q.put(STOP)
        self._w.thread.join(timeout)
        finished = not self._w.thread.is_alive()
        if not finished and self._w.error is None:
            self._w.error = (f"TimeoutError: writer still busy after {timeout} s at close "
                             f"(writing {self.path})")
        if write_sidecar:
            self.write_sidecar(summary)
        st = self._stats()
        st["complete"] = finished
        if finished:
            self._close_stats = st
        return dict(st)

    def write_sidecar(self, summary: Mapping[str, Any] | None = None,
                      extra: Mapping[str, Any] | None = None) -> str | None:
        """Write the final sidecar: the start-up content, the counters,
        ``summary`` and ``extra`` (top-level keys, e.g. ``exit_code``). On a
        full disk it goes over the start-up sidecar's reservation. Never
        raises: returns (and keeps, for :meth:`stats`) the error text."""
        finished = not self._w.thread.is_alive()
        st = self._stats()
        side = {
            **self._sidecar_base,
            "complete": finished,
            "closed_utc": _utc_now(),
            **{k: v for k, v in st.items() if k not in ("path", "sidecar", "closed", "sidecar_error")},
            "summary": dict(summary or {}),
            **dict(extra or {}),
        }
        try:
            files.write_json(self.sidecar, side)
            self._sidecar_error = None
        except Exception as exc:  # noqa: BLE001
            self._sidecar_error = f"{type(exc).__name__}: {exc} (writing {self.sidecar})"
        if self._close_stats is not None:
            self._close_stats["sidecar_error"] = self._sidecar_error
        return self._sidecar_error

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Recorder({str(self.path)!r}, {len(self.columns)} columns, closed={self._closed})"
