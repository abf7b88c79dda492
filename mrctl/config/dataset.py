"""The dataset description: where measured data is and what it means.

``mrctl identify --dataset DATA.yaml`` reads one of these instead of mrctl's
own run CSVs: a lab's records with any column names (CSV) or variables
(MATLAB ``.mat``), any units, windows to use or skip, the input level of
constant-input tests, which records or how much of each to hold out. The
schema is validated like an experiment file (every error with its key path,
all at once) and generates the reference table in docs/identification.md
(``python -m mrctl.config.dataset``). Relative paths resolve against
``data_dir`` (itself relative to the dataset file), or the dataset file's
directory; ``mrctl identify --data-dir DIR`` overrides both, so one
description serves data kept anywhere. Data paths must stay under the
dataset file's directory (or the ``--data-dir`` given) unless
``allow_outside``: a description from elsewhere cannot make identify read
``/etc/shadow``, not even through its own ``data_dir`` key. Reading the data
is :mod:`mrctl.offline.identify`'s.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from mrctl.config.params import INPUT_KINDS
from mrctl.util.files import Fence, fence_root, not_regular
from mrctl.util.schema import Bool, ConfigError, Custom, Node, Num, Section, Str, check_num, load_yaml, validate_fields
from mrctl.util.schema import schema_markdown as _markdown

__all__ = ["DATASET_VERSION", "PROTOCOLS", "COLUMN_ROLES", "MAX_RATE_HZ", "dataset_schema", "validate_dataset",
           "load_dataset", "data_fence", "dataset_markdown"]

DATASET_VERSION = 1
PROTOCOLS = ("constant_input", "broadband")
#: the columns a record may give, and the SI unit each is scaled to
COLUMN_ROLES = {"time": "s", "displacement": "m", "velocity": "m/s", "force": "N", "input": "A or V"}
ROLES = ("fit", "holdout")
#: the highest sample rate a description may give (Hz): far above any DAQ, far below overflow
MAX_RATE_HZ = 1e7


def _column(value: Any, path: str) -> tuple[Any, list[str]]:
    """A column: its name, or {name, scale, offset, index, delay_samples}; null = not recorded."""
    if value is None:
        return None, []
    if isinstance(value, str):
        value = {"name": value}
    node, errors = validate_fields({
        "name": Str(doc="column header (CSV) or variable (.mat)"),
        "scale": Num(default=1.0, doc="multiply by this to get SI units"),
        "offset": Num(default=0.0, doc="then add this (SI units)"),
        "index": Num(default=None, optional=True, integer=True, min=0,
                     doc="column of a 2-D .mat variable (0-based)"),
        "delay_samples": Num(default=0, integer=True, min=0, max=100000,
                             doc="this signal is that many samples late (sample k+n measured the instant of "
                                 "sample k, e.g. a load cell read one tick after x and v): moved back, the "
                                 "record shortened by n"),
    }, value, path)
    if not errors and node.scale == 0.0:
        errors.append(f"{path}.scale: must not be 0")
    return (node if not errors else None), errors


def _windows(value: Any, path: str) -> tuple[Any, list[str]]:
    """A list of [t0, t1] windows (s, record time), t0 < t1."""
    if value is None:
        return [], []
    if not isinstance(value, list):
        return None, [f"{path}: must be a list of [t0, t1] windows (s)"]
    out, errors = [], []
    for i, w in enumerate(value):
        p = f"{path}[{i}]"
        if not isinstance(w, list) or len(w) != 2:
            errors.append(f"{p}: must be [t0, t1] (s), got {w!r}")
            continue
        a, e1 = check_num(Num(), w[0], f"{p}[0]")
        b, e2 = check_num(Num(), w[1], f"{p}[1]")
        if e1 or e2:
            errors += e1 + e2
        elif not a < b:
            errors.append(f"{p}: need t0 < t1, got {w!r}")
        else:
            out.append((a, b))
    return out, errors


def _levels(value: Any, path: str) -> tuple[Any, list[str]]:
    """Per-segment input levels: [{from_s, to_s, value}], non-overlapping."""
    if value is None:
        return [], []
    if not isinstance(value, list) or not value:
        return None, [f"{path}: must be a non-empty list of {{from_s, to_s, value}}"]
    out, errors = [], []
    for i, seg in enumerate(value):
        node, errs = validate_fields({"from_s": Num(doc="segment start (s)"), "to_s": Num(doc="segment end (s)"),
                                      "value": Num(doc="constant input (A or V)")}, seg, f"{path}[{i}]")
        if not errs and not node.from_s < node.to_s:
            errs.append(f"{path}[{i}]: need from_s < to_s, got {node.from_s:g} and {node.to_s:g}")
        errors += errs
        if not errs:
            out.append(node)
    for i in range(1, len(out)):
        if out[i].from_s < out[i - 1].to_s:
            errors.append(f"{path}[{i}]: overlaps the segment before it (from_s {out[i].from_s:g} < "
                          f"{out[i - 1].to_s:g}); list segments in time order")
    return out, errors


def _file_entry_fields() -> dict[str, Any]:
    return {
        "path": Str(doc="data file (.csv or .mat), relative to data_dir (default the dataset file's directory)"),
        "name": Str(default=None, optional=True, doc="record name in tables and the JSON (default: the file name)"),
        "role": Str(default="fit", choices=ROLES,
                    doc="fit: fitted (its held-out part excepted); holdout: never fitted, only predicted"),
        "use": Custom(_windows, default=None, doc="[[t0, t1], ...] windows to use (s); default the whole record"),
        "exclude": Custom(_windows, default=None, doc="[[t0, t1], ...] windows to drop (s)"),
        "level": Num(default=None, optional=True, doc="constant_input: the input level of the whole file (A or V)"),
        "levels": Custom(_levels, default=None,
                         doc="constant_input: [{from_s, to_s, value}] input level per segment"),
    }


def _files_check(base_dir: Path, fence: Fence):
    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if value is None:
            return [], []
        if not isinstance(value, list):
            return None, [f"{path}: must be a list of records ({{path: ..., ...}} or a path)"]
        out, errors = [], []
        for i, entry in enumerate(value):
            p = f"{path}[{i}]"
            if isinstance(entry, str):
                entry = {"path": entry}
            node, errs = validate_fields(_file_entry_fields(), entry, p)
            if not errs:
                full, errs = _resolve(node.path, base_dir, p, fence)
                node = node.replace(path=full) if full else node
                if node.level is not None and node.levels:
                    errs.append(f"{p}: give level (whole file) or levels (per segment), not both")
            errors += errs
            if not errs:
                out.append(node)
        return out, errors

    return check


def data_fence(root: str | Path | None) -> Fence:
    """Where a description's records must lie: under ``root`` (resolved;
    None: anywhere, ``--allow-outside-paths``). Files and manifest rows are
    held to it by the one check, :meth:`Fence.admit`."""
    return Fence(None if root is None else Path(root).expanduser().resolve(),
                 where="the directory data must stay in",
                 hint="give --data-dir DIR (its directory) or --allow-outside-paths if you trust this description")


def _resolve(value: str, base_dir: Path, path: str, fence: Fence) -> tuple[str | None, list[str]]:
    """``value`` resolved against base_dir, or an error naming the missing
    file, one that is not a regular file, or one outside the fence (checked
    first: nothing is said about a file outside)."""
    full, err = fence.admit(value, base_dir, f"{path}.path")
    if full is None:
        return None, [str(err) + (": the data is not part of mrctl; check the path relative to the dataset file, "
                                  "or where the data is stored" if "no such directory" in str(err) else "")]
    return str(full.resolve()), []


def _manifest_check(base_dir: Path, fence: Fence):
    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if value is None:
            return None, []
        node, errors = validate_fields({
            "path": Str(doc="CSV listing the files, relative to data_dir (default the dataset file's directory)"),
            "file": Str(default="file", doc="its column with the data file names (relative to the manifest)"),
            "level": Str(doc="its column with each file's constant input level"),
        }, value, path)
        if not errors:
            full, errors = _resolve(node.path, base_dir, path, fence)
            if full:  # its rows are held to the same fence (mrctl.offline.identify.records)
                node = Node({**node.to_dict(), "path": full, "root": fence.to_text()})
        return (node if not errors else None), errors

    return check


def _delimiter(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return ",", []
    if not isinstance(value, str) or len(value) != 1 or value in "\r\n\"":
        return None, [f"{path}: must be one character (',' ';' '\\t' ...), got {value!r}"[:200]]
    return value, []


def dataset_schema(base_dir: Path, root: Path | None = None) -> dict[str, Any]:
    """The dataset schema; relative paths resolve against ``base_dir`` and
    must stay under ``root`` (None: anywhere)."""
    fence = data_fence(root)
    return {
        "version": Num(integer=True, min=DATASET_VERSION, max=DATASET_VERSION, doc="format version (1)"),
        "name": Str(default=None, optional=True, doc="dataset name (tables, figure titles)"),
        "description": Str(default=None, optional=True, doc="free text, copied into the JSON summary"),
        "data_dir": Str(default=None, optional=True,
                        doc="directory the records' relative paths (files, manifest) resolve against, itself "
                            "relative to this file; null = this file's directory; mrctl identify --data-dir "
                            "overrides it"),
        "protocol": Str(choices=PROTOCOLS, doc="constant_input: sine (or any periodic) strokes at constant input "
                                               "levels; broadband: any motion, any input (switched, random)"),
        "input": Str(default="current", choices=tuple(INPUT_KINDS),
                     doc="what the input is: a coil current (A) or a driver command voltage (V); the fitted set "
                         "records it and only a driver that takes the same will run it"),
        "columns": Section({
            "time": Custom(_column, default=None, doc="time (s); null = rebuild from sample_rate_hz"),
            "displacement": Custom(_column, default=None, doc="relative displacement (m after scale)"),
            "velocity": Custom(_column, default=None,
                               doc="relative velocity (m/s); null = differentiate displacement (Savitzky-Golay)"),
            "force": Custom(_column, doc="damper force (N)"),
            "input": Custom(_column, default=None,
                            doc="the drive input (A or V, see input); constant_input may give levels instead"),
        }, optional=False, doc="column (CSV header) or variable (.mat) of each signal: a name or {name, scale, "
                               "offset, index, delay_samples}; SI value = raw · scale + offset"),
        "format": Section({
            "type": Str(default=None, optional=True, choices=("csv", "mat"),
                        doc="file format; null = by extension (.mat is MATLAB, anything else CSV)"),
            "delimiter": Custom(_delimiter, default=",", doc="CSV field separator (one character)"),
            "skip_rows": Num(default=0, integer=True, min=0, max=100000,
                             doc="CSV: lines before the header to skip (an instrument's preamble)"),
            "max_gap_samples": Num(default=0, integer=True, min=0, max=1000,
                                   doc="missing samples in a row (a logger's skipped ticks) filled by linear "
                                       "interpolation; 0 = a gap in the time column is an error"),
        }, doc="how to read the files"),
        "sample_rate_hz": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=MAX_RATE_HZ,
                              doc="sample rate; when set, time is rebuilt as t0 + k/rate (for rounded or missing "
                                  "time columns)"),
        "resample_hz": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=MAX_RATE_HZ,
                           doc="fit at this rate (anti-aliased decimation of faster records); null = the lowest "
                               "integer division of the rate at or above max(20 × motion_band_hz, 500 Hz)"),
        "motion_band_hz": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=MAX_RATE_HZ,
                              doc="highest frequency of the motion; sets the resample rate and the velocity "
                                  "differentiator's window; null = estimated from the displacement or velocity"),
        "files": Custom(_files_check(base_dir, fence), default=None,
                        doc="records: [{path, name, role, use, exclude, level, levels}] (see below)"),
        "manifest": Custom(_manifest_check(base_dir, fence), default=None,
                           doc="constant_input: {path, file, level}: a CSV listing files and their levels"),
        "holdout": Section({
            "fraction": Num(default=None, optional=True, min=0.0, max=0.9,
                            doc="held out of the fit: the last fraction of each fit record (broadband, default "
                                "0.3) or of each constant-input segment's steady cycles (default 0.5); 0 = none"),
        }, doc="validation on data the fit never saw; records with role: holdout are held out whole"),
        "model": Section({
            "offset": Bool(default=True, doc="fit a constant force offset F_offset"),
            "stiffness": Bool(default=True, doc="fit a stiffness k_x on displacement (needs displacement)"),
            "lag": Bool(default=True,
                        doc="broadband: fit the first-order input lag tau_input; false applies the input at once"),
            "inertia": Bool(default=False,
                            doc="broadband: fit a moving mass m between load cell and piston (force = damper + "
                                "m·a); a measurement term, reported, not part of the parameter set"),
            "lag_fall": Bool(default=False,
                             doc="broadband: fit the lag of a falling input apart from the rising one "
                                 "(tau_input_fall; needs lag)"),
            "sigma1_v": Bool(default=False,
                             doc="broadband: fit sigma1(v) = sigma1·exp(-(v/vd)²), bristle damping that fades "
                                 "in sliding (sigma1_vd)"),
            "hysteresis": Bool(default=False,
                               doc="fit the hysteretic (Dahl) stiffness, a stiffness per direction of motion "
                                   "(k_hys_pos, k_hys_neg, x_hys)"),
        }, doc="terms around the LuGre laws (docs/identification.md, Model terms)"),
        "fit": Section({
            "starts": Num(default=3, integer=True, min=1, max=20,
                          doc="broadband: optimiser starts (input lags spread over 2-25 ms)"),
            "max_nfev": Num(default=60, integer=True, min=5, max=10000,
                            doc="broadband: residual evaluations per start"),
            "steady_tolerance": Num(default=0.05, min=0.005, max=0.5,
                                    doc="constant_input: a cycle is steady if its stroke is within this "
                                        "fraction of the segment's steady stroke"),
            "min_cycles": Num(default=2, integer=True, min=2, max=1000,
                              doc="constant_input: steady cycles a segment needs to be used"),
            "laws": Str(default="auto", choices=("auto", "paper", "table"),
                        doc="constant_input: the written laws: paper (6)-(11), table (per-level values "
                            "interpolated piecewise linearly), auto = whichever predicts a level left out of the "
                            "fit better (each interior level in turn); mrctl identify --fit-laws overrides it"),
        }, doc="fit settings"),
    }


def _cross_checks(node: Node) -> list[str]:
    errors: list[str] = []
    cols = node.columns
    if cols.get("displacement") is None and cols.get("velocity") is None:
        errors.append("columns: need displacement or velocity (velocity is differentiated from displacement)")
    if cols.get("time") is None and node.sample_rate_hz is None:
        errors.append("columns.time: no time column; give one or set sample_rate_hz")
    files = node.files or []
    if not files and node.manifest is None:
        errors.append("files: no records (list files, or give a manifest for constant_input)")
    if node.protocol == "broadband":
        if cols.get("input") is None:
            errors.append("columns.input: broadband identification needs the input column")
        if node.manifest is not None:
            errors.append("manifest: only for constant_input (it gives per-file levels)")
        if node.fit.laws == "table":
            errors.append("fit.laws: table is for constant_input (a table of per-level values); a broadband "
                          "fit's laws are the paper's (6)-(11)")
        for i, f in enumerate(files):
            if f.level is not None or f.levels:
                errors.append(f"files[{i}]: level/levels are for constant_input; broadband reads columns.input")
    else:
        for i, f in enumerate(files):
            if f.level is None and not f.levels and cols.get("input") is None:
                errors.append(f"files[{i}]: no input level: give level, levels, or columns.input")
    errors += [f"model.{k}: broadband only (fitted from broadband or switched-input records); set model.{k}: false"
               for k in ("lag_fall", "sigma1_v") if node.protocol == "constant_input" and node.model.get(k)]
    if node.model.get("lag_fall") and not node.model.lag:
        errors.append("model.lag_fall: needs model.lag (the falling lag is the rising one's other half)")
    if node.protocol == "constant_input" and node.model.inertia:
        errors.append("model.inertia: not identifiable from constant_input records (a steady sine's m·a is "
                      "in phase with the stiffness k_x·x); set model.inertia: false, or fit broadband records")
    if node.model.stiffness and cols.get("displacement") is None:
        errors.append("model.stiffness: needs columns.displacement (or set model.stiffness: 0)")
    names = [f.name or Path(f.path).stem for f in files]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        errors.append(f"files: record names must be unique; repeated: {', '.join(dup)} (set name:)")
    frac = node.holdout.fraction
    if files and all(f.role == "holdout" for f in files) and node.manifest is None:
        errors.append("files: every record has role: holdout; at least one must be fitted")
    if frac is not None and not math.isfinite(frac):  # pragma: no cover - check_num refuses it
        errors.append("holdout.fraction: must be finite")
    return errors


def validate_dataset(data: Any, base_dir: Path, source: str | None = None, *, data_dir: str | Path | None = None,
                     allow_outside: bool = False) -> Node:
    """Validate a parsed dataset description; raises ConfigError listing every problem.
    Data paths must lie under ``data_dir`` (default ``base_dir``'s folder,
    :func:`mrctl.util.files.fence_root`) unless ``allow_outside``."""
    if not isinstance(data, dict):
        raise ConfigError([f"dataset: must be a mapping, got {type(data).__name__}"], source)
    root = None if allow_outside else (Path(data_dir) if data_dir is not None else fence_root(base_dir))
    node, errors = validate_fields(dataset_schema(base_dir, root), data, "")
    if not errors:
        errors = _cross_checks(node)
    if errors:
        raise ConfigError(errors, source)
    return node


def data_base_dir(path: Path, data: Any, data_dir: str | Path | None = None) -> Path:
    """Where the records of the description at ``path`` are: ``data_dir``
    (``--data-dir``, relative to the current directory), else its
    ``data_dir:`` key (relative to the description), else its directory.
    ConfigError naming the source if that is not a directory."""
    if data_dir is not None:
        base, what = Path(data_dir).expanduser(), "--data-dir"
    elif isinstance(data, dict) and isinstance(data.get("data_dir"), str):
        base, what = path.parent / Path(data["data_dir"]).expanduser(), "data_dir"
    else:
        return path.parent
    if not base.is_dir():
        raise ConfigError([f"{what}: {base}: no such directory"], str(path))
    return base


def load_dataset(path: str | Path, data_dir: str | Path | None = None, *, allow_outside: bool = False) -> Node:
    """Load and validate a dataset description (YAML); its records are
    looked for in :func:`data_base_dir` and must lie under ``data_dir``
    (``--data-dir``) or else the description's directory, unless
    ``allow_outside``."""
    p = Path(path)
    data = load_yaml(p)
    base = data_base_dir(p, data, data_dir)
    root = Path(data_dir).expanduser() if data_dir is not None else fence_root(p.parent)
    return validate_dataset(data, base, str(p), data_dir=root, allow_outside=allow_outside)


def dataset_markdown() -> str:
    """The dataset schema as markdown tables (docs/identification.md's generated part)."""
    entry = {f"files[].{k}": v for k, v in _file_entry_fields().items()}
    col = {"columns.<signal>.name": Str(doc="column header (CSV) or variable (.mat)"),
           "columns.<signal>.scale": Num(default=1.0, doc="multiply by this to get SI units"),
           "columns.<signal>.offset": Num(default=0.0, doc="then add this (SI units)"),
           "columns.<signal>.index": Num(default=None, optional=True, integer=True, min=0,
                                         doc="column of a 2-D .mat variable (0-based)"),
           "columns.<signal>.delay_samples": Num(default=0, integer=True, min=0, max=100000,
                                                 doc="the signal is n samples late: moved back, the record "
                                                     "shortened by n")}
    return "\n".join([_markdown(dataset_schema(Path("."))), "### One record (`files[]`)", "", _markdown(entry),
                      "### One column (`columns.<signal>`: a name, or this mapping)", "", _markdown(col)])


if __name__ == "__main__":  # python -m mrctl.config.dataset: regenerate docs/identification.md's table
    from mrctl.util.gendoc import regenerate

    _doc = Path(__file__).resolve().parents[2] / "docs" / "identification.md"
    regenerate(_doc, "<!-- BEGIN GENERATED: mrctl.config.dataset.dataset_markdown -->", "<!-- END GENERATED -->",
               dataset_markdown())
