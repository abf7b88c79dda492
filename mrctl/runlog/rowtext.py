"""The run log's rows as CSV text: one formatter for ``mrctl run`` and ``mrctl simulate``.

The text of every value is the ``%``-format of its column
(:data:`mrctl.runlog.format.RUN_FORMATS`: ``'%.9g'``, ``'%.10g'`` for the
clocks and counters); that is the log's contract, and Python's ``%`` is its
reference. The compiled build formats in C (``_rowtext.c``, built with the
tick: mrctl/build.py), about ten times faster, and writes the same bytes:
tests/test_rowtext.py compares the two on the shipped experiments and on
awkward values (NaN, ±inf, −0.0, subnormals, ties, powers of ten, integers
in float columns). The interpreted build (``MRCTL_PURE_PYTHON=1``, or no
compiler at install) runs the ``%`` twin here. Formats other than ``%.Pg``
(e.g. a recorder's exact ``'%r'``) always take the twin.

Two layouts: :meth:`RowFormatter.rows` reads a row-major block of doubles
(the daemon's packed blocks), :meth:`RowFormatter.columns` one buffer per
column (``mrctl simulate``'s arrays; :meth:`RowFormatter.write_columns`
formats and writes them, in the compiled build to a plain file in one C
call without the GIL). ``release_gil``: the compiled path lets other threads
run while it formats (a writer thread); the daemon's loop thread keeps the
GIL for its few rows at a time (docs/design.md, "Threads").
"""

from __future__ import annotations

import io
import itertools
import os
import re
import struct
from typing import Any, BinaryIO, Mapping, Sequence

from mrctl.runlog.format import row_format

try:  # the compiled build's formatter; refused under MRCTL_PURE_PYTHON (mrctl/build.py)
    from mrctl.runlog import _rowtext as _compiled
except ImportError:
    _compiled = None

__all__ = ["RowFormatter", "compiled_available"]

_G_FORMAT = re.compile(r"%\.(\d{1,2})g\Z")
_MAX_PREC = 17  # _rowtext.c's MAX_PREC
#: rows per '%' call of the Python twin (bounds one C call holding the GIL, and its temporaries)
_PY_CHUNK_ROWS = 1024


def compiled_available() -> bool:
    """The C formatter is built and loaded (the compiled build)."""
    return _compiled is not None


def column_formats(columns: Sequence[str], fmt: str | Mapping[str, str]) -> list[str]:
    """Each column's ``%``-format: ``fmt`` for all, or ``{column: format}`` over exact ``'%r'``."""
    return [fmt] * len(columns) if isinstance(fmt, str) else [fmt.get(c, "%r") for c in columns]


def precisions(formats: Sequence[str]) -> tuple[int, ...] | None:
    """The P of every ``'%.Pg'`` format (1 ≤ P ≤ 17), or None if any column has another format."""
    out = []
    for f in formats:
        m = _G_FORMAT.match(f)
        if m is None or not 1 <= int(m.group(1)) <= _MAX_PREC:
            return None
        out.append(int(m.group(1)))
    return tuple(out)


