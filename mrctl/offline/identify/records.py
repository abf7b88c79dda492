"""Reading measured records as a dataset description says: CSV or MATLAB .mat.

One :class:`Record` per ``files[]`` entry (or manifest row): the signals in
SI units, the time axis, the windows and levels the description gives.
Every problem is an :class:`IdentificationError` naming the file and, where
it helps, the column and line. scipy (``scipy.io.loadmat``) is needed for .mat
files only.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mrctl.offline.identify.errors import IdentificationError
from mrctl.util.files import FileProblem, MiB, not_regular, read_regular_file

__all__ = ["Record", "read_records", "read_signals", "MAX_DATA_BYTES", "MAX_MANIFEST_BYTES", "MAX_SI_MAGNITUDE"]

#: the largest data file read (CSV or .mat): hours of a fast DAQ; read whole, so bounded
MAX_DATA_BYTES = 1024 * MiB
#: the largest manifest (one line per data file)
MAX_MANIFEST_BYTES = 16 * MiB
#: the largest magnitude of a scaled signal (SI units): no damper, stroke or time comes near it;
#: beyond it the fit's arithmetic overflows
MAX_SI_MAGNITUDE = 1e12

_SIGNALS = ("time", "displacement", "velocity", "force", "input")


@dataclass
class Record:
    """One measured record in SI units (arrays of equal length)."""

    name: str
    path: str
    role: str  # "fit" or "holdout"
    t: np.ndarray
    F: np.ndarray
    x: np.ndarray | None = None
    v: np.ndarray | None = None
    u: np.ndarray | None = None
    level: float | None = None  # constant input of the whole record
    levels: list[tuple[float, float, float]] = field(default_factory=list)  # (from_s, to_s, value)
    use: list[tuple[float, float]] = field(default_factory=list)
    exclude: list[tuple[float, float]] = field(default_factory=list)
    fs: float = 0.0  # sample rate (Hz)


def _read_bytes(path: Path, max_bytes: int | None = None) -> bytes:
    """A data file's bytes: a regular file, at most ``max_bytes`` (default
    :data:`MAX_DATA_BYTES`; never /dev/zero or a FIFO)."""
    try:
        return read_regular_file(path, MAX_DATA_BYTES if max_bytes is None else max_bytes)
    except FileProblem as exc:
        raise IdentificationError(f"{path}: {exc}") from None


def _read_csv(path: Path, names: dict[str, str], delimiter: str, skip_rows: int = 0) -> dict[str, np.ndarray]:
    """The named columns of a CSV; ``skip_rows`` lines before the header are
    an instrument's preamble (``format.skip_rows``), skipped whatever they hold."""
    try:
        text = _read_bytes(path).decode("utf-8-sig")
    except UnicodeDecodeError:
        raise IdentificationError(f"{path}: not a text (UTF-8) CSV file; is it a .mat file? "
                                  "(set format.type: mat)") from None
    lines = text.splitlines()
    if skip_rows and skip_rows >= len(lines):
        raise IdentificationError(f"{path}: format.skip_rows {skip_rows} skips the whole file "
                                  f"({len(lines)} line(s))")
    k = skip_rows
    while k < len(lines) and (not lines[k].strip() or lines[k].lstrip().startswith("#")):
        k += 1
    if k == len(lines):
        raise IdentificationError(f"{path}: empty file (no header line)")
    header = [h.strip() for h in next(csv.reader(io.StringIO(lines[k]), delimiter=delimiter))]
    idx = {}
    for role, name in names.items():
        if name not in header:  # the header is not echoed: the file may not be data at all
            raise IdentificationError(f"{path}: no column {name!r} (columns.{role}) in the header (line {k + 1}, "
                                      f"{len(header)} field(s) split at {delimiter!r}); check columns and "
                                      "format.delimiter")
        idx[role] = header.index(name)
    rows = [ln for ln in lines[k + 1:] if ln.strip() and not ln.lstrip().startswith("#")]
    if len(rows) < 3:
        raise IdentificationError(f"{path}: {len(rows)} data row(s); far too short to identify from")
    cols = sorted(set(idx.values()))
    try:
        data = np.loadtxt(rows, delimiter=delimiter, dtype=float, ndmin=2, usecols=cols, comments=None)
    except ValueError:
        _first_bad(path, lines, k, idx, delimiter)
        raise IdentificationError(f"{path}: cannot parse the data rows") from None  # pragma: no cover
    return {role: data[:, cols.index(j)].copy() for role, j in idx.items()}


