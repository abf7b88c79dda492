"""A sweep's results as Parquet (pyarrow): checked, read and written as streams.

The table runs as a CSV journal (``NAME.parquet.partial.csv``,
:mod:`mrctl.sweep.table`); the Parquet file is written from it at the end or
at an interruption, batch by batch, each column typed by what it holds (a
column of whole numbers int64, of numbers float64, of true/false bool,
else text; the hash, status and error always text). What is there is
checked before any journal is written: a file pyarrow cannot read, or the
table of another sweep, is refused (exit 2).
"""

from __future__ import annotations

import csv
import io
import itertools
import os
from pathlib import Path
from typing import Any, Iterator

from mrctl.errors import BadInput
from mrctl.sweep.rows import cell, sorted_rows

__all__ = ["parquet_wanted", "check_columns", "text_rows", "write_parquet", "TEXT_COLUMNS"]

#: columns kept as text whatever they hold
TEXT_COLUMNS = ("config_hash", "status", "error", "mrctl_version", "build")
#: rows per batch read or written
BATCH = 65536


def parquet_wanted(path: Path) -> bool:
    """A ``.parquet`` name: check pyarrow before any point runs."""
    if path.suffix != ".parquet":
        return False
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        raise BadInput(f"{path}: a .parquet table needs pyarrow (pip install pyarrow), or name it .csv") from None
    return True


def _batches(path: Path) -> Iterator[Any]:
    import pyarrow.parquet as pq

    try:
        yield from pq.ParquetFile(path).iter_batches(batch_size=BATCH)
    except Exception as exc:  # noqa: BLE001 - pyarrow's errors vary by version: a corrupt file is bad input
        raise BadInput(f"{path}: not a readable Parquet file ({type(exc).__name__}); give a new --out") from None


def columns_of(path: Path) -> list[str]:
    """The columns of the Parquet file at ``path`` (``BadInput`` if pyarrow cannot read it)."""
    import pyarrow.parquet as pq

    try:
        return list(pq.read_schema(path).names)
    except Exception as exc:  # noqa: BLE001 - pyarrow's errors vary by version: any is "not a table"
        raise BadInput(f"{path}: not a readable Parquet file ({type(exc).__name__}); give a new --out") from None


def check_columns(path: Path, cols: list[str]) -> None:
    """``BadInput`` unless the Parquet file at ``path`` is a table with ``cols``."""
    names = columns_of(path)
    if names != cols:
        raise BadInput(f"{path}: holds another sweep's table (its columns differ from this sweep's: "
                       f"{', '.join(sorted(set(names) ^ set(cols))) or 'order'}); give a new --out")


def text_rows(path: Path, cols: list[str]) -> Iterator[list[str]]:
    """The rows of the Parquet file at ``path``, as the journal's text cells, batch by batch."""
    for batch in _batches(path):
        data = batch.to_pydict()
        for i in range(batch.num_rows):
            yield [cell(data[c][i]) for c in cols]


def write_csv_rows(fd: int, rows: Iterator[list[str]]) -> None:
    """``rows`` appended to the file open at ``fd``, a batch per write."""
    while True:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        n = 0
        for row in rows:
            w.writerow(row)
            n += 1
            if n >= BATCH:
                break
        if n == 0:
            return
        os.write(fd, buf.getvalue().encode("utf-8"))


def write_parquet(path: Path, cols: list[str], rows: Iterator[list[str]], spill_dir: Path) -> None:
    """``rows`` (the first per config hash, in any order) as the Parquet file
    ``path`` in point order, replaced at once when complete. One pass: each
    column's type is widened as the sort reads the rows, and is final once
    the sort gives its first row."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    kinds = ["str" if c in TEXT_COLUMNS else "none" for c in cols]

    def typed() -> Iterator[list[str]]:
        for row in rows:
            for j, v in enumerate(row):
                kinds[j] = _widen(kinds[j], v)
            yield row

    ordered = sorted_rows(typed(), spill_dir)
    first = next(ordered, None)  # the sort has read every row: the kinds are final
    kinds = ["float" if k == "none" else k for k in kinds]
    types = {"int": pa.int64(), "float": pa.float64(), "bool": pa.bool_(), "str": pa.string()}
    schema = pa.schema([(c, types[k]) for c, k in zip(cols, kinds)])
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with pq.ParquetWriter(tmp, schema) as writer:
            batch: list[list[str]] = []
            for row in itertools.chain([first] if first is not None else [], ordered):
                batch.append(row)
                if len(batch) >= BATCH:
                    writer.write_table(_arrow(batch, schema, kinds))
                    batch = []
            writer.write_table(_arrow(batch, schema, kinds))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _widen(kind: str, v: str) -> str:
    """The narrowest column type (none → int → float → str, none → bool → str)
    that holds what it held and ``v`` (an empty cell is null in any)."""
    if v == "" or kind == "str":
        return kind
    if v in ("true", "false"):
        return "bool" if kind in ("none", "bool") else "str"
    if kind == "bool":
        return "str"
    if kind in ("none", "int"):
        try:
            int(v)
            return "int"
        except ValueError:
            pass
    try:
        float(v)
        return "float"
    except ValueError:
        return "str"


def _arrow(rows: list[list[str]], schema: Any, kinds: list[str]) -> Any:
    import pyarrow as pa

    conv = {"int": lambda v: None if v == "" else int(v), "float": lambda v: None if v == "" else float(v),
            "bool": lambda v: None if v == "" else v == "true", "str": lambda v: v}
    arrays = [pa.array([conv[k](r[j]) for r in rows], type=schema.field(j).type) for j, k in enumerate(kinds)]
    return pa.Table.from_arrays(arrays, schema=schema)
