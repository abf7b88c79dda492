"""The results table of a sweep: one row per point, written as it completes.

CSV, appended row by row and flushed, so a Ctrl-C or a kill leaves a valid
partial table (a half-written last line from a kill is dropped when the
sweep resumes); the points already in it are skipped by their config hash.
A ``.parquet`` name (with pyarrow installed) gets its rows journalled in
``NAME.parquet.partial.csv`` and the Parquet file written from them at the
end or at an interruption. A finished table is rewritten in point order.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any, Iterable

from mrctl.errors import BadInput
from mrctl.runlog.files import fsync_dir

TAIL = ("status", "error", "wall_s", "mrctl_version", "build")


def columns(axes: list[str], metrics: Iterable[str]) -> list[str]:
    """The table's columns: point, config_hash, the point's values, seed, metrics, status …"""
    return ["point", "config_hash", *axes, "seed", *metrics, *TAIL]


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else repr(v))
    if isinstance(v, (dict, list)):
        return json.dumps(v, sort_keys=True)
    return str(v)


def parquet_wanted(path: Path) -> bool:
    """A ``.parquet`` name: check pyarrow before any point runs."""
    if path.suffix != ".parquet":
        return False
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        raise BadInput(f"{path}: a .parquet table needs pyarrow (pip install pyarrow), or name it .csv") from None
    return True


class ResultsTable:
    """Append-only results of one sweep (resumable)."""

    def __init__(self, path: str | os.PathLike[str], cols: list[str]) -> None:
        self.path = Path(path)
        self.cols = cols
        self.parquet = parquet_wanted(self.path)
        self.journal = self.path.with_name(self.path.name + ".partial.csv") if self.parquet else self.path
        self.rows: list[dict[str, str]] = []
        self._fh: io.TextIOBase | None = None

    def open(self) -> set[str]:
        """Open for appending; the config hashes already done (resumption)."""
        if self.parquet and self.path.exists() and not self.journal.exists():
            self._parquet_to_journal()
        if self.journal.is_symlink():
            raise BadInput(f"{self.journal}: is a symlink; refusing to write through it")
        if self.journal.exists():
            self.rows = self._read_existing()
        fd = os.open(self.journal, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        self._fh = io.open(fd, "w", newline="", encoding="utf-8")
        if not self.rows and os.fstat(fd).st_size == 0:
            self._fh.write(",".join(self.cols) + "\n")
            self._fh.flush()
        return {r["config_hash"] for r in self.rows}

    def _read_existing(self) -> list[dict[str, str]]:
        raw = self.journal.read_bytes()
        if raw and not raw.endswith(b"\n"):  # a kill mid-row: drop the half row
            raw = raw[: raw.rfind(b"\n") + 1]
            with open(self.journal, "r+b") as fh:
                fh.truncate(len(raw))
        if not raw:
            return []
        reader = csv.reader(io.StringIO(raw.decode("utf-8")))
        header = next(reader)
        if header != self.cols:
            raise BadInput(f"{self.journal}: holds another sweep's table (its columns differ from this sweep's: "
                           f"{', '.join(sorted(set(header) ^ set(self.cols))) or 'order'}); give a new --out")
        return [dict(zip(header, r)) for r in reader if len(r) == len(header)]

    def add(self, row: dict[str, Any]) -> None:
        """Append one row and flush it (a kill loses at most the row being written)."""
        assert self._fh is not None
        cells = {c: _cell(row.get(c)) for c in self.cols}
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow([cells[c] for c in self.cols])
        self._fh.write(buf.getvalue())
        self._fh.flush()
        self.rows.append(cells)

    def close(self, complete: bool) -> None:
        """Flush; a complete table is rewritten in point order; Parquet written from the journal."""
        if self._fh is not None:
            os.fsync(self._fh.fileno())
            self._fh.close()
            self._fh = None
        rows = sorted(self.rows, key=lambda r: int(r["point"])) if complete else self.rows
        if self.parquet:
            self._write_parquet(rows)
            if complete:
                self.journal.unlink(missing_ok=True)
        elif complete:
            self._replace(self.path, _csv_text(self.cols, rows).encode("utf-8"))

    def _replace(self, path: Path, data: bytes) -> None:
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)

    def _write_parquet(self, rows: list[dict[str, str]]) -> None:
        import pyarrow as pa
        import pyarrow.csv as pacsv
        import pyarrow.parquet as pq

        text = _csv_text(self.cols, rows).encode("utf-8")
        opts = pacsv.ConvertOptions(column_types={"config_hash": pa.string(), "error": pa.string()},
                                    strings_can_be_null=False)
        table = pacsv.read_csv(io.BytesIO(text), convert_options=opts)
        tmp = self.path.with_name(f".{self.path.name}.tmp{os.getpid()}")
        pq.write_table(table, tmp)
        os.replace(tmp, self.path)

    def _parquet_to_journal(self) -> None:
        cols, rows = read_results(self.path)
        self.journal.write_text(_csv_text(cols, rows), encoding="utf-8")


def _csv_text(cols: list[str], rows: list[dict[str, str]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow([r.get(c, "") for c in cols])
    return buf.getvalue()


def read_results(path: str | os.PathLike[str]) -> tuple[list[str], list[dict[str, str]]]:
    """(columns, rows as text) of a results table, CSV or Parquet."""
    p = Path(path)
    from mrctl.util.files import MiB, FileProblem, read_regular_file

    if p.suffix == ".parquet":
        parquet_wanted(p)
        import pyarrow.parquet as pq

        t = pq.read_table(p)
        cols = t.column_names
        data = t.to_pydict()
        return cols, [{c: _cell(data[c][i]) for c in cols} for i in range(t.num_rows)]
    try:
        raw = read_regular_file(p, 512 * MiB).decode("utf-8")
    except FileProblem as exc:
        raise BadInput(f"{p}: {exc}") from None
    reader = csv.reader(io.StringIO(raw))
    try:
        cols = next(reader)
    except StopIteration:
        raise BadInput(f"{p}: empty, not a sweep's results table") from None
    return cols, [dict(zip(cols, r)) for r in reader if len(r) == len(cols)]


def is_results_table(path: str | os.PathLike[str]) -> bool:
    """A sweep's table (its header has config_hash and status), not a run log."""
    p = Path(path)
    if p.suffix == ".parquet":
        return True
    try:
        with open(p, encoding="utf-8", errors="replace") as fh:
            head = fh.readline().strip().split(",")
    except OSError:
        return False
    return "config_hash" in head and "status" in head