class RowFormatter:
    """CSV lines of float rows, each value in its column's ``%``-format.

    ``columns``/``fmt``/``require_core`` as :func:`mrctl.runlog.format.row_format`
    (which checks them: ValueError). ``compiled`` says which path runs;
    ``use_compiled=False`` forces the Python twin (tests, benches)."""

    __slots__ = ("columns", "ncols", "row_fmt", "precisions", "_c", "_structs")

    def __init__(self, columns: Sequence[str], fmt: str | Mapping[str, str] = "%r", require_core: bool = True,
                 use_compiled: bool = True) -> None:
        self.columns = tuple(str(c) for c in columns)
        self.ncols = len(self.columns)
        self.row_fmt = row_format(self.columns, fmt, require_core)
        self.precisions = precisions(column_formats(self.columns, fmt))
        self._c = _compiled if use_compiled and self.precisions is not None else None
        self._structs: dict[int, Any] = {}

    @property
    def compiled(self) -> bool:
        return self._c is not None

    def header(self) -> bytes:
        """The CSV's first line: the column names."""
        return (",".join(self.columns) + "\n").encode("ascii")

    def rows(self, buf: Any, row0: int, nrows: int, release_gil: bool = False) -> bytes:
        """Rows ``row0 .. row0 + nrows`` of ``buf``, a row-major buffer of
        float64 (``ncols`` a row: the recorder's packed blocks)."""
        if self._c is not None:
            return self._c.format_rows(buf, self.precisions, row0, nrows, release_gil)
        if row0 < 0 or nrows < 0:
            raise IndexError(f"rows {row0}..{row0 + nrows}: negative")
        if nrows == 0:
            return b""
        n = nrows * self.ncols
        unpack = self._structs.get(n)
        if unpack is None:
            unpack = struct.Struct("=" + "d" * n).unpack_from
            if len(self._structs) < 64:
                self._structs[n] = unpack
        try:
            values = unpack(buf, 8 * self.ncols * row0)
        except struct.error:
            raise IndexError(f"rows {row0}..{row0 + nrows} outside the buffer") from None
        return ((self.row_fmt * nrows) % values).encode("ascii")

    def columns_text(self, cols: Sequence[Any], row0: int, nrows: int, release_gil: bool = False) -> bytes:
        """Rows ``row0 .. row0 + nrows`` of one float64 buffer per column
        (``array('d')``, 1-D contiguous ndarrays), in the order of ``columns``."""
        self._check_columns(cols, row0, nrows)
        if self._c is not None:
            return self._c.format_columns(cols, self.precisions, row0, nrows, release_gil)
        parts = []
        for a in range(row0, row0 + nrows, _PY_CHUNK_ROWS):
            b = min(a + _PY_CHUNK_ROWS, row0 + nrows)
            lists = [memoryview(c)[a:b].tolist() for c in cols]
            if any(len(v) != b - a for v in lists):
                raise IndexError(f"rows {row0}..{row0 + nrows} outside a column of {min(map(len, lists)) + a}")
            parts.append((self.row_fmt * (b - a)) % tuple(itertools.chain.from_iterable(zip(*lists))))
        return "".join(parts).encode("ascii")

    def write_columns(self, fh: BinaryIO, cols: Sequence[Any], row0: int, nrows: int
                      ) -> tuple[int, int, OSError | None]:
        """:meth:`columns_text` written to ``fh``: (bytes written, complete
        rows written, the write's error or None). Compiled, to a plain file
        (``io.FileIO``), the rows are formatted and written in one call
        without the GIL; else the text goes through ``fh.write``."""
        if self._c is not None and type(fh) is io.FileIO:
            self._check_columns(cols, row0, nrows)
            done, rows, err = self._c.write_columns(fh.fileno(), cols, self.precisions, row0, nrows)
            return done, rows, (OSError(err, os.strerror(err)) if err else None)
        return write_all(fh, self.columns_text(cols, row0, nrows, release_gil=True), nrows)

    def _check_columns(self, cols: Sequence[Any], row0: int, nrows: int) -> None:
        """ValueError unless one buffer per column; IndexError for a negative row range."""
        if len(cols) != self.ncols:
            raise ValueError(f"{self.ncols} columns, {len(cols)} buffers given")
        if row0 < 0 or nrows < 0:
            raise IndexError(f"rows {row0}..{row0 + nrows}: negative")


def write_all(fh: BinaryIO, data: bytes, rows: int) -> tuple[int, int, OSError | None]:
    """``data`` (``rows`` lines) written to ``fh``, repeating short writes:
    (bytes written, complete lines written, the error or None)."""
    view = memoryview(data)
    done = 0
    try:
        while done < len(data):
            k = fh.write(view[done:])
            if k is None:  # a buffered file takes everything
                k = len(data) - done
            if k <= 0:
                raise OSError(f"write() returned {k} with {len(data) - done} bytes left")
            done += k
    except OSError as exc:
        return done, data.count(b"\n", 0, done), exc
    return done, rows, None
