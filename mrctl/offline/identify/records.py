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
from mrctl.util.files import FileProblem, MiB, read_regular_file

__all__ = ["Record", "read_records", "read_signals", "manifest_paths", "MAX_DATA_BYTES", "MAX_MANIFEST_BYTES", "MAX_SI_MAGNITUDE"]

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
    notes: list[str] = field(default_factory=list)  # what reading did to it (warnings: a torn line, filled gaps)

    def kept(self) -> np.ndarray:
        """The samples used: inside a ``use`` window (default all), outside every ``exclude`` window."""
        t = self.t
        m = np.zeros(t.size, bool) if self.use else np.ones(t.size, bool)
        for a, b in self.use:
            m |= (t >= a) & (t <= b)
        for a, b in self.exclude:
            m &= ~((t >= a) & (t <= b))
        return m


def _read_bytes(path: Path, max_bytes: int | None = None) -> bytes:
    """A data file's bytes: a regular file, at most ``max_bytes`` (default
    :data:`MAX_DATA_BYTES`; never /dev/zero or a FIFO)."""
    try:
        return read_regular_file(path, MAX_DATA_BYTES if max_bytes is None else max_bytes)
    except FileProblem as exc:
        raise IdentificationError(f"{path}: {exc}") from None


def _read_csv(path: Path, names: dict[str, str], delimiter: str, skip_rows: int = 0,
              notes: list[str] | None = None) -> dict[str, np.ndarray]:
    """The named columns of a CSV; ``skip_rows`` lines before the header are
    an instrument's preamble (``format.skip_rows``), skipped whatever they hold.
    A last line with too few fields and no line end is a torn write: dropped,
    said in ``notes``."""
    notes = [] if notes is None else notes
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
    if rows and len(rows[-1].split(delimiter)) < len(header) and not text.endswith(("\n", "\r")):
        rows.pop()  # a torn last line (a logger killed mid-write, a full disk): the data before it stands
        notes.append("its last line was cut off mid-write; dropped")
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


def read_signals(path: str, ds: Any, notes: list[str] | None = None) -> dict[str, np.ndarray]:
    """The described columns of one file, scaled to SI units (role → array),
    as recorded (:func:`read_records` fills gaps, then undoes delays)."""
    p = Path(path)
    specs = {r: ds.columns.get(r) for r in _SIGNALS if ds.columns.get(r) is not None}
    kind = ds.format.type or ("mat" if p.suffix.lower() == ".mat" else "csv")
    if kind == "mat":
        raw = _read_mat(p, specs)
    else:
        raw = _read_csv(p, {r: s.name for r, s in specs.items()}, ds.format.delimiter,
                        int(ds.format.get("skip_rows", 0) or 0), notes)
    n = {r: a.size for r, a in raw.items()}
    if len(set(n.values())) > 1:
        raise IdentificationError(f"{p}: the columns have different lengths: "
                                  + ", ".join(f"{r} {k}" for r, k in n.items()))
    out = {}
    for r, a in raw.items():
        with np.errstate(over="ignore", invalid="ignore"):
            si = a * specs[r].scale + specs[r].offset
            big = np.flatnonzero(np.isfinite(a) & ~(np.abs(si) <= MAX_SI_MAGNITUDE))
        if big.size:
            raise IdentificationError(f"{p}: column {specs[r].name!r} (columns.{r}) scaled by columns.{r}.scale "
                                      f"{specs[r].scale:g} and columns.{r}.offset {specs[r].offset:g} is "
                                      f"{'not finite' if not np.isfinite(si[big[0]]) else 'beyond 1e12'} at sample "
                                      f"{big[0]}: check the scale and offset (SI value = raw · scale + offset)")
        out[r] = si
    return out


def _fill_gaps(sig: dict[str, np.ndarray], max_gap: int, notes: list[str]) -> None:
    """Samples missing from a uniform time axis (a logger's skipped ticks), at
    most ``max_gap`` in a row, put back by linear interpolation of every
    signal (in place). Any other irregularity leaves the record as it is,
    for :func:`_time` to refuse with its message."""
    t = sig["time"]
    dt = np.diff(t)
    if dt.size == 0 or not np.isfinite(t).all() or np.any(dt <= 0.0):
        return
    med = float(np.median(dt))
    steps = np.rint(dt / med).astype(int)
    if not np.any(steps > 1) or np.any(steps > max_gap + 1) or np.any(np.abs(dt - steps * med) > 0.05 * med):
        return
    k = np.concatenate(([0], np.cumsum(steps)))
    full = np.arange(int(k[-1]) + 1, dtype=float)
    missing = np.ones(full.size, bool)
    missing[k] = False
    for r, a in sig.items():  # each signal from its finite samples: a NaN row stays NaN, and fills nothing
        out = np.full(full.size, np.nan)
        out[k] = a
        fin = np.isfinite(a)
        if fin.any():
            out[missing] = np.interp(full[missing], k[fin], a[fin])
        sig[r] = out
    notes.append(f"{int((steps - 1).sum())} missing sample(s) in {int(np.count_nonzero(steps > 1))} gap(s) "
                 "filled by linear interpolation (format.max_gap_samples)")


