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

from mrctl.errors import BadInput
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


class ReportError(BadInput):
    """A run file cannot be reported on; the message says why, for the CLI user."""


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
    return {"law": law if isinstance(law, str) else None,
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
_COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive")
#: line styles of overlaid runs: told apart in grey print and by colour-blind readers too
_STYLES = ("-", (0, (6, 2)), (0, (1, 1.2)), (0, (6, 2, 1, 2)), (0, (3, 1, 1, 1, 1, 1)), (0, (10, 3)))

#: every panel the report can draw: (title, y label); time panels share the time axis
PANELS: dict[str, tuple[str, str]] = {
    "force": ("damper force", "force (N)"),
    "error": ("tracking error $F - F_{des}$", "error (N)"),
    "current": ("coil current", "coil current (A)"),
    "fv": ("force–velocity", "force (N)"),
    "fx": ("force–displacement", "force (N)"),
    "body_acc": ("body acceleration", "body acceleration (m/s²)"),
    "stroke": ("suspension stroke", "stroke (mm)"),
    "tyre": ("tyre deflection", "tyre deflection (mm)"),
}
TIME_PANELS = ("force", "error", "current", "body_acc", "stroke", "tyre")
#: the default panels: a force-tracking run, and a quarter-car run (judged on comfort and road holding)
DEFAULT_PANELS = ("force", "error", "current", "fv", "fx")
QUARTER_CAR_PANELS = ("body_acc", "stroke", "tyre", "current")
_QC_COLUMNS = ("a_sprung", "tyre_defl")
_EXTRA_COLUMNS = ("k", "fault", *_QC_COLUMNS)

__all__ += ["PANELS", "DEFAULT_PANELS", "QUARTER_CAR_PANELS", "build_figure", "parse_pair", "fault_spans",
            "skipped_spans"]


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
    bits, the quarter car's channels), those that are there and numeric."""
    out: dict[str, np.ndarray] = {}
    for c in _EXTRA_COLUMNS:
        try:
            out.update(read_run_table(path, (c,)).columns)
        except CsvError:
            continue  # absent or not numeric: nothing to shade or draw from it
    return out


def _runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
    """[first, last] row index of each run of True."""
    m = np.asarray(mask, bool)
    if not m.any():
        return []
    d = np.diff(np.concatenate(([0], m.view(np.int8), [0])))
    return list(zip(np.flatnonzero(d == 1).tolist(), (np.flatnonzero(d == -1) - 1).tolist()))


def fault_spans(t: np.ndarray, fault: np.ndarray | None, dt: float) -> list[tuple[float, float]]:
    """Time spans (s) of rows with a fault bit set: from the first such
    row's time to one tick after the last."""
    if fault is None:
        return []
    f = np.asarray(fault, float)
    return [(float(t[a]), float(t[b]) + dt) for a, b in _runs_of(np.isfinite(f) & (f != 0))]


def skipped_spans(t: np.ndarray, k: np.ndarray | None, dt: float) -> list[tuple[float, float]]:
    """Time spans (s) of skipped deadlines: where the tick index jumps,
    from one tick after the row before to the row after."""
    if k is None or len(k) < 2:
        return []
    jumps = np.flatnonzero(np.diff(np.asarray(k, float)) > 1.5)
    return [(float(t[i]) + dt, float(t[i + 1])) for i in jumps]


def _rgb(colour: str) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    return to_rgb(colour)


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


def check_panels(panels: Sequence[str]) -> list[str]:
    """``--panels`` as a list; ReportError naming any unknown panel (checked
    before any file is touched)."""
    panels = list(panels)
    unknown = [q for q in panels if q not in PANELS]
    if unknown or not panels:
        raise ReportError(f"--panels: unknown panel(s) {', '.join(unknown) or '(none given)'}; "
                          f"choose from {', '.join(PANELS)}")
    return panels


def build_figure(runs: str | os.PathLike[str] | Sequence[str | os.PathLike[str]], title: str | None = None,
                 settle: float | None = None, size: tuple[float, float] | None = None,
                 time: tuple[float, float] | None = None,
                 panels: Sequence[str] | None = None) -> tuple[Any, list[dict[str, Any]]]:
    """The report's Figure (unsaved) and each run's figures: for tests that
    check what is drawn, and for :func:`make_report`. Each panel's Axes is
    labelled with its name (``ax.get_label()``); shaded spans carry the
    labels ``fault``, ``skipped deadlines`` and ``settling``."""
    paths = [Path(runs)] if isinstance(runs, (str, os.PathLike)) else [Path(r) for r in runs]
    if not paths:
        raise ReportError("no run to report on")
    loaded = []
    read = [(p, load_run(p)) for p in paths]
    # like with like: the plant's own force only when every run has it (simulated benches),
    # else every run's load cell (a run on hardware beside its replay)
    quantity = "F_true" if all("F_measured" in cols for _, cols in read) else "F"
    for p, cols in read:
        if quantity == "F" and "F_measured" in cols:
            cols["F"] = cols.pop("F_measured")
        cols.update(_load_extras(p))
        facts = _run_facts(p)
        st = settle if settle is not None else (facts["settle"] if facts["settle"] is not None else DEFAULT_SETTLE_S)
        m: dict[str, Any] = summarize(cols, st, facts["I_max"])
        m.update(I_max=facts["I_max"], path=str(p), verdict=facts["verdict"], force_from=quantity,
                 verdict_reasons=facts["verdict_reasons"],
                 label=f"{p.name} ({facts['law']})" if facts["law"] else p.name)
        m["quarter_car"] = all(c in cols for c in _QC_COLUMNS)
        dt = _dt(cols["t"], cols.get("k"))
        m["fault_spans"] = fault_spans(cols["t"], cols.get("fault"), dt)
        m["skipped_spans"] = skipped_spans(cols["t"], cols.get("k"), dt)
        loaded.append((cols, m))
    if panels is None:
        panels = QUARTER_CAR_PANELS if all(m["quarter_car"] for _, m in loaded) else DEFAULT_PANELS
    panels = check_panels(panels)
    missing = [q for q in panels if q in ("body_acc", "tyre") and not all(m["quarter_car"] for _, m in loaded)]
    if missing:
        raise ReportError(f"--panels: {', '.join(missing)} needs a quarter-car run (columns a_sprung, tyre_defl)")
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Patch
    except ImportError:
        raise ReportError("matplotlib is needed for reports: pip install 'mrctl[plot]'") from None

    single = len(loaded) == 1
    ncols = 1 if len(panels) <= 2 else 2
    nrows = -(-len(panels) // ncols)
    if size is None:
        size = (12.0, 2.9 * nrows + 1.6 + 0.35 * len(loaded))
    fig = Figure(figsize=size, dpi=200, layout="constrained")
    FigureCanvasAgg(fig)
    axes = {}
    for i, name in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, i + 1, label=name)
        axes[name] = ax
    t_lo = min(float(c["t"][0]) for c, _ in loaded)
    t_hi = max(float(c["t"][-1]) for c, _ in loaded)
    if time is not None:
        t_lo, t_hi = time
    time_axes = [axes[q] for q in panels if q in TIME_PANELS]
    lines = []
    for n, (cols, m) in enumerate(loaded):
        t = cols["t"]
        settle_used = m["t_start"] > t[0]
        colour = _COLOURS[n % len(_COLOURS)]
        style = _STYLES[n % len(_STYLES)]
        sel = (t >= t_lo) & (t <= t_hi)
        w = sel & (t >= m["t_start"])  # loops over the metrics window only (no stray start-up cycle)
        if single:  # actual first and lighter, desired on top and dark-dashed: when tracking
            # is good the two coincide, and the reference must stay visible
            act = dict(color=colour, lw=0.9, alpha=0.8, zorder=2,
                       label="true $F$ (simulated plant)" if "F_measured" in cols else "load-cell $F$")
            des = dict(color="black", lw=1.3, ls=(0, (4, 2)), zorder=3, label="desired $F_{des}$")
            line = dict(color=colour, lw=1.0, zorder=2)
        else:  # each run in its colour and line style; a demand that differs from the first run's gets a line
            act = dict(color=colour, ls=style, lw=1.0, alpha=0.9, zorder=2 + n, label=m["label"])
            des = None if n and _same_demand(loaded, n) else dict(
                color="black" if n == 0 else colour, lw=1.1, ls=(0, (4, 2)), zorder=20, alpha=0.8,
                label="desired $F_{des}$" if n == 0 else f"desired $F_{{des}}$, {m['label']}")
            line = dict(color=colour, ls=style, lw=1.0, zorder=2 + n, label=m["label"])
        F, F_des = cols["F"], cols["F_des"]
        draw = {
            "force": lambda ax: (ax.plot(t[sel], F[sel], **act),
                                 des is not None and ax.plot(t[sel], F_des[sel], **des)),
            "error": lambda ax: ax.plot(t[sel], (F - F_des)[sel], **{**line, "label": line.get("label",
                                                                                        "$F - F_{des}$")}),
            "current": lambda ax: ax.plot(t[sel], cols["I"][sel], **{**line, "label": line.get("label",
                                                                                            "current $I$")}),
            "fv": lambda ax: (ax.plot(1e3 * cols["v"][w], F[w], **act),
                              des is not None and ax.plot(1e3 * cols["v"][w], F_des[w], **des)),
            "fx": lambda ax: (ax.plot(1e3 * cols["x"][w], F[w], **act),
                              des is not None and ax.plot(1e3 * cols["x"][w], F_des[w], **des)),
            "body_acc": lambda ax: ax.plot(t[sel], cols["a_sprung"][sel], **line),
            "stroke": lambda ax: ax.plot(t[sel], 1e3 * cols["x"][sel], **line),
            "tyre": lambda ax: ax.plot(t[sel], 1e3 * cols["tyre_defl"][sel], **line),
        }
        for q in panels:
            draw[q](axes[q])
        # what happened, shaded in every time panel: faults (0 A), skipped deadlines
        for ax in time_axes:
            for a, b in m["skipped_spans"]:
                ax.axvspan(a, b, color="tab:orange" if single else colour, alpha=0.22, lw=0, zorder=0.5,
                           label="skipped deadlines")
            for a, b in m["fault_spans"]:  # over the skips: a fault is what a reader must not miss
                ax.axvspan(a, b, facecolor=(1.0, 0.0, 0.0, 0.22) if single else (*_rgb(colour), 0.22),
                           edgecolor="tab:red" if single else colour, hatch="///", lw=0, zorder=0.6,
                           label="fault")
        if m["quarter_car"]:
            summary = _ride_line(cols, m)
        else:
            summary = _summary_line(m, settle_used)
        verdict = "\n".join(textwrap.wrap(_verdict_text(m), 150))
        lines.append(f"{summary}\n{verdict}" if single else f"{m['label']}: {summary}\n{verdict}")
    # the settling window (what the metrics leave out), shaded in every time panel
    t_settle = max(m["t_start"] for _, m in loaded)
    if t_settle > t_lo:
        for ax in time_axes:
            ax.axvspan(t_lo, min(t_settle, t_hi), color="0.88", zorder=0, lw=0, label="settling")
    for q, ax in axes.items():
        what, ylabel = PANELS[q]
        if q == "force":  # which force every run is drawn and judged on
            what += ": the plant's $F_{true}$" if quantity == "F_true" else ": the load cell's $F$"
        letter = "abcdefghij"[panels.index(q)]
        if q in ("fv", "fx"):
            window = (f" ({_window_text(loaded[0][1], loaded[0][1]['t_start'] > loaded[0][0]['t'][0])})"
                      if single else " (metrics windows)")
            ax.set(xlabel="velocity (mm/s)" if q == "fv" else "displacement (mm)", ylabel=ylabel,
                   title=f"({letter}) {what}{window}")
        else:
            ax.set(xlabel="time (s)", ylabel=ylabel, title=f"({letter}) {what}")
            ax.set_xlim(t_lo, t_hi)
        if q == "error":
            ax.axhline(0.0, color="0.3", lw=0.6, zorder=1)
            lim = _error_limits(loaded, t_lo, t_hi)
            if lim is not None:  # scaled to the metrics window: a start-up transient is not the story
                ax.set_ylim(*lim)
        ax.grid(True, lw=0.5, alpha=0.5)
    # one shared legend below the panels, so no legend ever covers data; the
    # shaded spans once each
    handles, labels = [], []
    for ax in axes.values():
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels and lab not in ("fault", "skipped deadlines", "settling"):
                handles.append(h)
                labels.append(lab)
    shade = {"fault": any(m["fault_spans"] for _, m in loaded),
             "skipped deadlines": any(m["skipped_spans"] for _, m in loaded), "settling": t_settle > t_lo}
    for lab, colour, alpha in (("fault", "tab:red", 0.22), ("skipped deadlines", "tab:orange", 0.22),
                               ("settling", "0.88", 1.0)):
        if shade[lab] and time_axes:
            handles.append(Patch(facecolor=(*_rgb(colour), alpha), edgecolor=colour, lw=0,
                                 hatch="///" if lab == "fault" else None))
            labels.append({"fault": "fault (0 A)", "settling": "settling (not in metrics)"}.get(lab, lab))
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncol=min(len(handles), 4), frameon=False,
                   fontsize="medium")
    head = title if title is not None else ", ".join(m["label"] for _, m in loaded)
    fig.suptitle(head + "\n" + "\n".join(lines), fontsize="large" if single else "medium")
    return fig, [m for _, m in loaded]


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


