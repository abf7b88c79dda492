"""Post-run report: the Fig 5 plot of Palka & Maślanka 2013 from run logs.

One or several run logs (docs/runlog.md) become one figure an engineer can
judge at a glance and a paper can print: desired vs actual force, the
tracking error, the coil current over time, the force–velocity and
force–displacement loops (a quarter-car run: body acceleration, stroke,
tyre deflection and the current), faults and skipped deadlines shaded, and
one summary line per run with its verdict. Several runs are overlaid, each
in its colour and line style, labelled by file name and law (the paper law
against the smooth one is the first thing a reader wants to see). The format is the output name's (png, pdf, svg).
The figures are the daemon's (:func:`mrctl.runlog.metrics.tracking_summary`)
with the run's ``I_max`` and settle window from its sidecar, so "I = I_max"
means what ``mrctl run`` prints; a log without a sidecar counts "at the
run's largest current" and says so. matplotlib (``mrctl[plot]``) is
imported only inside the figure functions: the daemon never needs it.
"""

from __future__ import annotations

import io
import math
import os
import textwrap
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mrctl.offline.report_figure import (DEFAULT_PANELS, PANELS, QUARTER_CAR_PANELS, ReportError, check_panels,
                                         draw_runs, events_line, palette_png)
from mrctl.offline.report_marks import fault_spans, fault_ticks, skipped_spans, skipped_ticks
from mrctl.runlog.files import check_output_path, write_outputs
from mrctl.runlog.metrics import tracked_force, tracking_summary
from mrctl.runlog.read import read_run_table, sidecar_path, try_sidecar
from mrctl.util.csvtable import CsvError

__all__ = ["REQUIRED_COLUMNS", "FORMATS", "ReportError", "load_run", "summarize", "make_report",
           "figure_format"]

#: Columns a run CSV must have (SI units: s, m, m/s, N, N, A). Others are ignored.
REQUIRED_COLUMNS: tuple[str, ...] = ("t", "x", "v", "F_des", "F", "I")

#: Default settling time (s) excluded from the metrics when the log has no
#: sidecar saying: the start-up transient (filter fill, LuGre bristle state
#: from z = 0) is not tracking performance.
DEFAULT_SETTLE_S = 1.0

#: figure formats, by the output name's extension
FORMATS = ("png", "pdf", "svg")


def figure_format(out_path: str | os.PathLike[str]) -> str:
    """The format the output name asks for; ReportError for one we cannot write."""
    ext = Path(out_path).suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise ReportError(f"{out_path}: cannot write a .{ext or '(no extension)'} figure; "
                          f"name it .png, .pdf or .svg")
    return ext


