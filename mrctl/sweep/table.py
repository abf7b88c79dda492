"""The results table of a sweep: one row per point, written as it completes.

CSV, appended row by row and flushed, so a Ctrl-C or a kill leaves a valid
partial table (a half-written last line from a kill is dropped when the
sweep resumes); the points already in it are skipped by their config hash,
and a row whose hash came before is dropped (one row per point, whatever
ran twice). A ``.parquet`` name (with pyarrow installed) gets its rows
journalled in ``NAME.parquet.partial.csv`` and the Parquet file written from
them at the end or at an interruption. A finished table is rewritten in
point order. Nothing here holds the table in memory: rows are read and
written as streams, the hashes done kept at 8 bytes each.

One sweep per table: the journal is ``flock``-ed while the sweep runs, and
a second sweep on it is refused (exit 3) naming the first one's pid, as a
second daemon on a device is. What is there must be a regular file (a FIFO
would block the read, ``/dev/null`` swallow the rows) and a table of this
sweep (its columns; every row's ``point`` a whole number, its text UTF-8),
else the sweep is refused before any point runs, naming the line.
"""

from __future__ import annotations

import csv
import fcntl
import io
import os
from pathlib import Path
from typing import Any, Iterable, Iterator

from mrctl.errors import BadInput, LinkFailure
from mrctl.runlog.files import fsync_dir
from mrctl.sweep.parquet import check_columns, columns_of, parquet_wanted, text_rows, write_csv_rows, write_parquet
from mrctl.sweep.rows import HashSet, cell, checked_rows, sorted_rows
from mrctl.util.files import FileProblem, flock_holder, not_regular, open_regular

__all__ = ["TAIL", "columns", "check_table_path", "TableBusy", "ResultsTable", "read_results", "is_results_table",
           "parquet_wanted"]

TAIL = ("status", "error", "wall_s", "mrctl_version", "build")


def columns(axes: list[str], metrics: Iterable[str]) -> list[str]:
    """The table's columns: point, config_hash, the point's values, seed, metrics, status …"""
    return ["point", "config_hash", *axes, "seed", *metrics, *TAIL]


def check_table_path(path: str | os.PathLike[str]) -> None:
    """``BadInput`` unless ``path`` (and a Parquet table's journal) is absent
    or a regular file, not a symlink: checked before anything is opened."""
    p = Path(path)
    for f in (p, p.with_name(p.name + ".partial.csv")) if p.suffix == ".parquet" else (p,):
        if f.is_symlink():
            raise BadInput(f"{f}: is a symlink; refusing to write through it (give the table's own path)")
        kind = not_regular(f)
        if kind not in (None, "missing"):
            raise BadInput(f"{f}: is {kind}, not a regular file: a results table is one (give a file name)")


class TableBusy(LinkFailure):
    """Another sweep holds the table (exit 3, as a device in use)."""