def _error_limits(loaded: list, t_lo: float, t_hi: float) -> tuple[float, float] | None:
    """y limits of the error panel: the runs' F - F_des over their metrics
    windows within [t_lo, t_hi], 15 % margin; None when there is nothing
    finite there (matplotlib's own limits then)."""
    lo, hi = math.inf, -math.inf
    for cols, m in loaded:
        t = cols["t"]
        sel = (t >= max(t_lo, m["t_start"])) & (t <= t_hi)
        e = (cols["F"] - cols["F_des"])[sel]
        e = e[np.isfinite(e)]
        if e.size:
            lo, hi = min(lo, float(e.min())), max(hi, float(e.max()))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return None
    pad = 0.15 * max(hi - lo, 1e-9)
    return lo - pad, hi + pad


def _same_demand(loaded: list, n: int) -> bool:
    """Run n asks for the force run 0 asks for (the same demand on the same
    time base): its dashed reference would only repeat run 0's."""
    a, b = loaded[0][0], loaded[n][0]
    return len(a["t"]) == len(b["t"]) and np.allclose(a["F_des"], b["F_des"], rtol=1e-6, atol=1e-6, equal_nan=True)


def figure_bytes(fig: Any, fmt: str) -> bytes:
    """The rendered figure (png, pdf or svg) as bytes, for
    :func:`mrctl.runlog.files.write_outputs`."""
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt)
    return buf.getvalue()


def _save(fig: Any, out_path: str | os.PathLike[str] | None, fmt: str, force: bool = False) -> bytes:
    """Render ``fig``; write it to ``out_path`` (whole or not at all) unless None."""
    data = figure_bytes(fig, fmt)
    if out_path is not None:
        try:
            write_outputs([(out_path, data)], force)
        except OSError as exc:
            raise ReportError(f"{out_path}: cannot write the figure: {exc.strerror or exc}") from None
    return data