# -- loading ----------------------------------------------------------------
def load_run(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read a run CSV into ``{column: float array}`` for the required columns.

    A log with a finite ``F_true`` column (a simulated bench) has it as
    ``F``, the force tracking is judged on (the load cell's reading moves to
    ``F_measured``): the same rule as the daemon's summary
    (:func:`mrctl.runlog.metrics.tracked_force`).

    Columns are found by header name; the others are not parsed at all. A
    torn last line (a full disk, a SIGKILL) is dropped, ``#`` lines are
    comments. Every error is a :class:`ReportError` naming the file and,
    where it helps, the column or the 1-based line number.
    """
    p = Path(path)
    try:
        table = read_run_table(p, (*REQUIRED_COLUMNS, "F_true"), require=REQUIRED_COLUMNS)
        for c in REQUIRED_COLUMNS:
            # NaN is "no value": a daemon log has it in x, v, F_des while the
            # safety supervisor holds the damper at 0 A, and in F without a
            # load cell. It plots as a gap and is left out of the metrics.
            # Time and current are always logged.
            table.check_finite(c, allow_nan=c not in ("t", "I"))
        F, name = tracked_force(table.columns)
        if name == "F_true":  # a simulated bench: judge and plot the plant's own force
            table.check_finite("F_true", allow_nan=True)
    except CsvError as exc:
        raise ReportError(str(exc)) from None
    n = len(table.lines)
    if n < 2:
        raise ReportError(f"{p}: {n} data row(s); a report needs at least 2")
    out = {c: table.columns[c] for c in REQUIRED_COLUMNS}
    if name == "F_true":
        out["F_measured"] = out["F"]
        out["F"] = F
    return out


def _run_facts(path: Path) -> dict[str, Any]:
    """What the sidecar says about a run (empty where it has none): law, I_max, settle."""
    side = try_sidecar(path)
    cfg = side.get("config") if isinstance(side.get("config"), dict) else {}
    if not cfg and isinstance(side.get("meta"), dict) and isinstance(side["meta"].get("config"), dict):
        cfg = side["meta"]["config"]  # a sidecar of mrctl before 2026-11
    law = side.get("law") or (cfg.get("inverse") or {}).get("law")
    I_max = side.get("I_max_A", (cfg.get("safety") or {}).get("I_max"))
    settle = side.get("settle_s")
    verdict = side.get("verdict")
    reasons = side.get("verdict_reasons")
    demand = (cfg.get("demand") or {}).get("type") if isinstance(cfg.get("demand"), dict) else None
    return {"law": law if isinstance(law, str) else None, "demand": demand if isinstance(demand, str) else None,
            "I_max": float(I_max) if isinstance(I_max, (int, float)) and not isinstance(I_max, bool) else None,
            "settle": float(settle) if isinstance(settle, (int, float)) and not isinstance(settle, bool) else None,
            "verdict": verdict if verdict in ("ok", "degraded") else None,
            "verdict_reasons": [str(r) for r in reasons] if isinstance(reasons, list) else []}


# -- metrics ----------------------------------------------------------------
def summarize(cols: dict[str, np.ndarray], settle: float = DEFAULT_SETTLE_S,
              I_max: float | None = None) -> dict[str, float]:
    """Tracking metrics of a run, over ``t >= t[0] + settle``.

    The figures are :func:`mrctl.runlog.metrics.tracking_summary`'s (the daemon and
    ``mrctl simulate`` use the same), renamed for the figure title. The
    window drops the start-up transient; a run shorter than ``settle`` (or
    leaving fewer than 2 rows) is taken whole rather than refused, since a
    short bench run still deserves a number. NaN rows carry no value.

    Returns:
        nrmse: RMS(F - F_des) / peak-to-peak(F_des); ``nan`` if F_des is flat.
        max_dI: largest |I[k+1] - I[k]| (A) between consecutive rows.
        share_zero: fraction of rows with I <= 1 nA (driver switched off).
        share_max: fraction of rows at ``I_max`` (the run's configured limit,
            as the daemon counts), or at the run's largest current if
            ``I_max`` is None (unknown).
        t_start: first time (s) in the window; n: rows in the window.
    """
    m = tracking_summary(cols["t"], cols["F_des"], cols["F"], cols["I"], I_max, settle)
    return {
        "nrmse": m["force_nrmse"],
        "max_dI": m["max_current_step_A"],
        "share_zero": m["share_at_zero"],
        "share_max": m["share_at_I_max"],
        "t_start": m["window_start_s"],
        "n": m["window_ticks"],
    }


def _window_text(m: dict[str, float], settle_used: bool) -> str:
    return f"t ≥ {m['t_start']:.3g} s" if settle_used else "whole run"


def _summary_line(m: dict[str, Any], settle_used: bool) -> str:
    window = _window_text(m, settle_used)
    nrmse = "n/a (flat F_des)" if math.isnan(m["nrmse"]) else f"{100.0 * m['nrmse']:.2f} %"
    nrmse += " of the plant's F_true" if m.get("force_from") == "F_true" else " of the load cell's F"
    top = f"I = I_max ({m['I_max']:g} A)" if m.get("I_max") is not None else "I = run's max (I_max unknown)"
    return (f"force NRMSE {nrmse}   ·   max |ΔI| {m['max_dI']:.3f} A   ·   "
            f"I = 0: {100.0 * m['share_zero']:.1f} %   ·   {top}: {100.0 * m['share_max']:.1f} %"
            f"   ({window})")


# -- figure -----------------------------------------------------------------
__all__ += ["PANELS", "DEFAULT_PANELS", "QUARTER_CAR_PANELS", "check_panels", "build_figure", "parse_pair",
            "fault_spans", "skipped_spans"]
#: the quarter car's columns, and the optional columns the report shades or draws
_QC_COLUMNS = ("a_sprung", "tyre_defl")
_EXTRA_COLUMNS = ("k", "fault", *_QC_COLUMNS)


def parse_pair(text: str, option: str, positive: bool = False) -> tuple[float, float]:
    """``"A,B"`` as two finite numbers (``--size W,H``, ``--time T0,T1``); ReportError otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        a, b = (float(p) for p in parts) if len(parts) == 2 else (math.nan, math.nan)
    except ValueError:
        a = b = math.nan
    if not (math.isfinite(a) and math.isfinite(b)) or (positive and not (a > 0 and b > 0)) or (not positive and b <= a):
        what = "two positive numbers W,H (inches)" if positive else "two times T0,T1 (s) with T0 < T1"
        raise ReportError(f"{option}: expected {what}, got {text!r}")
    return a, b


