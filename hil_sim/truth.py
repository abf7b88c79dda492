"""Ground-truth log of the simulated bench: one CSV row per device tick.

Columns (SI units)::

    k,t,x,v,F_true,I_cmd,I_applied,x_meas,v_meas,F_meas,status,fault

``k`` is the tick index, which is also the device ``seq`` of the sample
published at that tick (``seq = k mod 2**32``), so a host log that records
the device seq aligns with this file exactly. ``x, v, F_true`` are the plant's
true values at tick k, ``I_cmd`` the driver input the device applied at tick
k (after enable, watchdog and clamping), ``I_applied`` the driver output
(after its lag), ``*_meas`` what the sensors reported in the sample of tick k
(``F_meas`` is the previous tick's force, NaN without a load cell) and
``status`` the sample's :class:`mrctl.io.base.Status` bits, ``fault`` the
scheduled-fault bits active at tick k (:class:`hil_sim.faults.FaultBit`; 0
outside any fault window). During a sample fault the ``*_meas`` columns hold
what was published (e.g. NaN), so the log shows what the host was sent.

Design — the clock thread never waits on the disk: :meth:`TruthLog.record`
appends the row tuple to a list; every ``batch_ticks`` rows (0.1 s) the list
is handed to the writer thread with a non-blocking ``put_nowait`` on a
bounded queue. If the queue is full (disk stalled), the batch is dropped and
counted (``dropped_rows``) rather than blocking the clock. The writer
formats a batch (``%r``: exact floats), writes it and flushes the file after
every batch, i.e. about 10 times a second. :meth:`close` hands over the rest,
joins the writer and writes a JSON summary beside the CSV (``truth.csv`` →
``truth.json``).

Cooperative mode (``threaded=False``), used when hil_sim serves its link
inline from a spinning clock thread: there is then no second thread at all.
A writer thread would need the GIL ten times a second for ~0.3 ms of
formatting, and every hand-back of the GIL costs the spinning clock a thread
wake-up, which on a VM can be milliseconds late. Instead the clock calls
:meth:`work_once` from its idle spin; each call formats at most a few rows
(a few µs) and writes the text once a batch is complete.
"""

from __future__ import annotations

import json
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any

from mrctl.util.jsonutil import jsonable

__all__ = ["COLUMNS", "TruthLog", "summary_path"]

COLUMNS = ("k", "t", "x", "v", "F_true", "I_cmd", "I_applied", "x_meas", "v_meas", "F_meas", "status", "fault")
_ROW_FMT = "%d,%r,%r,%r,%r,%r,%r,%r,%r,%r,%d,%d\n"
_ROW_FMT_NO_FAULT = "%d,%r,%r,%r,%r,%r,%r,%r,%r,%r,%d,0\n"  # an 11-field row: no fault


def _fmt(r: tuple) -> str:
    return (_ROW_FMT if len(r) == 12 else _ROW_FMT_NO_FAULT) % r
_STOP = None


def summary_path(csv_path: str | Path) -> Path:
    """The JSON summary beside a truth CSV: same stem, ``.json``."""
    p = Path(csv_path)
    s = p.with_suffix(".json")
    return s if s != p else p.with_name(p.name + ".summary.json")


