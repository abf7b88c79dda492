"""What identification returns, and how it is written and shown.

Whatever the source (a dataset description, or mrctl's run CSVs described
by :mod:`.runs`), :class:`IdentificationResult` holds the fitted set, the held-out scores and the
plotting data; :func:`write_result` writes the parameters YAML
(``mrctl.config.load_params_file`` reads it: the set, ``input``,
``input_range``, and a ``fit:`` block) and the JSON summary beside it
(``PARAMS.json``: settings, the ``holdout`` list of ``{record, level,
nrmse}``, per-level or per-record figures); :func:`format_summary`
is what ``mrctl identify`` prints.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mrctl.model.params import LuGreParams
from mrctl.offline.identify.errors import IdentificationError

__all__ = ["Score", "Trace", "IdentificationResult", "write_result", "result_bytes", "format_summary",
           "json_path"]


@dataclass
class Score:
    """Force NRMSE (RMSE / peak-to-peak of the measured force) of one record at one level."""

    record: str
    level: float | None  # constant-input level; None for a broadband record
    nrmse: float
    samples: int
    nrmse_laws: float | None = None  # with the written set's laws (constant input)
    part: str = "holdout"  # "holdout" or "fit"
    nrmse_paper: float | None = None  # with the paper's laws (6)-(11) (constant input)
    nrmse_table: float | None = None  # with laws: table (constant input, >= 2 levels)
    #: the test condition (constant input): the steady stroke, peak to peak (m), and the frequency (Hz)
    #: of the scored cycles (the median over the record's segments at the level)
    stroke_m: float | None = None
    frequency_hz: float | None = None

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"record": self.record, "level": _r(self.level) if self.level is not None else None,
                             "nrmse": _r(self.nrmse, 5), "samples": self.samples}
        for key in ("stroke_m", "frequency_hz"):
            if getattr(self, key) is not None:
                d[key] = _r(getattr(self, key), 5)
        for key in ("nrmse_laws", "nrmse_paper", "nrmse_table"):
            if getattr(self, key) is not None:
                d[key] = _r(getattr(self, key), 5)
        return d


@dataclass
class Trace:
    """Measured and predicted force of one record's held-out (or fitted) part, for the figure."""

    record: str
    level: float | None
    t: np.ndarray
    v: np.ndarray
    F_meas: np.ndarray
    F_pred: np.ndarray
    part: str = "holdout"


@dataclass
class IdentificationResult:
    """The fitted set and how good it is on data the fit never saw."""

    name: str
    source: str
    protocol: str
    input: str  # "current" | "voltage"
    unit: str  # "A" | "V"
    params: LuGreParams
    input_range: tuple[float, float]
    holdout: list[Score]
    train: list[Score]
    settings: dict[str, Any]
    details: dict[str, Any]  # per level (constant input) or the broadband fit
    traces: list[Trace] = field(default_factory=list, repr=False)
    warnings: list[str] = field(default_factory=list)
    time_s: float = 0.0
    inertia_kg: float = 0.0

    @property
    def tau_s(self) -> float:
        return self.params.tau_input


def nrmse(meas: np.ndarray, pred: np.ndarray) -> float:
    """RMS(pred − meas) over the peak-to-peak of meas (NaN where it is flat)."""
    ptp = float(np.ptp(meas)) if meas.size else 0.0
    return float(np.sqrt(np.mean((pred - meas) ** 2)) / ptp) if ptp > 0 else float("nan")


def _r(x: float | None, digits: int = 6) -> Any:
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x):
        return None
    return float(f"{x:.{digits}g}")


def _compact_dumper():
    import yaml

    class Dumper(yaml.SafeDumper):
        """Flow style for lists and mappings of scalars: one line per Θ, per matrix row."""

    def _flat(items) -> bool:
        return all(isinstance(x, (int, float, str, bool)) or x is None for x in items)

    def rep_list(d, data):
        return d.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=_flat(data) and len(data) > 0)

    def rep_dict(d, data):
        flat = _flat(data.values()) and len(data) <= 8 and all(not isinstance(v, str) or len(v) < 20
                                                                for v in data.values())
        return d.represent_mapping("tag:yaml.org,2002:map", data.items(), flow_style=flat and len(data) > 0)

    Dumper.add_representer(list, rep_list)
    Dumper.add_representer(dict, rep_dict)
    return Dumper


