"""mrctl's own run logs as a dataset: the description mrctl writes itself.

A run log (the CSV ``mrctl simulate`` or ``mrctl run`` writes, and its
sidecar) of a sine stroke through a staircase of constant currents — e.g.
``config/experiments/identify.yaml`` — is a constant-input dataset like any
lab's: :func:`describe_runs` writes the description a user would (which
columns, the commanded current ``I`` as the input, the load cell's delay
from the sidecar, the rows a fault left without a sample excluded), and
:func:`load_runs` validates it with the dataset schema, so ``mrctl identify
RUN.csv`` runs the same :mod:`.pipeline` as ``mrctl identify --dataset``. ``mrctl identify RUN.csv --describe D.yaml`` writes the
description for a user to edit and run with ``--dataset``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mrctl.offline.identify.errors import IdentificationError
from mrctl.runlog.read import read_sidecar
from mrctl.util.files import FileProblem
from mrctl.util.csvtable import CsvError, read_table, shown_header
from mrctl.util.schema import Node

__all__ = ["describe_runs", "load_runs", "RUN_FIT_RATE_HZ", "RUN_MAX_GAP_SAMPLES"]

#: the first of each pair a run CSV has (with a value) is read; hand-made records name them so
_FORCE = ("F_meas", "F")
_VELOCITY = ("v_meas", "v")
_DISPLACEMENT = ("x_meas", "x")
#: the fit rate of a run (Hz): the loop's own, so the pre-sliding transients after a reversal, a few
#: ticks long, stay in the data (a faster log is decimated to it, anti-aliased)
RUN_FIT_RATE_HZ = 1000.0
#: skipped ticks in a row filled by interpolation (50 ms at 1 kHz: a stalled loop, not a lost link)
RUN_MAX_GAP_SAMPLES = 50


def _unique(name: str, taken: set[str]) -> str:
    out, k = name, 2
    while out in taken:
        out, k = f"{name}-{k}", k + 1
    taken.add(out)
    return out


def _nan_windows(t: np.ndarray, bad: np.ndarray) -> list[list[float]]:
    """[t0, t1] windows around every run of rows in ``bad`` (one row's margin each side)."""
    if not bad.any():
        return []
    d = np.diff(np.concatenate(([0], bad.astype(np.int8), [0])))
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    return [[float(t[a]) - 0.5 * dt, float(t[b - 1]) + 0.5 * dt]
            for a, b in zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist())]


def _sidecar_delay(p: Path, notes: list[str]) -> int:
    """The sidecar's ``load_cell_delay_ticks`` (0 without a sidecar: a CSV
    written by hand); an unreadable sidecar or value is said in ``notes``."""
    from mrctl.runlog.files import sidecar_path

    if not sidecar_path(p).exists():
        return 0
    try:
        side = read_sidecar(p)
    except (OSError, ValueError, UnicodeDecodeError, FileProblem) as exc:
        notes.append(f"{p.name}: its sidecar cannot be read ({str(exc)[:80]}): the load cell is taken to read in "
                     "step with x and v (no delay)")
        return 0
    n = side.get("load_cell_delay_ticks", 0) if isinstance(side, dict) else None
    if n is None or n == 0:
        return 0
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        notes.append(f"{p.name}: its sidecar's load_cell_delay_ticks {str(n)[:24]!r} is not a tick count: the load "
                     "cell is taken to read in step with x and v (no delay)")
        return 0
    return n