def _first_bad(path: Path, lines: list[str], k: int, idx: dict[str, int], delimiter: str) -> None:
    """Name the first field that is not a number (only on the error path)."""
    for n in range(k + 1, len(lines)):
        s = lines[n]
        if not s.strip() or s.lstrip().startswith("#"):
            continue
        fields = s.split(delimiter)
        for role, j in idx.items():
            if j >= len(fields):
                raise IdentificationError(f"{path}: line {n + 1} has {len(fields)} fields; column {role} is "
                                          f"field {j + 1}")
            try:
                float(fields[j])
            except ValueError:
                raise IdentificationError(f"{path}: line {n + 1}: column {role} (field {j + 1}) is not a "
                                          "number") from None


def _read_mat(path: Path, specs: dict[str, Any]) -> dict[str, np.ndarray]:
    try:
        from scipy.io import loadmat
    except ImportError:
        from mrctl.offline.identify.errors import SCIPY_MISSING, DependencyMissing

        raise DependencyMissing(SCIPY_MISSING) from None
    data = _read_bytes(path)
    if not data:
        raise IdentificationError(f"{path}: empty file; not a MATLAB .mat file")
    try:
        mat = loadmat(io.BytesIO(data))
    except NotImplementedError:
        raise IdentificationError(f"{path}: a MATLAB v7.3 (HDF5) file; save it with save(..., '-v7') or export "
                                  "a CSV") from None
    except (MemoryError, RecursionError):
        raise IdentificationError(f"{path}: not a readable MATLAB .mat file (its structure is too large "
                                  "or too deep)") from None
    except Exception as exc:  # noqa: BLE001 - scipy's MatReadError, ValueError, struct.error …: all "not a .mat"
        raise IdentificationError(f"{path}: not a readable MATLAB .mat file ({type(exc).__name__}: "
                                  f"{str(exc)[:120]}); is it a CSV? (set format.type: csv)") from None
    out = {}
    have = ", ".join(k for k in mat if not k.startswith("__"))
    for role, spec in specs.items():
        if spec.name not in mat:
            raise IdentificationError(f"{path}: no variable {spec.name!r} (columns.{role}); the file has: {have}")
        a = np.asarray(mat[spec.name])
        if not np.issubdtype(a.dtype, np.number):
            raise IdentificationError(f"{path}: variable {spec.name!r} (columns.{role}) is not numeric")
        a = a.astype(float)
        if a.ndim == 2 and min(a.shape) == 1:
            a = a.reshape(-1)
        if a.ndim == 2:
            if spec.index is None:
                raise IdentificationError(f"{path}: variable {spec.name!r} (columns.{role}) is {a.shape[0]}×"
                                          f"{a.shape[1]}: set columns.{role}.index to the column to use")
            j = int(spec.index)
            if a.shape[0] < a.shape[1]:
                a = a.T
            if j >= a.shape[1]:
                raise IdentificationError(f"{path}: columns.{role}.index {j} is out of range: {spec.name!r} has "
                                          f"{a.shape[1]} columns")
            a = a[:, j]
        elif a.ndim != 1:
            raise IdentificationError(f"{path}: variable {spec.name!r} (columns.{role}) has shape {a.shape}; "
                                      "need a vector")
        out[role] = a
    return out


def read_signals(path: str, ds: Any) -> dict[str, np.ndarray]:
    """The described columns of one file, scaled to SI units (role → array)."""
    p = Path(path)
    specs = {r: ds.columns.get(r) for r in _SIGNALS if ds.columns.get(r) is not None}
    kind = ds.format.type or ("mat" if p.suffix.lower() == ".mat" else "csv")
    if kind == "mat":
        raw = _read_mat(p, specs)
    else:
        raw = _read_csv(p, {r: s.name for r, s in specs.items()}, ds.format.delimiter,
                        int(ds.format.get("skip_rows", 0) or 0))
    n = {r: a.size for r, a in raw.items()}
    if len(set(n.values())) > 1:
        raise IdentificationError(f"{p}: the columns have different lengths: "
                                  + ", ".join(f"{r} {k}" for r, k in n.items()))
    out = {}
    for r, a in raw.items():
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise IdentificationError(f"{p}: column {specs[r].name!r} (columns.{r}) is not finite at sample "
                                      f"{bad[0]} ({bad.size} sample(s) in all); cut it out with exclude: or use:")
        with np.errstate(over="ignore", invalid="ignore"):
            si = a * specs[r].scale + specs[r].offset
            big = np.flatnonzero(~(np.abs(si) <= MAX_SI_MAGNITUDE))
        if big.size:
            raise IdentificationError(f"{p}: column {specs[r].name!r} (columns.{r}) scaled by columns.{r}.scale "
                                      f"{specs[r].scale:g} and columns.{r}.offset {specs[r].offset:g} is "
                                      f"{'not finite' if not np.isfinite(si[big[0]]) else 'beyond 1e12'} at sample "
                                      f"{big[0]}: check the scale and offset (SI value = raw · scale + offset)")
        out[r] = si
    F = out.get("force")
    if F is not None and F.size and float(np.ptp(F)) == 0.0:
        raise IdentificationError(f"{p}: column {specs['force'].name!r} (columns.force) is constant "
                                  f"({F[0]:g} N in every sample): no force to identify from; is it the right "
                                  "column?")
    return out