def _load_extras(path: Path) -> dict[str, np.ndarray]:
    """The optional columns the report shades or draws (tick index, fault
    bits, the quarter car's channels), those that are there and numeric:
    read together, and only if one of them cannot be, one by one."""
    try:
        got = read_run_table(path, _EXTRA_COLUMNS).columns
        return {c: got[c] for c in _EXTRA_COLUMNS if c in got}
    except CsvError:
        pass
    out: dict[str, np.ndarray] = {}
    for c in _EXTRA_COLUMNS:
        try:
            out.update(read_run_table(path, (c,)).columns)
        except CsvError:
            continue  # absent or not numeric: nothing to shade or draw from it
    return out


def _dt(t: np.ndarray, k: np.ndarray | None) -> float:
    if k is not None and len(k) > 1 and k[-1] > k[0]:
        return float((t[-1] - t[0]) / (k[-1] - k[0]))
    return float(np.median(np.diff(t))) if len(t) > 1 else 1e-3


def _verdict_text(facts: dict[str, Any]) -> str:
    v = facts.get("verdict")
    if v == "ok":
        return "verdict: ok"
    if v == "degraded":
        return "verdict: DEGRADED: " + "; ".join(facts.get("verdict_reasons") or [])
    return "verdict: not recorded"


def _ride_line(cols: dict[str, np.ndarray], m: dict[str, Any]) -> str:
    from mrctl.runlog.ride import ride_summary

    r = ride_summary({"t": cols["t"], "a_sprung": cols["a_sprung"], "tyre_defl": cols["tyre_defl"],
                      "x": cols["x"]}, m["t_start"] - float(cols["t"][0]))
    m.update(r)
    return (f"RMS body acceleration {r['rms_a_sprung_mps2']:.3f} m/s²   ·   RMS tyre deflection "
            f"{1e3 * r['rms_tyre_defl_m']:.3f} mm   ·   RMS stroke {1e3 * r['rms_stroke_m']:.2f} mm   ·   "
            f"I = 0: {100.0 * m['share_zero']:.1f} %")


def _events(cols: dict[str, np.ndarray], m: dict[str, Any]) -> None:
    """The run's faults, latched faults and skipped deadlines: their spans
    (s) and how many ticks each, into ``m``."""
    t, k, fault = cols["t"], cols.get("k"), cols.get("fault")
    dt = _dt(t, k)
    m["fault_spans"] = fault_spans(t, fault, dt)
    m["latched_spans"] = fault_spans(t, fault, dt, latched=True)
    m["skipped_spans"] = skipped_spans(t, k, dt)
    m["ticks"] = {"fault": fault_ticks(fault), "latched": fault_ticks(fault, latched=True),
                  "skipped deadlines": skipped_ticks(k)}
    m["rows"] = len(t)
    m["deadlines"] = len(t) + m["ticks"]["skipped deadlines"]


def _labels(paths: list[Path], facts: list[dict[str, Any]]) -> list[str]:
    """Each run's label: its file name and law (with its demand where the runs'
    demands differ: skyhook beside groundhook); its folder too where two runs
    share a name."""
    names = [p.name for p in paths]
    demands = len({f["demand"] for f in facts}) > 1
    out = []
    for p, f in zip(paths, facts):
        name = p.name if names.count(p.name) == 1 else f"{p.parent.name}/{p.name}"
        law = f"{f['demand']} + {f['law']}" if demands and f["demand"] and f["law"] else f["law"]
        out.append(f"{name} ({law})" if law else name)
    return out


