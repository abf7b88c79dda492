"""Reading the CSV tables mrctl writes and reads: run logs, ground truth,
excitation and demand series.

One reader, so every table fails the same way: a :class:`CsvError` naming
the file and, where it helps, the 1-based physical line (what an editor
shows) and the column. Callers add their own rules on the numbers (finite
or not, how many rows, increasing time) and their own error type.

Format: UTF-8; ``#`` lines and blank lines are skipped anywhere; the first
other line is the header; fields are separated by commas and never quoted
(mrctl writes none, so a field count is one more than the comma count).
Columns are found by header name. Only the columns asked for are parsed as
floats (``nan``/``inf`` included): the others may hold anything, e.g. the
fault names a daemon log carries.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from mrctl.errors import BadInput
from mrctl.util.files import FileProblem, MiB, read_regular_file

__all__ = ["CsvError", "Table", "read_table", "load_series", "shown_header", "MAX_CSV_BYTES", "MAX_SERIES_BYTES"]

#: the largest CSV read: a run log of ~4 h at 1 kHz (~150 B per row)
MAX_CSV_BYTES = 2048 * MiB
#: the largest series a config points at (excitation, demand): ~1 h of 1 kHz samples is ~30 MiB
MAX_SERIES_BYTES = 256 * MiB


class CsvError(BadInput, ValueError):
    """A table cannot be read; the message names the file, line and column."""


class Table(NamedTuple):
    """What :func:`read_table` returns."""

    #: the columns asked for that the header has, in header order: float arrays
    columns: dict[str, np.ndarray]
    #: the physical (1-based) line number of each data row
    lines: np.ndarray
    #: every header name, as written
    header: list[str]
    #: the file read (for messages)
    path: Path

    def check_finite(self, column: str, allow_nan: bool = False) -> None:
        """:class:`CsvError` naming the line of the first infinite value in
        ``column`` (or NaN, unless ``allow_nan``: NaN as "no value")."""
        col = self.columns[column]
        bad = np.isinf(col) if allow_nan else ~np.isfinite(col)
        if bad.any():
            k = int(np.argmax(bad))
            raise CsvError(f"{self.path}: line {self.lines[k]}: column {column} is not finite: {float(col[k])!r}")


_COLUMN_NAME = re.compile(r"[A-Za-z0-9_ .()\[\]%/+*-]{1,40}")


def shown_header(header: Sequence[str], limit: int = 200) -> str:
    """A header's names for an error message, only if they look like column
    names: a file that is not a CSV (``/etc/shadow`` named by mistake or
    malice) has its first line kept out of the message."""
    names = [h for h in header if h]
    if not names:
        return "(none)"
    if not all(_COLUMN_NAME.fullmatch(h) for h in names):
        return f"{len(names)} field(s) that are not column names (not shown: is it a CSV?)"
    text = ", ".join(names)
    return text if len(text) <= limit else text[:limit] + "…"


def read_table(
    path: str | os.PathLike[str],
    columns: Sequence[str] | None = None,
    *,
    require: Sequence[str] = (),
    torn_last_line_ok: bool = False,
    max_bytes: int = MAX_CSV_BYTES,
) -> Table:
    """Read ``columns`` (None = all) of the CSV at ``path``.

    ``require``: columns that must be in the header. ``torn_last_line_ok``:
    drop a last line without its newline (what a killed writer leaves)
    instead of parsing it. Only a regular file of at most ``max_bytes`` is
    read (a device such as ``/dev/zero`` is refused at once). Raises
    :class:`CsvError` only.
    """
    p = Path(path)
    try:
        text = read_regular_file(p, max_bytes).decode("utf-8")
    except FileProblem as exc:
        what = "is a directory, not a CSV file" if "directory" in str(exc) else str(exc)
        raise CsvError(f"{p}: {what}") from None
    except UnicodeDecodeError:
        raise CsvError(f"{p}: not a text (UTF-8) CSV file") from None
    physical = text.split("\n")
    if physical[-1] == "" or torn_last_line_ok:
        physical.pop()  # the empty string after the final newline, or a torn last line
    rows: list[str] = []
    linenos: list[int] = []
    header_line = None
    for n, line in enumerate(physical, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if header_line is None:
            header_line = n
            header = [h.strip() for h in s.split(",")]
            continue
        rows.append(s)
        linenos.append(n)
    if header_line is None:
        raise CsvError(f"{p}: empty file (no header line)")
    missing = [c for c in require if c not in header]
    if missing:
        raise CsvError(f"{p}: missing required column(s) {', '.join(missing)}; found: {shown_header(header)}")
    wanted = [c for c in header if c] if columns is None else [c for c in columns if c in header]
    wanted = sorted(set(wanted), key=header.index)
    dupes = [c for c in wanted if header.count(c) > 1]
    if dupes:
        raise CsvError(f"{p}: column(s) {', '.join(dupes)} appear more than once in the header "
                       f"(line {header_line})")
    ncol = len(header)
    for n, s in zip(linenos, rows):
        if s.count(",") + 1 != ncol:
            raise CsvError(f"{p}: line {n} has {s.count(',') + 1} fields, the header has {ncol}")
    idx = [header.index(c) for c in wanted]
    if rows and idx:
        try:
            data = np.loadtxt(rows, delimiter=",", dtype=float, ndmin=2, usecols=idx, comments=None)
        except ValueError:
            _raise_first_bad_value(p, rows, linenos, wanted, idx)
            raise CsvError(f"{p}: cannot parse the data rows") from None  # pragma: no cover
    else:
        data = np.zeros((len(rows), len(idx)))
    return Table({c: data[:, j].copy() for j, c in enumerate(wanted)}, np.asarray(linenos, dtype=np.int64), header, p)


def _raise_first_bad_value(p: Path, rows: list[str], linenos: list[int], wanted: list[str], idx: list[int]) -> None:
    """Name the first field that is not a number (only on the slow, error path)."""
    for n, s in zip(linenos, rows):
        fields = s.split(",")
        for c, k in zip(wanted, idx):
            try:
                float(fields[k])
            except ValueError:
                raise CsvError(f"{p}: line {n}: column {c} is not a number: {fields[k].strip()!r}") from None


def load_series(path: str | Path, columns: tuple[str, ...], optional: tuple[str, ...] = (),
                gaps_ok: bool = False) -> dict[str, list[float]]:
    """Read a CSV time series with a header naming at least ``columns``
    (and ``optional`` ones if it has them); every other column is ignored,
    whatever it holds (a run log is a valid series: its ``late_us`` may be NaN).

    Time must start anywhere but strictly increase. ``gaps_ok``: a row whose
    value (not time) is NaN, a run log's missing sample, is left out (the
    series is interpolated across it); infinities are still errors. Errors
    are :class:`CsvError` naming the file, line and column, for the config
    layer to report with its key path."""
    p = Path(path)
    table = read_table(p, (*columns, *optional), require=columns, max_bytes=MAX_SERIES_BYTES)
    lines = table.lines
    cols = dict(table.columns)
    if gaps_ok:
        values = [c for c in cols if c != columns[0]]
        keep = ~np.any([np.isnan(cols[c]) for c in values], axis=0) if values else np.ones(len(lines), bool)
        if not keep.all():
            cols = {c: v[keep] for c, v in cols.items()}
            lines = lines[keep]
            table = table._replace(columns=cols, lines=lines)
    for c in table.columns:
        table.check_finite(c)
    out = {c: col.tolist() for c, col in table.columns.items()}
    t = out[columns[0]]
    if len(t) < 2:
        raise CsvError(f"{p}: needs at least 2 data rows" + (" with values (not NaN)" if gaps_ok else ""))
    for i in range(1, len(t)):
        if not t[i] > t[i - 1]:
            raise CsvError(f"{p}: line {table.lines[i]}: {columns[0]} must strictly increase")
    return out
