"""``mrctl simulate``'s run log, written a block at a time while the next block runs.

Each block of the simulation (:func:`mrctl.offline.simulate.simulate_blocks`)
becomes the run log's rows (:func:`mrctl.offline.simulate.log_block`),
formatted by the run log's one formatter (:class:`mrctl.runlog.rowtext.RowFormatter`)
and written in order. In the compiled build a writer thread formats and
writes each block in one C call without the GIL while the loop runs the
next block; at most
:data:`DEPTH` blocks wait, so memory stays flat whatever the duration. The
interpreted build formats in turn (its formatter is Python, which a second
thread would only make wait for the GIL).

Before the rest of the run, the first block tells how much the log will
take (:class:`LogEstimate`): its rows' mean size, with the clock and
counter columns' text averaged over the whole run instead (it grows with
the tick index). A disk that cannot hold that and a :data:`ESTIMATE_MARGIN`
more refuses the run (``BadInput``, exit 2) before anything but the header
is written.
"""

from __future__ import annotations

import math
import os
import queue
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np

from mrctl.errors import BadInput
from mrctl.offline.simulate import BLOCK_COLUMNS, CSV_COLUMNS, I_APPLIED0, log_block
from mrctl.runlog.format import RUN_FORMATS
from mrctl.runlog.rowtext import RowFormatter, write_all

#: blocks formatted or being written at most, beside the one the loop fills
DEPTH = 2
#: columns that grow with the tick index
_COUNTERS = ("t", "k", "seq", "t_dev")
#: ticks drawn from the whole run to estimate those columns' text
_SAMPLE_TICKS = 512
#: the estimate's error allowed for when the disk is checked (the rest of a
#: run's values can take more digits than its first block's)
ESTIMATE_MARGIN = 0.05


@dataclass(frozen=True)
class LogEstimate:
    """How much the run log takes, from its first block."""

    rows: int
    bytes_per_row: float
    total_bytes: int
    free_bytes: int
    directory: str

    def text(self) -> str:
        return (f"about {human_bytes(self.total_bytes)} ({self.rows} rows of ~{self.bytes_per_row:.0f} B); "
                f"{human_bytes(self.free_bytes)} free in {self.directory}")


