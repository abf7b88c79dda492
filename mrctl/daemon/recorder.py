"""Lossless, non-blocking run log for the 1 kHz control loop.

One CSV row per tick (header ``t,x,v,F_des,F,I,…``, SI units, the same core
columns in the same order as ``mrctl simulate``) plus a JSON sidecar with the
same stem (``run.csv`` → ``run.json``).

Design — the loop thread never waits on the disk:

* The loop thread owns one **block**: a preallocated ``array('d')`` of
  ``block_ticks`` rows × C columns. :meth:`Recorder.record` packs the row
  into it with one ``struct.Struct.pack_into`` call and bumps a byte offset:
  no allocation per tick (the ``*values`` tuple goes straight back to
  CPython's tuple free-list), no lock, no clock call.
* A full block goes to the writer thread through a ``queue.SimpleQueue``
  (``put`` never blocks); the loop takes the next block from a **free-list**
  (``deque.pop``, atomic under the GIL). All blocks are allocated up front
  (``capacity_ticks`` rows in total), so at most that many rows are ever in
  flight: the hand-over queue is bounded by construction.
* If the free-list is empty (writer stalled), the tick's row is **dropped**
  and counted (``overflow_rows``, first/last dropped tick index); ``record``
  still returns at once. Recording resumes as soon as a block comes back.
* Blocks are at most ``rate_hz × flush_interval_s`` ticks long (default 256
  rows), so a partial block is never older than one flush interval while the
  loop runs — a tick count, not a clock read, bounds the data at risk.
  :meth:`Recorder.flush` hands a partial block over on demand (e.g. before
  pausing the loop).
* The writer thread formats a block as CSV text (``'%r'`` = shortest exact
  repr by default, so values round-trip bit-exactly), writes it with a
  **single** ``write()`` (a SIGKILL can tear at most the file's last line),
  and ``fsync``\\ s at least every ``flush_interval_s``. After a SIGKILL the
  CSV holds the header and every row up to the last handed-over block: at
  most ``block_ticks`` ticks (≤ 1 s) plus the block being written are lost.
  :func:`read_run` drops a torn last line.
* Writer errors (disk full, EIO, …) never reach the loop: the writer keeps
  recycling blocks but discards them, counting their rows as ``lost_rows``;
  :meth:`Recorder.stats` and :meth:`Recorder.close` report the error. The
  caller decides what to do (the daemon keeps the damper safe and exits
  non-zero).

Measured cost of ``record(*12 floats)`` (CPython 3.11.7, timeit, median of
9 × 100 000–200 000 calls on the shared, noisy 2-core dev box, medians of
several runs; a no-op ``f(*args)`` call costs 0.18 µs there):

==================================================  ==============
``Recorder.record`` as shipped (pack_into)          0.52–0.73 µs
  (same, box under load from other jobs)            1.1–1.4 µs
bare ``struct.pack_into`` into ``array('d')``       0.77–0.89 µs
tuple stored in a preallocated list slot            0.24–0.27 µs
``buf[i:j] = array('d', values)``                   1.06–1.58 µs
per-element ``buf[i] = v`` loop                     1.61–1.69 µs
==================================================  ==============

The list-slot variant is cheaper per call but keeps one tuple and 12 float
objects alive per buffered row (≈ 0.4 kB/row, 3.6 MB at the default
capacity) and adds one GC-tracked object per tick, which drives the
generational collector from inside the loop; ``pack_into`` leaves the heap
unchanged tick after tick, so it was chosen (0.5 µs/tick is 0.05 % of a
1 ms period). The writer spends ~10–20 µs per 12-column row formatting
(``'%.9g'`` about half that), i.e. 1–2 % of a core at 1 kHz, in chunks of
``_CHUNK_ROWS`` rows so no single C call holds the GIL for long.

**Formatting in the loop's idle time** (``defer_format=True``, what
``mrctl run`` uses): a full block is not handed to the writer thread but
kept for :meth:`Recorder.format_pending`, which the loop calls after each
tick with the time by which it must start waiting for the next deadline; it
formats ``_CHUNK_ROWS`` rows at a time while that time has not come, then
hands the finished text to the writer thread, which only ``write()``\\ s and
``fsync``\\ s (system calls that release the GIL). Why: a second thread
running Python code takes the GIL away from the loop, and on this VM every
hand-over of the GIL between the two threads can cost a cross-CPU wake-up of
tens to hundreds of µs, landing inside a tick (bench/loop_timing.py: compute
p99 ≈ 100–180 µs with the spinning strategies when the thread formatted).
If the loop gets no idle time (a second block fills while one is still
waiting), every waiting block goes to the writer thread to be formatted
there, in order, so the data at risk stays within one flush interval.

**GIL note for the daemon**: the writer is a SCHED_OTHER Python thread;
while it holds the GIL the loop thread can wait up to
``sys.getswitchinterval()`` (5 ms by default) for it. Set e.g.
``sys.setswitchinterval(2e-4)`` in the daemon, and construct the Recorder
(which starts its thread) *before* :func:`mrctl.daemon.rt.apply_rt`, so the writer
does not inherit SCHED_FIFO / the loop's CPU pinning.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import queue
import socket
import struct
import threading
import time
from array import array
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from mrctl.util.jsonutil import jsonable

__all__ = ["CORE_COLUMNS", "Recorder", "read_run", "read_sidecar", "sidecar_path"]

#: Core columns every run CSV starts with, in this order (SI: s, m, m/s, N, N, A).
CORE_COLUMNS: tuple[str, ...] = ("t", "x", "v", "F_des", "F", "I")

#: Sidecar format tag.
SIDECAR_FORMAT = "mrctl-run/1"

#: Rows formatted per ``%`` call in the writer (bounds one GIL-holding C call
#: to ~0.1 ms for 12 columns).
_CHUNK_ROWS = 8

_STOP = object()


def sidecar_path(path: str | os.PathLike[str]) -> Path:
    """The JSON sidecar beside a run CSV: same stem, ``.json`` suffix."""
    return Path(path).with_suffix(".json")


def _write_json_atomic(path: Path, data: Mapping[str, Any]) -> None:
    """Write JSON to a temp file in the same directory, fsync, ``os.replace``."""
    text = json.dumps(jsonable(data), indent=2, allow_nan=False) + "\n"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    _fsync_dir(path.parent)


def _fsync_dir(directory: Path) -> None:
    """Best effort: make a directory entry (new/renamed file) durable."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _err_text(exc: BaseException, path: Path) -> str:
    return f"{type(exc).__name__}: {exc} (writing {path})"