def _time(sig: dict[str, np.ndarray], ds: Any, p: str) -> tuple[np.ndarray, float]:
    n = sig["force"].size
    if ds.sample_rate_hz is not None:
        t0 = float(sig["time"][0]) if "time" in sig else 0.0
        return t0 + np.arange(n) / ds.sample_rate_hz, float(ds.sample_rate_hz)
    t = sig["time"]
    dt = np.diff(t)
    if np.any(dt <= 0.0):
        k = int(np.flatnonzero(dt <= 0.0)[0])
        raise IdentificationError(f"{p}: time is not strictly increasing at sample {k + 1} "
                                  f"({t[k]:g} → {t[k + 1]:g} s); if the time column is rounded, set sample_rate_hz")
    med = float(np.median(dt))
    if np.max(np.abs(dt - med)) > 0.05 * med:
        k = int(np.argmax(np.abs(dt - med)))
        raise IdentificationError(f"{p}: not uniformly sampled: step {dt[k]:.4g} s at sample {k + 1} against "
                                  f"{med:.4g} s typical (a gap or a rounded time column?); cut gaps with exclude: "
                                  "into separate windows, or set sample_rate_hz if the time is only rounded")
    return t, 1.0 / med


def read_records(ds: Any) -> list[Record]:
    """Every record of a validated dataset description (``mrctl.config.dataset``)."""
    entries: list[tuple[str, str | None, str, list, list, float | None, list]] = []
    for f in ds.files or []:
        entries.append((f.path, f.name, f.role, f.use, f.exclude, f.level,
                        [(s.from_s, s.to_s, s.value) for s in f.levels]))
    if ds.manifest is not None:
        entries += _manifest_entries(ds.manifest)
    records = []
    for path, name, role, use, exclude, level, levels in entries:
        sig = read_signals(path, ds)
        t, fs = _time(sig, ds, path)
        records.append(Record(name=name or Path(path).stem, path=path, role=role, t=t, F=sig["force"],
                              x=sig.get("displacement"), v=sig.get("velocity"), u=sig.get("input"),
                              level=level, levels=levels, use=list(use), exclude=list(exclude), fs=fs))
    names = [r.name for r in records]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise IdentificationError(f"record names must be unique; repeated: {', '.join(dup)} (set files[].name)")
    return records


def _manifest_entries(man: Any) -> list:
    p = Path(man.path)
    try:
        text = _read_bytes(p, MAX_MANIFEST_BYTES).decode("utf-8-sig")
        rows = list(csv.DictReader(io.StringIO(text, newline="")))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise IdentificationError(f"{p}: cannot read the manifest: {exc}") from None
    root = Path(man.root) if man.get("root") else None
    out = []
    for i, row in enumerate(rows, start=2):
        if man.file not in row or man.level not in row:
            raise IdentificationError(f"{p}: no column {man.file!r} or {man.level!r} (manifest.file, manifest.level)")
        name = (row[man.file] or "").strip()
        if not name:
            raise IdentificationError(f"{p}: line {i}: no file name in column {man.file!r}")
        f = (p.parent / name).resolve()
        if root is not None:
            try:
                f.relative_to(root)
            except ValueError:
                from mrctl.config.dataset import outside_message

                raise IdentificationError(f"{p}: line {i}: " + outside_message("the file", f, root)) from None
        try:
            level = float(row[man.level])
        except (TypeError, ValueError):
            raise IdentificationError(f"{p}: line {i}: level {str(row[man.level])[:24]!r} is not a "
                                      "number") from None
        if not math.isfinite(level):
            raise IdentificationError(f"{p}: line {i}: level {level!r} (column {man.level!r}) is not a finite "
                                      "number")
        kind = not_regular(f)
        if kind == "missing":
            raise IdentificationError(f"{p}: line {i}: no such file: {f}")
        if kind is not None:
            raise IdentificationError(f"{p}: line {i}: {f} is not a regular file ({kind})")
        out.append((str(f), None, "fit", [], [], level, []))
    if not out:
        raise IdentificationError(f"{p}: the manifest lists no files")
    return out