def _undo_delays(sig: dict[str, np.ndarray], ds: Any, p: str) -> dict[str, np.ndarray]:
    """Each delayed signal (``columns.<signal>.delay_samples`` = n: sample k + n
    measured the instant of sample k) moved back to the sample it measured, on
    the gap-filled sample grid; the record loses the last n samples."""
    delay = {r: int(ds.columns.get(r).get("delay_samples", 0) or 0) for r in sig}
    most = max(delay.values(), default=0)
    if not most:
        return sig
    n0 = next(iter(sig.values())).size
    if n0 - most < 3:
        raise IdentificationError(f"{p}: {n0} sample(s), too few for a delay of {most} sample(s) "
                                  "(columns.<signal>.delay_samples)")
    return {r: a[delay[r]:n0 - most + delay[r]] for r, a in sig.items()}


def _time(sig: dict[str, np.ndarray], ds: Any, p: str) -> tuple[np.ndarray, float]:
    n = sig["force"].size
    if ds.sample_rate_hz is not None:
        t0 = float(sig["time"][0]) if "time" in sig else 0.0
        return t0 + np.arange(n) / ds.sample_rate_hz, float(ds.sample_rate_hz)
    t = sig["time"]
    if not np.isfinite(t).all():
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise IdentificationError(f"{p}: the time column is not finite at sample {k}; set sample_rate_hz to "
                                  "rebuild it")
    dt = np.diff(t)
    if np.any(dt <= 0.0):
        k = int(np.flatnonzero(dt <= 0.0)[0])
        raise IdentificationError(f"{p}: time is not strictly increasing at sample {k + 1} "
                                  f"({t[k]:g} → {t[k + 1]:g} s); if the time column is rounded, set sample_rate_hz")
    med = float(np.median(dt))
    if np.max(np.abs(dt - med)) > 0.05 * med:
        k = int(np.argmax(np.abs(dt - med)))
        raise IdentificationError(f"{p}: not uniformly sampled: step {dt[k]:.4g} s at sample {k + 1} against "
                                  f"{med:.4g} s typical (a gap or a rounded time column?); fill gaps of a few "
                                  "samples with format.max_gap_samples, or set sample_rate_hz if the time is only "
                                  "rounded")
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
    max_gap = int(ds.format.get("max_gap_samples", 0) or 0)
    for path, name, role, use, exclude, level, levels in entries:
        notes: list[str] = []
        sig = read_signals(path, ds, notes)
        if max_gap and "time" in sig and ds.sample_rate_hz is None:
            _fill_gaps(sig, max_gap, notes)
        sig = _undo_delays(sig, ds, path)
        t, fs = _time(sig, ds, path)
        rec = Record(name=name or Path(path).stem, path=path, role=role, t=t, F=sig["force"],
                     x=sig.get("displacement"), v=sig.get("velocity"), u=sig.get("input"),
                     level=level, levels=levels, use=list(use), exclude=list(exclude), fs=fs, notes=notes)
        kept = rec.kept()
        for r, a in sig.items():  # a gap in the data is fine where the windows leave it out, nowhere else
            bad = np.flatnonzero(kept & ~np.isfinite(a))
            if bad.size:
                raise IdentificationError(
                    f"{path}: column {ds.columns.get(r).name!r} (columns.{r}) is not finite at sample {bad[0]} (t = "
                    f"{t[bad[0]]:.6g} s; {bad.size} sample(s) in the used windows); cut it out with exclude: or use:")
        F = sig["force"][kept]
        if F.size and float(np.ptp(F)) == 0.0:
            raise IdentificationError(f"{path}: column {ds.columns.get('force').name!r} (columns.force) is constant "
                                      f"({F[0]:g} N in every sample): no force to identify from; is it the right "
                                      "column?")
        records.append(rec)
    names = [r.name for r in records]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise IdentificationError(f"record names must be unique; repeated: {', '.join(dup)} (set files[].name)")
    return records


def manifest_paths(man: Any) -> list[str]:
    """The data files a manifest lists (checked as :func:`read_records` does)."""
    return [e[0] for e in _manifest_entries(man)]


def _manifest_entries(man: Any) -> list:
    p = Path(man.path)
    try:
        text = _read_bytes(p, MAX_MANIFEST_BYTES).decode("utf-8-sig")
        rows = list(csv.DictReader(io.StringIO(text, newline="")))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise IdentificationError(f"{p}: cannot read the manifest: {exc}") from None
    from mrctl.config.dataset import data_fence

    fence = data_fence(man.get("root"))  # the description's, as for its files
    out = []
    for i, row in enumerate(rows, start=2):
        if man.file not in row or man.level not in row:
            raise IdentificationError(f"{p}: no column {man.file!r} or {man.level!r} (manifest.file, manifest.level)")
        name = (row[man.file] or "").strip()
        if not name:
            raise IdentificationError(f"{p}: line {i}: no file name in column {man.file!r}")
        full, err = fence.admit(name, p.parent, f"line {i}")
        if full is None:
            raise IdentificationError(f"{p}: {err}")
        f = full.resolve()
        try:
            level = float(row[man.level])
        except (TypeError, ValueError):
            raise IdentificationError(f"{p}: line {i}: the level (column {man.level!r}) is not a "
                                      "number") from None
        if not math.isfinite(level):
            raise IdentificationError(f"{p}: line {i}: level {level!r} (column {man.level!r}) is not a finite "
                                      "number")
        out.append((str(f), None, "fit", [], [], level, []))
    if not out:
        raise IdentificationError(f"{p}: the manifest lists no files")
    return out