def human_bytes(n: float) -> str:
    """``n`` bytes with a binary-prefix unit, e.g. ``'4.5 GiB'``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


class BlockLog:
    """The CSV of a simulation, fed one block at a time (:meth:`add`, a
    :data:`mrctl.offline.simulate.BlockSink`), closed by :meth:`close`.

    ``fh``: the created CSV (binary, written and closed here); ``rows``:
    the run's ticks (for the estimate); ``dt``: the tick (s);
    ``on_estimate``: told the estimate after the first block, before the
    disk check; ``threaded``: None = a writer thread when the formatter is
    compiled. Errors: :meth:`add` raises ``BadInput`` when the disk cannot
    hold the estimate, and the writer's ``OSError`` (disk full, EIO) at the
    next block or at :meth:`close`; ``rows_written`` counts complete lines."""

    def __init__(self, fh: BinaryIO, path: str | os.PathLike[str], rows: int, dt: float,
                 on_estimate: Callable[[LogEstimate], None] | None = None, threaded: bool | None = None) -> None:
        self.fh = fh
        self.path = Path(path)
        self.rows = int(rows)
        self.dt = float(dt)
        self.on_estimate = on_estimate
        self.threaded = threaded
        self.formatter: RowFormatter | None = None
        self.estimate: LogEstimate | None = None
        self.rows_written = 0
        self.bytes_written = 0
        self.error: OSError | None = None
        self._I_before = I_APPLIED0
        self._q: queue.Queue[Any] = queue.Queue(maxsize=DEPTH)
        self._thread: threading.Thread | None = None

    # -- the loop's side -----------------------------------------------------------
    def add(self, k0: int, block: dict[str, np.ndarray]) -> None:
        """The rows of ticks k0 … (copied: the block's arrays are the loop's)."""
        self._raise_error()
        n = len(block["t"])
        if not n:
            return
        first = self.formatter is None
        if first:
            self._start(block)
        log = log_block(block, k0, self._I_before)
        self._I_before = float(block["I_applied"][-1])
        owned = {"I_applied", "k", "seq", "late_us", "compute_us", "fault", "link_errors"}  # made by log_block
        cols = [log[c] if c in owned else np.array(log[c]) for c in CSV_COLUMNS]
        cols += [np.array(block[c]) for c in self.formatter.columns[len(CSV_COLUMNS):]]
        if first:
            data = self.formatter.columns_text(cols, 0, n)
            self._check_disk(data, cols, n)
            self._write(data, n)
        elif self._thread is not None:
            self._q.put((cols, n))
        else:
            self._count(*self.formatter.write_columns(self.fh, cols, 0, n))

    def _start(self, block: dict[str, np.ndarray]) -> None:
        channels = tuple(c for c in block if c not in BLOCK_COLUMNS)  # a bench's (the quarter car's)
        self.formatter = RowFormatter(CSV_COLUMNS + channels, {c: RUN_FORMATS.get(c, "%.9g") for c in
                                                               CSV_COLUMNS + channels})
        self._write(self.formatter.header(), 0)
        self._raise_error()
        if self.threaded if self.threaded is not None else self.formatter.compiled:
            self._thread = threading.Thread(target=self._run, name="mrctl-simulate-log", daemon=True)
            self._thread.start()

    def _check_disk(self, data: bytes, cols: list[np.ndarray], n: int) -> None:
        """Refuse the run (BadInput) if the disk cannot hold the estimated log:
        the first block's rows without their clock and counter columns, plus
        those columns' mean text over ticks drawn from the whole run (they
        grow with the tick index)."""
        assert self.formatter is not None
        names = self.formatter.columns
        counters = RowFormatter(_COUNTERS, {c: RUN_FORMATS[c] for c in _COUNTERS}, require_core=False)
        in_block = len(counters.columns_text([cols[names.index(c)] for c in _COUNTERS], 0, n))
        # ticks spread over the whole run (golden-ratio steps: no numpy.random to import)
        k = np.sort(np.floor((np.arange(1, _SAMPLE_TICKS + 1) * 0.6180339887498949) % 1.0 * self.rows))
        t = k * self.dt  # as the loop computes a tick's time
        sampled = len(counters.columns_text([t, k, k, t], 0, _SAMPLE_TICKS)) / _SAMPLE_TICKS
        per_row = (len(data) - in_block) / n + sampled
        total = self.bytes_written + int(math.ceil(per_row * self.rows))
        free = shutil.disk_usage(self.path.parent).free
        self.estimate = LogEstimate(self.rows, per_row, total, free, str(self.path.parent.resolve()))
        if self.on_estimate is not None:
            self.on_estimate(self.estimate)
        if (total - self.bytes_written) * (1 + ESTIMATE_MARGIN) > free:
            raise BadInput(f"{self.path}: the run log needs {self.estimate.text()}: it does not fit; not started. "
                           f"Free some space, write it elsewhere (--out), simulate less (--duration), or keep only "
                           f"the figures (--no-log)")

    # -- the writer's side ---------------------------------------------------------------
    def _run(self) -> None:
        assert self.formatter is not None
        while True:
            item = self._q.get()
            if item is None:
                return
            if self.error is None:
                cols, n = item
                try:
                    self._count(*self.formatter.write_columns(self.fh, cols, 0, n))
                except Exception as exc:  # noqa: BLE001 - a bug in formatting: reported like a write error
                    self.error = OSError(f"formatting the rows failed: {type(exc).__name__}: {exc}")

    def _write(self, data: bytes, rows: int) -> None:
        """``data`` holding ``rows`` rows (0: the header)."""
        done, lines, err = write_all(self.fh, data, rows)
        self._count(done, lines if rows else 0, err)

    def _count(self, done: int, rows: int, err: OSError | None) -> None:
        """What a write did: bytes, complete rows (a partial write keeps its complete lines), its error."""
        self.bytes_written += done
        self.rows_written += rows
        if err is not None and self.error is None:
            self.error = err

    def _raise_error(self) -> None:
        if self.error is not None:
            raise self.error

    # -- the end --------------------------------------------------------------------
    def close(self) -> None:
        """Write what waits, fsync and close; the first write error, if any (OSError)."""
        try:
            if self._thread is not None:
                self._q.put(None)
                self._thread.join()
                self._thread = None
            self._raise_error()
            try:
                self.fh.flush()
                os.fsync(self.fh.fileno())
            except OSError as exc:
                self.error = exc
                raise
        finally:
            self.fh.close()

    def abandon(self) -> None:
        """Stop the writer without waiting for the rest (the run failed) and close the file."""
        self.error = self.error or OSError("abandoned")
        if self._thread is not None:
            while True:  # make room for the stop, dropping what waits
                try:
                    self._q.get_nowait()
                except queue.Empty:
                    break
            self._q.put(None)
            self._thread.join()
            self._thread = None
        self.fh.close()