def describe_runs(paths: Sequence[str | os.PathLike[str]], *, name: str | None = None,
                  notes: list[str] | None = None) -> dict[str, Any]:
    """The dataset description (a plain mapping, the YAML a user would write)
    of mrctl run CSVs: constant_input, ``input: current`` from the commanded
    current ``I``, force ``F_meas`` or ``F`` moved back by the sidecar's
    ``load_cell_delay_ticks``, velocity ``v_meas`` or ``v``, displacement
    ``x_meas`` or ``x`` when logged; the force offset always fitted, the
    stiffness when there is a displacement. Rows
    where a used column is NaN (a tick without a sample) are excluded.
    What the description cannot say (an unreadable sidecar) goes to ``notes``.

    Raises:
        IdentificationError: no path, the same file twice, a file that is not
            a run CSV (a missing or empty column named with what
            identification needs), runs whose columns or load-cell delays
            differ, a delay longer than the run."""
    if not paths:
        raise IdentificationError("no run CSV given")
    notes = [] if notes is None else notes
    files: list[dict[str, Any]] = []
    columns: dict[str, Any] | None = None
    delays: set[int] = set()
    taken: set[str] = set()
    seen: dict[Path, str] = {}
    for path in paths:
        p = Path(path)
        key = p.resolve()
        if key in seen:
            raise IdentificationError(f"{p}: given twice (also as {seen[key]}); its data would count twice")
        seen[key] = str(p)
        try:
            table = read_table(p, ["t", "I", *_FORCE, *_VELOCITY, *_DISPLACEMENT], torn_last_line_ok=True)
        except CsvError as exc:
            raise IdentificationError(str(exc)) from None
        h, data = table.header, table.columns

        def pick(names: Sequence[str]) -> str | None:
            """The first of ``names`` with a value in some row, else the first there (an empty one)."""
            there = [n for n in names if n in h]
            return next((n for n in there if np.isfinite(data[n]).any()), there[0] if there else None)

        cols = {"time": "t" if "t" in h else None, "input": "I" if "I" in h else None,
                "force": pick(_FORCE), "velocity": pick(_VELOCITY), "displacement": pick(_DISPLACEMENT)}
        missing = [what for what, key in (("time column 't' (s)", "time"),
                                          ("current column 'I' (commanded current, A)", "input"),
                                          ("force column 'F_meas' or 'F' (N)", "force"),
                                          ("velocity column 'v_meas' or 'v' (m/s)", "velocity")) if cols[key] is None]
        if missing:
            raise IdentificationError(f"{p}: no {' and no '.join(missing)}; identifying from a run CSV needs t, I, "
                                      f"F_meas (or F) and v_meas (or v); header: {shown_header(h, 120)} (a lab's "
                                      "own record: describe it in a dataset, mrctl identify --dataset, "
                                      "docs/identification.md)")
        empty = [c for c in cols.values() if c is not None and not np.isfinite(data[c]).any()]
        if empty:
            raise IdentificationError(f"{p}: column {', '.join(empty)} has no value in any row (NaN throughout: no "
                                      "load cell or no sample on this bench?); identification needs the force, the "
                                      "velocity and the current measured")
        if columns is not None and cols != columns:
            raise IdentificationError(f"{p}: its columns differ from {paths[0]}'s "
                                      f"({', '.join(f'{k} {v}' for k, v in cols.items() if v)}); identify them "
                                      "separately, or describe them in a dataset")
        columns = cols
        delay = _sidecar_delay(p, notes)
        t = data["t"]
        if delay and delay > t.size - 3:
            raise IdentificationError(f"{p}: its sidecar's load_cell_delay_ticks {delay} is longer than the run "
                                      f"({t.size} rows)")
        delays.add(delay)
        bad = np.zeros(t.size, bool)
        bad_F = np.zeros(t.size, bool)
        for role, c in cols.items():
            if c is not None:
                (bad_F if role == "force" and delay else bad)[:] |= ~np.isfinite(data[c])
        entry: dict[str, Any] = {"path": str(key), "name": _unique(p.stem, taken)}
        if np.isfinite(t).all() and t.size > 1:
            dt = float(np.median(np.diff(t)))
            # a force row is the load cell's reading of the tick `delay` ticks before it (on the tick grid)
            windows = _nan_windows(t, bad) + [[a - delay * dt, b - delay * dt] for a, b in _nan_windows(t, bad_F)]
            if windows:
                entry["exclude"] = sorted(windows)
        files.append(entry)
    if len(delays) > 1:
        raise IdentificationError(f"the runs' sidecars give different load-cell delays ({sorted(delays)} ticks); "
                                  "identify them separately")
    assert columns is not None
    delay = delays.pop()
    col_doc: dict[str, Any] = {k: v for k, v in columns.items()}
    if delay:
        col_doc["force"] = {"name": columns["force"], "delay_samples": delay}
    has_x = columns["displacement"] is not None
    return {
        "version": 1,
        "name": name or (Path(paths[0]).stem if len(paths) == 1 else f"{Path(paths[0]).stem} and {len(paths) - 1} more"),
        "description": "mrctl run log(s) of constant-current steps, described by mrctl identify"
                       + (f"; the load cell reads {delay} tick(s) late (sidecar load_cell_delay_ticks)" if delay else ""),
        "protocol": "constant_input",
        "input": "current",
        "columns": col_doc,
        "format": {"max_gap_samples": RUN_MAX_GAP_SAMPLES},
        "resample_hz": RUN_FIT_RATE_HZ,
        "files": files,
        "model": {"offset": True, "stiffness": has_x},
    }


def load_runs(paths: Sequence[str | os.PathLike[str]], *, name: str | None = None,
              overrides: dict[str, Any] | None = None, notes: list[str] | None = None) -> tuple[Node, dict[str, Any]]:
    """:func:`describe_runs`, validated like any description (the files were
    named on the command line: no directory confines them); ``overrides``
    replace top-level sections (``{"fit": {"laws": "paper"}}``); ``notes`` as
    for :func:`describe_runs`. Returns the validated node and the plain
    description."""
    from mrctl.config.dataset import validate_dataset
    from mrctl.util.schema import ConfigError

    doc = describe_runs(paths, name=name, notes=notes)
    for key, value in (overrides or {}).items():
        doc[key] = {**doc.get(key, {}), **value} if isinstance(value, dict) else value
    try:
        return validate_dataset(doc, Path.cwd(), "(run CSVs)", allow_outside=True), doc
    except ConfigError as exc:  # pragma: no cover - the description above is valid by construction
        raise IdentificationError(f"the description of the run CSVs is invalid: {exc}") from None
