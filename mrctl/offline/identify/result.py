"""What identification returns, and how it is written and shown.

:class:`CurrentFit` per current and :class:`IdentificationResult` for the
whole; :func:`write_params_yaml` writes the parameters file
(``mrctl.config.load_params_file`` reads it; the ``fit:`` block below the 13
constants is :func:`result_metadata`); :func:`format_summary` is the table
``mrctl identify`` prints.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mrctl.model.params import LuGreParams
from mrctl.offline.identify.errors import IdentificationError
from mrctl.offline.identify.fit import _WELL_REL_SE, _WELL_SENS
from mrctl.offline.identify.laws import LawFit
from mrctl.offline.identify.model import THETA_NAMES

__all__ = ["CurrentFit", "IdentificationResult", "result_metadata", "write_params_yaml", "params_yaml_bytes",
           "format_summary"]


@dataclass
class CurrentFit:
    """Identification at one constant current."""

    current: float  # A (mean applied current over the fit windows)
    current_cmd: float  # commanded current (A)
    theta: dict[str, float]
    theta0: dict[str, float]  # starting values (from the data)
    start_notes: dict[str, str]
    nrmse: float  # RMS(F_meas − F_fit) / ptp(F_meas) with this current's Θ
    noise_nrmse: float  # sensor-noise floor of the same ratio (estimated from F_meas)
    nrmse_laws: float = math.nan  # same with Θ from the written set's laws
    nrmse_paper: float = math.nan  # same through the paper's laws (6)–(11)
    nrmse_table: float = math.nan  # same through laws: table (every current's fit: its own NRMSE)
    rms_N: float = math.nan
    ptp_N: float = math.nan
    noise_N: float = math.nan
    se: dict[str, float] = field(default_factory=dict)  # standard errors (white-noise assumption)
    rel_se: dict[str, float] = field(default_factory=dict)  # se / |θ|
    sensitivity: dict[str, float] = field(default_factory=dict)  # |Δθ|/|θ| moving F by 1 % of ptp
    corr: list[list[float]] = field(default_factory=list)
    determined: dict[str, str] = field(default_factory=dict)  # "well" / "poor"
    offset_N: float = 0.0  # fitted force offset at this current (0 unless identify(offset=True))
    k_x: float = 0.0  # fitted stiffness (N/m) (0 unless identify(stiffness=True))
    nfev: int = 0
    starts: int = 1
    time_s: float = 0.0
    samples: int = 0
    periods: float = 0.0
    segments: list[tuple[int, float, float]] = field(default_factory=list)  # (run, t0, t1) of fit windows
    # plotting data (fit samples only)
    v: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    F_meas: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    F_fit: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    F_laws: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)


@dataclass
class IdentificationResult:
    """The 13 constants, the per-current fits they came from, and how they were obtained."""

    params: LuGreParams  # the 13 constants (laws 6–11)
    fits: list[CurrentFit]  # per current, ascending
    laws: dict[str, LawFit]
    method: str
    period_s: float
    dt_s: float
    settle_periods: float
    warmup_periods: float
    fit_periods: float | None
    sources: list[str]
    time_s: float
    warnings: list[str] = field(default_factory=list)
    laws_choice: dict[str, Any] = field(default_factory=dict)  # the written laws and the scores that chose them

    @property
    def currents(self) -> np.ndarray:
        return np.array([f.current for f in self.fits])

    def theta(self, name: str) -> np.ndarray:
        return np.array([f.theta[name] for f in self.fits])

    def summary_determined(self) -> dict[str, str]:
        """Per parameter: 'well' (at ≥ 75 % of the currents), 'poor' (≤ 25 %) or 'mixed'."""
        out = {}
        for k in THETA_NAMES:
            share = float(np.mean([f.determined.get(k) == "well" for f in self.fits]))
            out[k] = "well" if share >= 0.75 else ("poor" if share <= 0.25 else "mixed")
        return out


def _r(x: float, digits: int = 6) -> float | str:
    if x is None or not math.isfinite(x):
        return "nan" if x is None or math.isnan(x) else ("inf" if x > 0 else "-inf")
    return float(f"{x:.{digits}g}")


_METHOD_TEXT = {
    "trf": "per-current least squares, trust-region reflective (scipy) on log(sigma0, Fc, Fs, vs) and scaled "
           "sigma1, sigma2; vectorised LuGre model driven by the measured velocity",
    "lm": "per-current least squares, Levenberg-Marquardt (scipy MINPACK) on log(sigma0, Fc, Fs, vs) "
          "and scaled sigma1, sigma2; vectorised LuGre model driven by the measured velocity",
    "trf-bounds": "per-current least squares, trust-region reflective (scipy) with bounds sigma0, Fc, Fs, vs > 0; "
           "vectorised LuGre model driven by the measured velocity",
    "nelder-mead": "per-current Nelder-Mead on Q (as the paper's fminsearch), log-scaled parameters; "
                   "vectorised LuGre model driven by the measured velocity",
}


def result_metadata(result: IdentificationResult) -> dict[str, Any]:
    """The ``fit:`` block of the parameters YAML (plain types only)."""
    per = []
    for f in result.fits:
        per.append({
            "current_A": _r(f.current), "current_cmd_A": _r(f.current_cmd),
            "theta": {k: _r(v) for k, v in f.theta.items()},
            "nrmse": _r(f.nrmse, 4), "nrmse_noise_floor": _r(f.noise_nrmse, 4), "nrmse_laws": _r(f.nrmse_laws, 4),
            "nrmse_paper": _r(f.nrmse_paper, 4), "nrmse_table": _r(f.nrmse_table, 4),
            "rms_N": _r(f.rms_N, 4), "noise_N": _r(f.noise_N, 4),
            "offset_N": _r(f.offset_N), "k_x": _r(f.k_x),
            "std_error": {k: _r(v, 3) for k, v in f.se.items()},
            "rel_std_error": {k: _r(v, 3) for k, v in f.rel_se.items()},
            "sensitivity_1pct": {k: _r(v, 3) for k, v in f.sensitivity.items()},
            "determined": dict(f.determined),
            "correlation": f.corr,
            "start": {k: _r(v, 4) for k, v in f.theta0.items()},
            "periods": _r(f.periods, 4), "samples": f.samples, "nfev": f.nfev, "starts": f.starts,
            "time_s": _r(f.time_s, 3),
        })
    return {
        "method": _METHOD_TEXT[result.method],
        "optimiser": result.method,
        "objective": "Q = sum over whole periods of (F_meas - F_LuGre(v_meas))^2, after a model warm-up",
        "period_s": _r(result.period_s), "sample_interval_s": _r(result.dt_s),
        "settle_periods": result.settle_periods, "warmup_periods": result.warmup_periods,
        "fit_periods": result.fit_periods if result.fit_periods is not None else "all",
        "source_runs": list(result.sources),
        "nrmse_definition": "RMS(F_meas - F_model) / peak-to-peak(F_meas) over the fit windows",
        "identifiability": {
            "summary": result.summary_determined(),
            "criterion": f"'well' at a current if rel_std_error < {_WELL_REL_SE:.0%} (std_error from the "
                         "Jacobian at the optimum, white sensor noise assumed) and sensitivity_1pct < "
                         f"{_WELL_SENS:.0%}; summary: 'well' at >= 75 % of the currents, 'poor' at <= 25 %, "
                         "else 'mixed'",
            "sensitivity_1pct": "relative parameter change that, the other five re-fitted, changes the "
                                "model force by 1 % of its peak-to-peak (noise-independent)",
            "correlation_order": list(THETA_NAMES),
        },
        "laws": {k: {"equation": lf.equation, "coefficients": {c: _r(v) for c, v in lf.coefficients.items()},
                     "rms": _r(lf.rms, 4), "rel_rms": _r(lf.rel_rms, 4), "max_abs": _r(lf.max_abs, 4),
                     "r2": _r(lf.r2, 4)} for k, lf in result.laws.items()},
        "laws_choice": result.laws_choice,
        "per_current": per,
        "warnings": list(result.warnings),
        "time_s": _r(result.time_s, 3),
    }


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


def params_yaml_bytes(result: IdentificationResult, description: str | None = None) -> bytes:
    """The parameters YAML: the 13 spec names at top level, ``fit:`` metadata below.

    ``mrctl.config.load_params_file`` reads it (metadata keys are ignored there)."""
    import yaml

    from mrctl import __version__

    _CompactDumper = _compact_dumper()
    p = result.params
    currents = result.currents
    doc: dict[str, Any] = {
        "version": 1,
        "description": description or (
            f"LuGre parameters identified by mrctl {__version__} from {len(result.fits)} constant-current "
            f"sine tests ({currents.min():g}–{currents.max():g} A, period {result.period_s:.4g} s)"),
        "source": ", ".join(result.sources),
    }
    values = p.as_dict()
    doc.update({k: float(values[k]) for k in p.names()})
    doc.update({k: float(values[k]) for k in p.bench_names() if values[k] != 0.0})  # only the terms a fit set
    if p.table is not None:  # the written laws: every current's Θ (the 13 constants stay, for the inverse laws)
        doc["laws"] = "table"
        doc["table"] = {k: [_r(x, 8) for x in col] for k, col in p.table.as_dict().items()}
    doc["fit"] = result_metadata(result)
    text = io.StringIO()
    text.write("# mrctl identify: LuGre parameters (SI units), " + (
        "a table of per-current values (laws: table)\n" if p.table is not None
        else "laws (6)-(11) of Palka & Maslanka 2013\n"))
    yaml.dump(doc, text, Dumper=_CompactDumper, sort_keys=False, allow_unicode=True, width=120)
    return text.getvalue().encode("utf-8")


def write_params_yaml(result: IdentificationResult, path: str | Path, description: str | None = None,
                      force: bool = False) -> None:
    """Write :func:`params_yaml_bytes` to ``path``, whole or not at all; an
    existing file is refused unless ``force``, a symlink never followed
    (:func:`mrctl.runlog.files.write_outputs`)."""
    from mrctl.runlog.files import write_outputs

    data = params_yaml_bytes(result, description)
    try:
        write_outputs([(path, data)], force, mkdir=True)
    except OSError as exc:
        raise IdentificationError(f"{path}: cannot write: {exc.strerror or exc}") from None


def format_summary(result: IdentificationResult) -> str:
    """The per-current table and the law residuals, as printed by the CLI."""
    lines = [f"{'I (A)':>7} {'Fc (N)':>8} {'Fs (N)':>8} {'σ0 (N/m)':>10} {'σ1 (N·s/m)':>11} "
             f"{'σ2 (N·s/m)':>11} {'vs (mm/s)':>10} {'NRMSE':>7} {'floor':>7} {'laws':>7}  poorly determined"]
    for f in result.fits:
        th = f.theta
        poor = ",".join(k for k in THETA_NAMES if f.determined.get(k) == "poor") or "-"
        lines.append(f"{f.current:7.3f} {th['Fc']:8.3f} {th['Fs']:8.3f} {th['sigma0']:10.4g} {th['sigma1']:11.4g} "
                     f"{th['sigma2']:11.4g} {1e3 * th['vs']:10.3f} {100 * f.nrmse:6.2f}% {100 * f.noise_nrmse:6.2f}% "
                     f"{100 * f.nrmse_laws:6.2f}%  {poor}")
    lines.append("laws (6)-(11): " + "; ".join(
        f"{k} rms {lf.rms:.4g} ({100 * lf.rel_rms:.1f} %)" for k, lf in result.laws.items()))
    ch = result.laws_choice
    if ch:
        mean = ", ".join(f"{k} {100 * v:.2f} %" for k, v in ch["leave_level_out_mean"].items() if v is not None)
        lines.append(f"written laws: {ch['laws']} (each interior current predicted from the others' fits: "
                     f"{mean or 'no interior current'})")
    lines.append("identifiability: " + ", ".join(f"{k} {v}" for k, v in result.summary_determined().items()))
    p = result.params
    lines.append("parameters: " + ", ".join(f"{k}={getattr(p, k):.5g}" for k in p.names()))
    for w in result.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)

