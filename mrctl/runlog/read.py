"""Reading run logs back: the CSV and its sidecar (docs/runlog.md).

For offline tools (report, identify, benches, test harnesses): nothing here
imports the daemon.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mrctl.runlog.files import sidecar_path
from mrctl.util.csvtable import Table, read_table
from mrctl.util.files import FileProblem, MiB, read_regular_file

__all__ = ["read_run", "read_run_table", "read_sidecar", "try_sidecar", "sidecar_path", "MAX_SIDECAR_BYTES"]

#: the largest sidecar read back (mrctl writes ~10-64 KiB: the config, the summary)
MAX_SIDECAR_BYTES = 16 * MiB


def read_run_table(path: str | os.PathLike[str], columns: Sequence[str] | None = None, *,
                   require: Sequence[str] = ()) -> Table:
    """A run log as a :class:`~mrctl.util.csvtable.Table` (``columns``: None = all).

    Tolerates what a killed recorder or a full disk leaves: a last line
    without its newline is dropped. ``#`` comment lines and blank lines are
    skipped (logs of mrctl before 2026-11 began with one). Any other
    malformed line raises :class:`mrctl.util.csvtable.CsvError` (a
    ``BadInput`` and a ``ValueError``) naming the file and 1-based line."""
    return read_table(path, columns, require=require, torn_last_line_ok=True)


def read_run(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read a run CSV into ``{column: float array}`` (all columns, in order)."""
    return read_run_table(path).columns


def read_sidecar(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The JSON sidecar of a run CSV (pass the CSV or the .json path): a
    regular file of at most :data:`MAX_SIDECAR_BYTES` (``/dev/zero`` or a
    FIFO planted there is refused, not read). ``FileProblem`` (a
    ``BadInput``) or ``ValueError`` (not JSON, or nested beyond reason)."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        p = sidecar_path(p)
    text = read_regular_file(p, MAX_SIDECAR_BYTES).decode("utf-8")
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"{p}: nested too deeply to be a sidecar") from None


def try_sidecar(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The sidecar if there is a readable one (a JSON object), else ``{}``:
    for tools that use it when present (a CSV written by hand has none)."""
    try:
        side = read_sidecar(path)
    except (OSError, ValueError, FileProblem):
        return {}
    return side if isinstance(side, dict) else {}