class ResultsTable:
    """Append-only results of one sweep (resumable), locked while it runs."""

    def __init__(self, path: str | os.PathLike[str], cols: list[str]) -> None:
        self.path = Path(path)
        self.cols = cols
        self.parquet = parquet_wanted(self.path)
        self.journal = self.path.with_name(self.path.name + ".partial.csv") if self.parquet else self.path
        self.count = 0  # rows in the table (first per hash)
        self._fd: int | None = None

    def open(self) -> HashSet:
        """Lock the table, check what is there, open it for appending; the config hashes already done."""
        check_table_path(self.path)
        if self.parquet and self.path.exists():
            check_columns(self.path, self.cols)  # before any journal is written
        fd = self._lock()
        try:
            if os.fstat(fd).st_size == 0 and self.parquet and self.path.exists():  # a finished Parquet resumed
                os.write(fd, (",".join(self.cols) + "\n").encode("utf-8"))
                write_csv_rows(fd, text_rows(self.path, self.cols))
            done = self._read_existing(fd)
            if os.fstat(fd).st_size == 0:
                os.write(fd, (",".join(self.cols) + "\n").encode("utf-8"))
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        return done

    def _lock(self) -> int:
        flags = os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW
        for _ in range(10):
            try:
                fd = open_regular(self.journal, flags)
            except FileProblem as exc:
                raise BadInput(f"{self.journal}: {exc}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = flock_holder(fd)
                os.close(fd)
                owner = f"pid {pid}" if pid else "a process that did not say its pid"
                raise TableBusy(f"{self.journal}: in use by another mrctl sweep ({owner}); refusing to start: two "
                                "sweeps on one table would run its points twice (wait for it to finish, or give "
                                "another --out)") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.journal, follow_symlinks=False).st_ino
            except FileNotFoundError:
                same = False
            if same:
                return fd
            os.close(fd)  # replaced by the sweep that held it, between our open and our lock: take the new one
        raise TableBusy(f"{self.journal}: keeps being replaced; is another sweep writing it?")

    def _read_existing(self, fd: int) -> HashSet:
        """The hashes in the journal, every row checked first; then a torn
        last line (a kill in the middle of a row) is cut off."""
        done = HashSet()
        with open(os.dup(fd), "rb", closefd=True) as fh:
            fh.seek(0)
            for row in checked_rows(fh, self.journal, self.cols):
                done.add(row[1])
            end = fh.tell()
        if end < os.fstat(fd).st_size:
            os.ftruncate(fd, end)
        self.count = len(done)
        return done

    def add(self, row: dict[str, Any]) -> None:
        """Append one row (one write, flushed: a kill loses at most the row being written)."""
        assert self._fd is not None
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow([cell(row.get(c)) for c in self.cols])
        os.write(self._fd, buf.getvalue().encode("utf-8"))
        self.count += 1

    def close(self, complete: bool) -> None:
        """Flush; a complete table is rewritten in point order; Parquet written from the journal.
        The lock goes last, once the table says what it holds."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            os.fsync(fd)
            if self.parquet:
                with open(os.dup(fd), "rb", closefd=True) as fh:
                    fh.seek(0)
                    write_parquet(self.path, self.cols, checked_rows(fh, self.journal, self.cols), self.path.parent)
                if complete:
                    self.journal.unlink(missing_ok=True)
            elif complete:
                self._rewrite_sorted(fd)
        finally:
            os.close(fd)

    def _journal_rows(self, fd: int) -> Iterator[list[str]]:
        with open(os.dup(fd), "rb", closefd=True) as fh:
            fh.seek(0)
            yield from sorted_rows(checked_rows(fh, self.journal, self.cols), self.path.parent)

    def _rewrite_sorted(self, fd: int) -> None:
        tmp = self.path.with_name(f".{self.path.name}.tmp{os.getpid()}")
        try:
            with open(tmp, "w", encoding="utf-8", newline="") as out:
                w = csv.writer(out, lineterminator="\n")
                w.writerow(self.cols)
                w.writerows(self._journal_rows(fd))
                out.flush()
                os.fsync(out.fileno())
            os.replace(tmp, self.path)
        finally:
            tmp.unlink(missing_ok=True)
        fsync_dir(self.path.parent)

def read_results(path: str | os.PathLike[str]) -> tuple[list[str], list[dict[str, str]]]:
    """(columns, rows as text) of a results table, CSV or Parquet (for its figure)."""
    p = Path(path)
    from mrctl.util.files import MiB, read_regular_file

    if p.suffix == ".parquet":
        parquet_wanted(p)
        kind = not_regular(p)
        if kind is not None:
            raise BadInput(f"{p}: {'no such file' if kind == 'missing' else f'not a regular file ({kind})'}")
        cols = columns_of(p)
        return cols, [dict(zip(cols, r)) for r in text_rows(p, cols)]
    try:
        data = read_regular_file(p, 512 * MiB)
    except FileProblem as exc:
        raise BadInput(f"{p}: {exc}") from None
    try:
        raw = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise BadInput(f"{p}: line {line}: not UTF-8 text") from None
    reader = csv.reader(io.StringIO(raw))
    try:
        cols = next(reader)
    except StopIteration:
        raise BadInput(f"{p}: empty, not a sweep's results table") from None
    return cols, [dict(zip(cols, r)) for r in reader if len(r) == len(cols)]


def is_results_table(path: str | os.PathLike[str]) -> bool:
    """A sweep's table (its header has config_hash and status), not a run log;
    read without blocking (a FIFO is no table: the report refuses it)."""
    p = Path(path)
    if p.suffix == ".parquet":
        return True
    try:
        fd = open_regular(p)
    except FileProblem:
        return False
    try:
        head = os.read(fd, 1 << 16).split(b"\n", 1)[0].decode("utf-8", "replace").strip().split(",")
    except OSError:
        return False
    finally:
        os.close(fd)
    return "config_hash" in head and "status" in head
