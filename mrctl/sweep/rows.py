"""A results table's rows as streams: read and checked, deduplicated, sorted, never all in memory.

A table of ten million rows is ~3 GB of text: it is read line by line
(:func:`checked_rows`: every line UTF-8, every row whole with a whole-number
``point``, the first row per config hash), the hashes kept at 8 bytes each
(:class:`HashSet`), and sorted by point in chunks merged from temporary
files (:func:`sorted_rows`).
"""

from __future__ import annotations

import csv
import hashlib
import heapq
import io
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from mrctl.errors import BadInput

__all__ = ["cell", "HashSet", "lines", "checked_rows", "sorted_rows", "SORT_CHUNK"]

#: rows sorted in memory at once when a table is rewritten in point order (more: merged from runs on disk)
SORT_CHUNK = 50_000


def cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else repr(v))
    if isinstance(v, (dict, list)):
        return json.dumps(v, sort_keys=True)
    return str(v)


class HashSet:
    """Config hashes at 8 bytes each (a 64-bit digest in a sorted array, the
    newest in a small set): a table of ten million rows is 80 MB, not 1 GB."""

    def __init__(self) -> None:
        self._sorted = np.empty(0, dtype=np.uint64)
        self._new: set[int] = set()

    @staticmethod
    def _key(h: str) -> int:
        return int.from_bytes(hashlib.blake2b(h.encode(), digest_size=8).digest(), "little")

    def add(self, h: str) -> None:
        self._new.add(self._key(h))
        if len(self._new) >= 1 << 16:
            self._sorted = np.union1d(self._sorted, np.fromiter(self._new, dtype=np.uint64, count=len(self._new)))
            self._new.clear()

    def __contains__(self, h: str) -> bool:
        k = self._key(h)
        if k in self._new:
            return True
        i = int(np.searchsorted(self._sorted, np.uint64(k)))
        return i < len(self._sorted) and int(self._sorted[i]) == k

    def __len__(self) -> int:
        return len(self._sorted) + len(self._new)


def lines(fh: Any, path: Path) -> Iterator[str]:
    """The text lines of a table, each checked to be UTF-8 (the error names
    the line); a last line without its newline (a row torn by a kill) is
    left out, and ``fh`` left at its start."""
    for n, raw in enumerate(iter(fh.readline, b""), start=1):
        if not raw.endswith(b"\n"):
            fh.seek(-len(raw), os.SEEK_CUR)
            return
        try:
            yield raw.decode("utf-8")
        except UnicodeDecodeError:
            raise BadInput(f"{path}: line {n}: not UTF-8 text; not a table mrctl wrote (hand-edited?): remove "
                           "the line or give a new --out") from None


def checked_rows(fh: Any, path: Path, cols: list[str]) -> Iterator[list[str]]:
    """The rows of a journal after its header (checked against ``cols``), each
    checked (its cells, a whole ``point``); the first row per config hash."""
    reader = csv.reader(lines(fh, path))
    try:
        header = next(reader)
    except StopIteration:
        return
    except csv.Error as exc:
        raise BadInput(f"{path}: line 1: not a CSV header ({exc})") from None
    if header != cols:
        raise BadInput(f"{path}: holds another sweep's table (its columns differ from this sweep's: "
                       f"{', '.join(sorted(set(header) ^ set(cols))) or 'order'}); give a new --out")
    seen = HashSet()
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise BadInput(f"{path}: line {reader.line_num}: not a CSV row ({exc}); hand-edited? remove the line "
                           "or give a new --out") from None
        where = f"{path}: line {reader.line_num}"
        if len(row) != len(cols):
            raise BadInput(f"{where}: {len(row)} cells, the table has {len(cols)} columns; hand-edited? remove "
                           "the line or give a new --out")
        if not row[0].isdigit():
            raise BadInput(f"{where}: point is not a whole number; hand-edited? remove the line or give a new --out")
        if not row[1] or row[1] in seen:
            continue  # a point that ran twice: its first row is the one
        seen.add(row[1])
        yield row


def sorted_rows(rows: Iterator[list[str]], spill_dir: Path) -> Iterator[list[str]]:
    """``rows`` in point order (stable): sorted in chunks of :data:`SORT_CHUNK`,
    merged from temporary files when there are several."""
    runs: list[Any] = []
    chunk: list[list[str]] = []
    try:
        for row in rows:
            chunk.append(row)
            if len(chunk) >= SORT_CHUNK:
                runs.append(spill(sorted(chunk, key=lambda r: int(r[0])), spill_dir))
                chunk = []
        chunk.sort(key=lambda r: int(r[0]))
        if not runs:
            yield from chunk
            return
        runs.append(spill(chunk, spill_dir))
        readers = [csv.reader(io.TextIOWrapper(f, encoding="utf-8", newline="")) for f in runs]
        yield from heapq.merge(*readers, key=lambda r: int(r[0]))
    finally:
        for f in runs:
            f.close()


def spill(rows: list[list[str]], spill_dir: Path) -> Any:
    f = tempfile.TemporaryFile(dir=spill_dir)  # unlinked already: nothing left behind
    text = io.TextIOWrapper(f, encoding="utf-8", newline="")
    csv.writer(text, lineterminator="\n").writerows(rows)
    text.flush()
    text.detach()
    f.seek(0)
    return f