def json_path(params_path: str | Path) -> Path:
    """``PARAMS.yaml`` → ``PARAMS.json`` (beside it)."""
    return Path(params_path).with_suffix(".json")


def _plain(x: Any) -> Any:
    """``x`` for JSON: non-finite floats as null, numpy scalars and tuples as plain types."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def summary_dict(res: IdentificationResult) -> dict[str, Any]:
    from mrctl import __version__

    p = res.params
    return {
        "mrctl_version": __version__,
        "dataset": res.source,
        "name": res.name,
        "protocol": res.protocol,
        "input": res.input,
        "input_unit": res.unit,
        "input_range": [_r(res.input_range[0]), _r(res.input_range[1])],
        "nrmse_definition": "RMS(F_meas - F_model) / peak-to-peak(F_meas) over the record's held-out samples",
        "holdout": [s.as_dict() for s in res.holdout],
        "fit_scores": [s.as_dict() for s in res.train],
        "tau_input_s": _r(p.tau_input),
        "F_offset_N": _r(p.F_offset),
        "k_x_N_per_m": _r(p.k_x),
        "inertia_kg": _r(res.inertia_kg),
        "parameters": {k: _r(v) for k, v in p.as_dict().items() if k not in ("laws", "table")},
        "laws": p.laws,
        "laws_choice": _plain(res.details.get("laws_choice")),
        "settings": _plain(res.settings),
        "details": _plain(res.details),
        "warnings": list(res.warnings),
        "time_s": _r(res.time_s, 4),
    }


def result_bytes(res: IdentificationResult, out: str | Path) -> list[tuple[Path, bytes]]:
    """The parameters YAML for ``out`` and the JSON summary beside it, as
    ``[(path, bytes), ...]`` for :func:`mrctl.runlog.files.write_outputs`."""
    import yaml

    summary = summary_dict(res)
    p = res.params
    levels = f"{res.input_range[0]:g}–{res.input_range[1]:g} {res.unit}"
    doc: dict[str, Any] = {
        "version": 1,
        "description": f"LuGre parameters identified by mrctl from the dataset {res.name} ({res.protocol}, "
                       f"{res.input} input {levels})",
        "source": res.source,
        "input": res.input,
        "input_range": [float(res.input_range[0]), float(res.input_range[1])],
    }
    doc.update({k: float(v) for k, v in p.as_dict().items() if k not in ("laws", "table")})  # the optional terms when on
    if p.table is not None:  # the written laws: the per-level table (the 13 constants stay, for the inverse laws)
        doc["laws"] = "table"
        doc["table"] = {k: [_r(x, 8) for x in col] for k, col in p.table.as_dict().items()}
    doc["fit"] = {
        "summary": json_path(out).name,
        "protocol": res.protocol,
        "laws": summary["laws_choice"],
        "holdout": summary["holdout"],
        "tau_input_s": summary["tau_input_s"],
        "inertia_kg": summary["inertia_kg"],
        "warnings": summary["warnings"],
    }
    out = Path(out)
    text = io.StringIO()
    laws = "a table of per-level values" if p.table is not None else "laws (6)-(11)"
    text.write(f"# mrctl identify: LuGre parameters, {laws} in the input ({res.unit}); SI units\n")
    yaml.dump(doc, text, Dumper=_compact_dumper(), sort_keys=False, allow_unicode=True, width=120)
    return [(out, text.getvalue().encode("utf-8")),
            (json_path(out), (json.dumps(summary, indent=2, allow_nan=False) + "\n").encode("utf-8"))]


def write_result(res: IdentificationResult, out: str | Path, force: bool = False) -> Path:
    """The parameters YAML at ``out`` and the JSON summary beside it, both or
    neither (an existing file refused unless ``force``); returns the JSON path."""
    from mrctl.runlog.files import write_outputs

    items = result_bytes(res, out)
    try:
        write_outputs(items, force, mkdir=True)
    except OSError as exc:
        raise IdentificationError(f"{exc.filename or out}: cannot write: {exc.strerror or exc}") from None
    return items[1][0]


def format_summary(res: IdentificationResult) -> str:
    """The held-out table and the fitted terms, as ``mrctl identify --dataset`` prints them."""
    u = res.unit
    lines = [f"{res.name}: {res.protocol}, {res.input} input, range {res.input_range[0]:.4g}–"
             f"{res.input_range[1]:.4g} {u}"]
    if res.protocol == "constant_input":
        lines.append(f"{'level (' + u + ')':>11} {'Fc (N)':>9} {'Fs (N)':>9} {'σ2 (N·s/m)':>11} {'offset (N)':>10} "
                     f"{'fit':>7} {'floor':>7}  poorly determined")
        for lv in res.details.get("levels", []):
            th = lv["theta"]
            poor = ",".join(k for k, v in (lv.get("determined") or {}).items() if v == "poor") or "-"
            floor = lv.get("nrmse_noise_floor")
            floor_s = f"{100 * floor:6.2f}%" if floor is not None and math.isfinite(floor) else f"{'-':>7}"
            lines.append(f"{lv['level']:11.4g} {th['Fc']:9.4g} {th['Fs']:9.4g} {th['sigma2']:11.4g} "
                         f"{lv['offset_N']:10.4g} {100 * lv['nrmse_fit']:6.2f}% {floor_s}  {poor}")
    if res.holdout:
        lines.append("held-out force NRMSE (RMSE / peak-to-peak of the measured force, data the fit never saw):")
        both = any(s.nrmse_paper is not None for s in res.holdout)
        table = any(s.nrmse_table is not None for s in res.holdout)
        lines.append(f"  {'record':<24} {'level':>9} {'NRMSE':>8}" + ("  with laws: paper" if both else "")
                     + ("    table" if table else ""))
        for s in res.holdout:
            lv = "-" if s.level is None else f"{s.level:.4g}"
            laws = f" {100 * s.nrmse_paper:16.2f}%" if s.nrmse_paper is not None else ""
            laws += f" {100 * s.nrmse_table:7.2f}%" if s.nrmse_table is not None else ""
            lines.append(f"  {s.record:<24} {lv:>9} {100 * s.nrmse:7.2f}%{laws}")
        ch = res.details.get("laws_choice")
        if ch:
            mean = ", ".join(f"{k} {100 * v:.2f} %" for k, v in ch["leave_level_out_mean"].items() if v is not None)
            lines.append(f"written laws: {ch['laws']} (fit.laws: {ch['asked']}; each interior level predicted from "
                         f"the others' fits: {mean or 'no interior level'})")
    else:
        lines.append("no held-out data: the scores are on fitted data only (see warnings)")
    p = res.params
    if p.table is not None and p.table.has_bench():
        lines.append(f"laws: table, with per-level F_offset {min(p.table.values[6]):.4g}–{max(p.table.values[6]):.4g} N "
                     f"and k_x {min(p.table.values[7]):.4g}–{max(p.table.values[7]):.4g} N/m (the constants below "
                     "are the paper-law set's)")
    lines.append(f"bench terms: F_offset {p.F_offset:.4g} N, k_x {p.k_x:.4g} N/m, tau_input "
                 f"{1e3 * p.tau_input:.3g} ms" + (f", inertia {res.inertia_kg:.3g} kg (measurement term, not in "
                                                  "the set)" if res.inertia_kg else ""))
    if p.extras():
        lines.append("model terms: " + ", ".join(f"{k}={v:.5g}" for k, v in p.extras().items()))
    lines.append("parameters: " + ", ".join(f"{k}={getattr(p, k):.5g}" for k in p.names()))
    for w in res.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)