class Recorder:
    """Per-tick CSV run log; see the module docstring for the design.

    Args:
        path: the CSV to create (truncated if it exists); the sidecar is
            ``sidecar_path(path)``.
        columns: column names; by default the first six must be
            :data:`CORE_COLUMNS`. Every value recorded is stored as a float
            (ints are exact below 2**53).
        meta: anything JSON-able describing the run (config, parameter set,
            versions, RT settings applied …); stored in the sidecar as
            ``"meta"``.
        capacity_ticks: rows that can be buffered while the writer lags
            (rounded up to whole blocks; at least two blocks).
        flush_interval_s: the writer fsyncs at least this often, and no
            block spans more than ``rate_hz × flush_interval_s`` ticks.
        rate_hz: the loop's tick rate, to turn the interval into ticks.
        block_ticks: rows per block (default ``min(256, interval ticks,
            capacity / 2)``).
        fmt: ``%``-format of every value (default ``'%r'``: shortest exact
            repr), or a mapping ``{column: fmt}`` overriding it per column
            (e.g. ``{"x": "%.9g", "seq": "%d"}``).
        require_core: check that ``columns`` starts with :data:`CORE_COLUMNS`.
        opener: ``opener(path) -> binary file`` with ``write`` (returning
            the bytes written) and ``close`` — and ``fileno`` for fsync;
            default: unbuffered ``open(path, "wb", buffering=0)``. For tests
            (stalled or failing disks).
        defer_format: full blocks wait for :meth:`format_pending` (called
            by the loop in its idle time) instead of being formatted by the
            writer thread; see the module docstring.

    Raises at construction (before any tick) if the CSV or the sidecar cannot
    be created; after that, errors are only reported (:meth:`stats`).

    Threads: :meth:`record` and :meth:`flush` belong to the loop thread;
    :meth:`close` to the thread that owns the loop, once the loop has
    stopped; :meth:`stats` may be called from any thread.
    """

    __slots__ = (
        # hot path (loop thread)
        "_buf", "_off", "_end", "_rb", "_pack",
        # loop-thread state
        "_tick", "_ov_rows", "_ov_first", "_ov_last", "_after_close", "_free", "_q",
        # writer-thread state
        "_rows_written", "_lost_rows", "_lost_first", "_lost_last", "_error", "_exception",
        "_fsyncs", "_max_write_s", "_max_fsync_s", "_writes",
        # config / bookkeeping
        "path", "sidecar", "columns", "meta", "rate_hz", "flush_interval_s",
        "block_ticks", "n_blocks", "capacity_ticks", "flush_every_ticks",
        "_ncols", "_row_fmt", "_chunk_fmt", "_fh", "_thread", "_closed", "_close_stats",
        "defer_format", "_pending", "_unpack_chunk", "_tail_fmts",
        "_sidecar_base", "_sidecar_error",
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
    ) -> None:
        cols = tuple(str(c) for c in columns)
        if not cols:
            raise ValueError("columns: need at least one column")
        bad = [c for c in cols if not c or c != c.strip() or any(ch in c for ch in ',"\r\n#')]
        if bad:
            raise ValueError(f"columns: invalid name(s) {bad!r} (empty, spaces, or one of , \" # newline)")
        dupes = sorted({c for c in cols if cols.count(c) > 1})
        if dupes:
            raise ValueError(f"columns: duplicate name(s) {dupes!r}")
        if require_core and cols[: len(CORE_COLUMNS)] != CORE_COLUMNS:
            raise ValueError(f"columns must start with {','.join(CORE_COLUMNS)}; got {','.join(cols)}")
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

        # Formats: validate on one row now, not in the writer thread later.
        if isinstance(fmt, str):
            fmts = [fmt] * len(cols)
        else:
            unknown = sorted(set(fmt) - set(cols))
            if unknown:
                raise ValueError(f"fmt: unknown column(s) {unknown!r}")
            fmts = [fmt.get(c, "%r") for c in cols]
        row_fmt = ",".join(fmts) + "\n"
        try:
            probe = row_fmt % tuple(0.5 for _ in cols)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"fmt: bad format {row_fmt!r}: {exc}") from None
        if probe.count(",") != len(cols) - 1 or probe.count("\n") != 1:
            raise ValueError(f"fmt: formats must not produce ',' or newlines: {row_fmt!r}")
        self._row_fmt = row_fmt
        self._chunk_fmt = row_fmt * _CHUNK_ROWS
        self._ncols = len(cols)
        self.defer_format = bool(defer_format)
        #: loop thread only: [block, rows, first tick, rows formatted, text parts]
        self._pending: deque[list] = deque()
        self._unpack_chunk = struct.Struct("=" + "d" * (len(cols) * _CHUNK_ROWS)).unpack_from
        self._tail_fmts = {m: (struct.Struct("=" + "d" * (len(cols) * m)).unpack_from, row_fmt * m)
                           for m in range(1, _CHUNK_ROWS)}

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

        self._rows_written = 0
        self._lost_rows = 0
        self._lost_first: int | None = None
        self._lost_last: int | None = None
        self._error: str | None = None
        self._exception: BaseException | None = None
        self._fsyncs = 0
        self._writes = 0
        self._max_write_s = 0.0
        self._max_fsync_s = 0.0
        self._closed = False
        self._close_stats: dict[str, Any] | None = None
        self._sidecar_error: str | None = None

        # Create the CSV with its header and the "incomplete" sidecar now, so
        # a bad path fails before the first tick.
        p.parent.mkdir(parents=True, exist_ok=True)
        self._fh = (opener or (lambda q: open(q, "wb", buffering=0)))(p)
        try:
            done, exc = self._write_all((",".join(cols) + "\n").encode("ascii"))
            if exc is not None:
                raise exc
            self._sync()
            _fsync_dir(p.parent)
            self._sidecar_base = {
                "format": SIDECAR_FORMAT,
                "csv": p.name,
                "columns": list(cols),
                "rate_hz": self.rate_hz,
                "flush_interval_s": self.flush_interval_s,
                "capacity_ticks": self.capacity_ticks,
                "block_ticks": self.block_ticks,
                "host": socket.gethostname(),
                "pid": os.getpid(),
                "started_utc": _utc_now(),
                "meta": self.meta,
            }
            _write_json_atomic(self.sidecar, {**self._sidecar_base, "complete": False})
        except BaseException:
            self._fh.close()
            raise

        self._thread = threading.Thread(target=self._writer, name="mrctl-recorder", daemon=True)
        self._thread.start()

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

        For the loop thread's idle time (``defer_format=True``): a chunk of
        ``_CHUNK_ROWS`` rows costs ~25 µs, so stop a little earlier than
        the moment the loop must start waiting. A finished block's text goes
        to the writer thread and the block back to the free list.
        """
        pend = self._pending
        while pend and clock() < until_ns:
            job = pend[0]
            buf, n, _, row, parts = job
            m = n - row
            if m >= _CHUNK_ROWS:
                parts.append(self._chunk_fmt % self._unpack_chunk(buf, row * self._rb))
                row += _CHUNK_ROWS
            else:
                unpack, fmt = self._tail_fmts[m]
                parts.append(fmt % unpack(buf, row * self._rb))
                row = n
            if row < n:
                job[3] = row
                continue
            pend.popleft()
            self._q.put(("".join(parts).encode("ascii"), n, job[2]))
            self._free.append(buf)

    # -- writer thread ----------------------------------------------------
    def _write_all(self, data: bytes) -> tuple[int, BaseException | None]:
        """Write ``data`` (normally in one write call); (bytes written, error)."""
        done = 0
        size = len(data)
        try:
            view = memoryview(data)
            while done < size:
                k = self._fh.write(view[done:] if done else data)
                if k is None:  # non-raw file object: assume it took everything
                    k = size - done
                if k <= 0:
                    raise OSError(f"write() returned {k} with {size - done} bytes left")
                done += k
        except Exception as exc:  # noqa: BLE001 - reported, never raised in the loop
            return done, exc
        return done, None

    def _sync(self) -> None:
        flush = getattr(self._fh, "flush", None)
        if flush is not None:
            flush()
        try:
            fd = self._fh.fileno()
        except (AttributeError, OSError, ValueError):
            return  # injected file object without a descriptor
        os.fsync(fd)

    def _format(self, buf: array, n: int) -> bytes:
        vals = buf[: n * self._ncols].tolist()
        step = _CHUNK_ROWS * self._ncols
        full = self._chunk_fmt
        parts = []
        yield_gil = time.sleep
        for a in range(0, len(vals), step):
            seg = vals[a : a + step]
            fmt = full if len(seg) == step else self._row_fmt * (len(seg) // self._ncols)
            parts.append(fmt % tuple(seg))
            # one chunk is one uninterruptible C call: hand the GIL back to the
            # control loop after each, instead of making it wait for the
            # interpreter's switch interval
            yield_gil(0)
        return "".join(parts).encode("ascii")

    def _lose(self, n: int, tick0: int) -> None:
        if n <= 0:
            return
        if self._lost_first is None:
            self._lost_first = tick0
        self._lost_last = tick0 + n - 1
        self._lost_rows += n

    def _fail(self, exc: BaseException) -> None:
        if self._error is None:
            self._exception = exc
            self._error = _err_text(exc, self.path)

    def _writer(self) -> None:
        get = self._q.get
        free = self._free
        interval = self.flush_interval_s
        clock = time.monotonic
        last_sync = clock()
        dirty = False
        while True:
            if dirty and self._error is None:
                try:
                    item = get(timeout=max(0.0, last_sync + interval - clock()))
                except queue.Empty:
                    item = None
            else:
                item = get()
            if item is _STOP:
                break
            if item is not None:
                buf, n, tick0 = item
                if self._error is not None:
                    self._lose(n, tick0)
                else:
                    try:
                        data = buf if isinstance(buf, bytes) else self._format(buf, n)
                    except Exception as exc:  # noqa: BLE001
                        self._fail(exc)
                        self._lose(n, tick0)
                    else:
                        t0 = clock()
                        done, exc = self._write_all(data)
                        dt = clock() - t0
                        self._writes += 1
                        if dt > self._max_write_s:
                            self._max_write_s = dt
                        if exc is None:
                            self._rows_written += n
                            dirty = True
                        else:  # a partial write keeps its complete lines
                            ok = data.count(b"\n", 0, done)
                            self._rows_written += ok
                            self._lose(n - ok, tick0 + ok)
                            self._fail(exc)
                if not isinstance(buf, bytes):
                    free.append(buf)  # recycle: the loop may fill it again
            if dirty and self._error is None and clock() - last_sync >= interval:
                dirty = not self._timed_sync()
                last_sync = clock()
        if dirty and self._error is None:
            self._timed_sync()
        try:
            self._fh.close()
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)

    def _timed_sync(self) -> bool:
        t0 = time.monotonic()
        try:
            self._sync()
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)
            return False
        dt = time.monotonic() - t0
        self._fsyncs += 1
        if dt > self._max_fsync_s:
            self._max_fsync_s = dt
        return True

    # -- any thread ---------------------------------------------------------
    @property
    def error(self) -> str | None:
        """The writer's first error as text (``None`` while all is well)."""
        return self._error

    @property
    def ok(self) -> bool:
        """No writer error and no row dropped so far."""
        return self._error is None and self._ov_rows == 0 and self._lost_rows == 0

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
        buf = self._buf
        ticks = self._tick + (self._off // self._rb if buf is not None else 0)
        return {
            "path": str(self.path),
            "sidecar": str(self.sidecar),
            "ticks": ticks,
            "rows_written": self._rows_written,
            "dropped_rows": self._ov_rows + self._lost_rows,
            "overflow_rows": self._ov_rows,
            "overflow_first_tick": self._ov_first,
            "overflow_last_tick": self._ov_last,
            "lost_rows": self._lost_rows,
            "lost_first_tick": self._lost_first,
            "lost_last_tick": self._lost_last,
            "error": self._error,
            "sidecar_error": self._sidecar_error,
            "rows_after_close": self._after_close,
            "capacity_ticks": self.capacity_ticks,
            "block_ticks": self.block_ticks,
            "blocks_free": len(self._free),
            "writes": self._writes,
            "fsyncs": self._fsyncs,
            "max_write_s": self._max_write_s,
            "max_fsync_s": self._max_fsync_s,
            "closed": self._closed,
        }

    # -- shutdown ---------------------------------------------------------
    def close(self, summary: Mapping[str, Any] | None = None,
              timeout: float | None = None) -> dict[str, Any]:
        """Drain every buffered row, stop the writer, finalize the sidecar.

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
            self._q.put(_STOP)
        self._thread.join(timeout)
        finished = not self._thread.is_alive()
        if not finished and self._error is None:
            self._error = (f"TimeoutError: writer still busy after {timeout} s at close "
                           f"(writing {self.path})")
        st = self._stats()
        st["complete"] = finished
        side = {
            **self._sidecar_base,
            "complete": finished,
            "closed_utc": _utc_now(),
            **{k: v for k, v in st.items() if k not in ("path", "sidecar", "closed", "complete",
                                                          "sidecar_error")},
            "summary": dict(summary or {}),
        }
        try:
            _write_json_atomic(self.sidecar, side)
        except Exception as exc:  # noqa: BLE001
            self._sidecar_error = f"{type(exc).__name__}: {exc} (writing {self.sidecar})"
        st["sidecar_error"] = self._sidecar_error
        if finished:
            self._close_stats = st
        return dict(st)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Recorder({str(self.path)!r}, {len(self.columns)} columns, closed={self._closed})"


# -- reading back -------------------------------------------------------------
def read_run(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read a run CSV into ``{column: float array}`` (all columns, in order).

    Tolerates what a killed recorder leaves: a last line without its
    newline is dropped. ``#`` comment lines and blank lines are skipped (so
    ``mrctl simulate`` output reads too). Any other malformed line raises
    :class:`mrctl.util.csvtable.CsvError` (a ``ValueError``) naming the file and
    1-based line number.
    """
    from mrctl.util.csvtable import read_table

    return read_table(path, torn_last_line_ok=True).columns  # CsvError is a ValueError


def read_sidecar(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The JSON sidecar of a run CSV (pass the CSV or the .json path)."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        p = sidecar_path(p)
    return json.loads(p.read_text(encoding="utf-8"))