class TruthLog:
    """Non-blocking per-tick CSV writer (see module doc)."""

    def __init__(self, path: str | Path, rate_hz: float = 1000.0, batch_s: float = 0.1,
                 queue_batches: int = 100, threaded: bool = True) -> None:
        self.path = Path(path)
        # Open (and write the header) in the caller's thread, so a bad path
        # is an error at start-up, not a silent writer-thread failure.
        self._fh = open(self.path, "w", encoding="ascii", newline="")
        self._fh.write(",".join(COLUMNS) + "\n")
        self._fh.flush()
        self.batch_ticks = max(1, int(rate_hz * batch_s))
        self._q: queue.Queue[list[tuple] | None] = queue.Queue(maxsize=queue_batches)
        self._batch: list[tuple] = []
        self.recorded_rows = 0  #: rows handed to record() (clock side)
        self.dropped_rows = 0  #: rows dropped because the queue was full
        self.written_rows = 0  #: rows written by the writer
        self.lost_rows = 0  #: rows discarded after a write error
        self.flushes = 0
        self.error: str | None = None
        self._closed = False
        self.threaded = threaded
        # cooperative mode: rows waiting to be formatted, and formatted text
        self._pending: list[tuple] = []
        self._pos = 0
        self._text: list[str] = []
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._writer, name="hil_sim-truth", daemon=True)
            self._thread.start()

    # -- clock side ---------------------------------------------------------
    def record(self, row: tuple) -> None:
        """Append one row (never blocks)."""
        b = self._batch
        b.append(row)
        if len(b) >= self.batch_ticks:
            self._handover()

    def work_once(self, max_rows: int = 4) -> None:
        """Cooperative mode: format up to ``max_rows`` rows; write a finished batch."""
        p = self._pending
        if self._pos >= len(p):
            return
        end = min(len(p), self._pos + max_rows)
        self._text.extend([_fmt(r) for r in p[self._pos:end]])
        self._pos = end
        if end == len(p):
            self._write_text()

    def _write_text(self) -> None:
        n = len(self._text)
        self._pending = []
        self._pos = 0
        if self.error is not None:
            self.lost_rows += n
            self._text = []
            return
        try:
            self._fh.write("".join(self._text))
            self._fh.flush()
            self.flushes += 1
            self.written_rows += n
        except (OSError, ValueError) as e:
            self.error = f"{self.path}: {e}"
            self.lost_rows += n
        self._text = []

    def _handover(self) -> None:
        b = self._batch
        if not b:
            return
        self._batch = []
        self.recorded_rows += len(b)
        if not self.threaded:
            if self._pending:  # the previous batch is not formatted yet: finish it now
                self.work_once(len(self._pending))
            self._pending = b
            return
        try:
            self._q.put_nowait(b)
        except queue.Full:
            self.dropped_rows += len(b)

    # -- writer side ----------------------------------------------------------
    def _writer(self) -> None:
        fh = self._fh
        while True:
            batch = self._q.get()
            if batch is _STOP:
                break
            if self.error is not None:
                self.lost_rows += len(batch)
                continue
            try:
                fh.write("".join([_fmt(r) for r in batch]))
                fh.flush()
                self.flushes += 1
                self.written_rows += len(batch)
            except (OSError, ValueError) as e:
                self.error = f"{type(e).__name__}: {e}"
                self.lost_rows += len(batch)

    # -- end ------------------------------------------------------------------
    def close(self, summary: dict[str, Any] | None = None, timeout_s: float = 10.0) -> dict[str, Any]:
        """Write the remaining rows, stop the writer, write the JSON summary.

        Returns the summary dict (the caller's ``summary`` plus the log's own
        counters). Idempotent; never raises for I/O errors (they are reported
        in ``error``)."""
        if self._closed:
            return {}
        self._closed = True
        self._handover()
        if not self.threaded:
            self.work_once(len(self._pending))
            return self._finish(summary)
        deadline = time.monotonic() + timeout_s
        try:
            self._q.put(_STOP, timeout=max(0.0, deadline - time.monotonic()))
        except queue.Full:
            self.error = self.error or "writer did not drain the queue in time"
        assert self._thread is not None
        self._thread.join(max(0.0, deadline - time.monotonic()))
        return self._finish(summary)

    def _finish(self, summary: dict[str, Any] | None) -> dict[str, Any]:
        """Close the CSV and write the JSON summary beside it."""
        try:
            self._fh.close()
        except OSError as e:
            self.error = self.error or f"close: {e}"
        out = dict(summary or {})
        out["truth_log"] = {
            "path": str(self.path),
            "columns": list(COLUMNS),
            "rows_recorded": self.recorded_rows,
            "rows_written": self.written_rows,
            "rows_dropped": self.dropped_rows,
            "rows_lost": self.lost_rows,
            "error": self.error,
        }
        try:
            sp = summary_path(self.path)
            sp.write_text(json.dumps(jsonable(out), indent=2) + "\n")
        except OSError as e:
            print(f"hil_sim: cannot write truth summary: {e}", file=sys.stderr)
        return out