def build_figure(runs: str | os.PathLike[str] | Sequence[str | os.PathLike[str]], title: str | None = None,
                 settle: float | None = None, size: tuple[float, float] | None = None,
                 time: tuple[float, float] | None = None,
                 panels: Sequence[str] | None = None) -> tuple[Any, list[dict[str, Any]]]:
    """The report's Figure (unsaved) and each run's figures: for tests that
    check what is drawn, and for :func:`make_report`. Each panel's Axes is
    labelled with its name (``ax.get_label()``); shaded stretches carry the
    labels ``fault``, ``latched``, ``skipped deadlines`` and ``settling``;
    markers of values beyond an axis the gid ``clipped``."""
    paths = [Path(runs)] if isinstance(runs, (str, os.PathLike)) else [Path(r) for r in runs]
    if not paths:
        raise ReportError("no run to report on")
    loaded = []
    read = [(p, load_run(p)) for p in paths]
    # like with like: the plant's own force only when every run has it (simulated benches),
    # else every run's load cell (a run on hardware beside its replay)
    quantity = "F_true" if all("F_measured" in cols for _, cols in read) else "F"
    facts_of = [_run_facts(p) for p in paths]
    labels = _labels(paths, facts_of)
    for (p, cols), facts, label in zip(read, facts_of, labels):
        if quantity == "F" and "F_measured" in cols:
            cols["F"] = cols.pop("F_measured")
        cols.update(_load_extras(p))
        st = settle if settle is not None else (facts["settle"] if facts["settle"] is not None else DEFAULT_SETTLE_S)
        m: dict[str, Any] = summarize(cols, st, facts["I_max"])
        m.update(I_max=facts["I_max"], path=str(p), verdict=facts["verdict"], force_from=quantity,
                 verdict_reasons=facts["verdict_reasons"], label=label)
        m["quarter_car"] = all(c in cols for c in _QC_COLUMNS)
        _events(cols, m)
        m["window"] = _window_text(m, m["t_start"] > cols["t"][0])
        summary = _ride_line(cols, m) if m["quarter_car"] else _summary_line(m, m["t_start"] > cols["t"][0])
        verdict = _verdict_text(m)
        parts = [summary + (f"   ·   {verdict}" if len(verdict) < 40 else ""), events_line(m),
                 "" if len(verdict) < 40 else "\n".join(textwrap.wrap(verdict, 150))]
        m["caption"] = "\n".join(part for part in parts if part)
        loaded.append((cols, m))
    if panels is None:
        panels = QUARTER_CAR_PANELS if all(m["quarter_car"] for _, m in loaded) else DEFAULT_PANELS
    panels = check_panels(panels)
    missing = [q for q in panels if q in ("body_acc", "tyre") and not all(m["quarter_car"] for _, m in loaded)]
    if missing:
        raise ReportError(f"--panels: {', '.join(missing)} needs a quarter-car run (columns a_sprung, tyre_defl)")
    if time is not None and not any(((c["t"] >= time[0]) & (c["t"] <= time[1])).sum() >= 2 for c, _ in loaded):
        lo, hi = min(float(c["t"][0]) for c, _ in loaded), max(float(c["t"][-1]) for c, _ in loaded)
        raise ReportError(f"--time {time[0]:g},{time[1]:g}: no run has two rows there (the runs span "
                          f"{lo:g}–{hi:g} s); every panel would be empty")
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ReportError("matplotlib is needed for reports: pip install 'mrctl[plot]'") from None
    return draw_runs(loaded, quantity, panels, title=title, size=size, time=time), [m for _, m in loaded]


def make_report(runs: str | os.PathLike[str] | Sequence[str | os.PathLike[str]], out_path: str | os.PathLike[str],
                title: str | None = None, settle: float | None = None, size: tuple[float, float] | None = None,
                time: tuple[float, float] | None = None,
                panels: Sequence[str] | None = None, force: bool = False) -> list[dict[str, Any]]:
    """Write the figure of one or several runs to ``out_path`` (format by
    its extension: png, pdf, svg); returns each run's label and figures
    (:func:`summarize`'s, with ``I_max``, ``label``, ``path``, the verdict,
    the shaded spans).

    Panels (``panels``, default :data:`DEFAULT_PANELS`, or
    :data:`QUARTER_CAR_PANELS` for quarter-car runs): desired and actual
    force, the tracking error, the current, the F–v and F–x loops; body
    acceleration, stroke and tyre deflection. Faults and skipped deadlines
    are shaded in every time panel, the settling window too; the caption
    gives each run's figures and its verdict (the sidecar's). ``settle``
    overrides each run's settle window; ``size`` is (W, H) in inches;
    ``time`` limits what is drawn to [T0, T1] s (the figures stay the
    run's). Uses explicit Figure/canvas objects (no pyplot, no global
    backend state), so it works on a headless controller. The figure is
    refused over an existing file unless ``force``, and over a run or its
    sidecar always (:func:`mrctl.runlog.files.check_output_path`); checked
    before any run is read.
    """
    paths = [Path(runs)] if isinstance(runs, (str, os.PathLike)) else [Path(r) for r in runs]
    if not paths:
        raise ReportError("no run to report on")
    fmt = figure_format(out_path)
    check_output_path(out_path, force, inputs=[q for p in paths for q in (p, sidecar_path(p))], what="the figure")
    fig, runs_out = build_figure(runs, title=title, settle=settle, size=size, time=time, panels=panels)
    _save(fig, out_path, fmt, force)
    return runs_out


def figure_bytes(fig: Any, fmt: str) -> bytes:
    """The rendered figure (png, pdf or svg) as bytes, for
    :func:`mrctl.runlog.files.write_outputs`."""
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt)
    return palette_png(buf.getvalue()) if fmt == "png" else buf.getvalue()


def _save(fig: Any, out_path: str | os.PathLike[str] | None, fmt: str, force: bool = False) -> bytes:
    """Render ``fig``; write it to ``out_path`` (whole or not at all) unless None."""
    data = figure_bytes(fig, fmt)
    if out_path is not None:
        try:
            write_outputs([(out_path, data)], force)
        except OSError as exc:
            raise ReportError(f"{out_path}: cannot write the figure: {exc.strerror or exc}") from None
    return data
