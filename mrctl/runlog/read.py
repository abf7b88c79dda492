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

__all__ = ["read_run", "read_run_table", "read_sidecar", "try_sidecar", "sidecar_path", "align_load_cell"]


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
    """The JSON sidecar of a run CSV (pass the CSV or the .json path)."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        p = sidecar_path(p)
    return json.loads(p.read_text(encoding="utf-8"))


def try_sidecar(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The sidecar if there is a readable one (a JSON object), else ``{}``:
    for tools that use it when present (a CSV written by hand has none)."""
    try:
        side = read_sidecar(path)
    except (OSError, ValueError):
        return {}
    return side if isinstance(side, dict) else {}


def align_load_cell(cols: dict[str, np.ndarray], side: dict[str, Any]) -> dict[str, np.ndarray]:
    """The columns with ``F`` moved to the tick it measured, for analyses that
    pair force with the same instant's x and v (identification).

    ``F`` is the load cell as the controller received it; the sidecar's
    ``load_cell_delay_ticks`` says how many ticks late that is (1 on the
    simulated benches, whose load cell reads the previous tick's force; 0 on
    hardware, where the DAQ samples x, v and F together). Every column loses
    its last ``n`` rows. Unchanged when the sidecar says 0 or nothing."""
    n = side.get("load_cell_delay_ticks")
    if not isinstance(n, int) or isinstance(n, bool) or n <= 0 or "F" not in cols or len(cols["F"]) <= n:
        return cols
    out = {c: a[:-n] for c, a in cols.items()}
    out["F"] = cols["F"][n:]
    return out
