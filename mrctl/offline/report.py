"""Post-run report: the Fig 5 plot of Palka & Maślanka 2013 from a run CSV.

``mrctl simulate`` and ``mrctl run`` log one row per 1 ms tick; this module
turns such a log into one PNG an engineer can judge at a glance: desired vs
actual force and the coil current over time, plus the force–velocity and
force–displacement loops, with a one-line tracking summary in the title.
:func:`make_identification_report` draws the paper's Figs 2 and 3 from an
identification (:mod:`mrctl.offline.identify`; the dependency is one way:
identification never imports this module).

Nothing here runs on the control hot path. matplotlib is an optional
dependency (``mrctl[plot]``) and is imported only inside the two figure
functions, so the daemon itself never needs it.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from mrctl.errors import BadInput
from mrctl.model.params import TABLE_I
from mrctl.offline.identify import (
    THETA_NAMES,
    IdentificationError,
    IdentificationResult,
    identify,
    load_identification_run,
    theta_from_params,
)
from mrctl.runlog.metrics import tracked_force, tracking_summary
from mrctl.util.csvtable import CsvError, read_table

__all__ = ["REQUIRED_COLUMNS", "ReportError", "load_run", "summarize", "make_report"]

#: Columns a run CSV must have (SI units: s, m, m/s, N, N, A). Others are ignored.
REQUIRED_COLUMNS: tuple[str, ...] = ("t", "x", "v", "F_des", "F", "I")

#: Default settling time (s) excluded from the metrics: the start-up transient
#: (filter fill, LuGre bristle state from z = 0) is not tracking performance.
DEFAULT_SETTLE_S = 1.0


class ReportError(BadInput):
    """A run file cannot be reported on, or the figure cannot be made; the
    message says why, for the CLI user (exit code 2)."""


# -- loading ----------------------------------------------------------------
def load_run(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read a run CSV into ``{column: float array}`` for the required columns.

    A log with a finite ``F_true`` column (a simulated bench) has it as
    ``F``, the force tracking is judged on (the load cell's reading moves to
    ``F_measured``): the same rule as the daemon's summary
    (:func:`mrctl.runlog.metrics.tracked_force`).

    Columns are found by header name because the loggers add columns (``seq``,
    ``z``, ``fault`` …) in whatever order suits them; those extra columns are
    not parsed at all, so they may hold anything. Lines starting with ``#``
    are comments and may precede the header. Every error is a
    :class:`ReportError` naming the file and, where it helps, the column or
    the 1-based line number, so a bad log is fixed without a debugger.
    """
    p = Path(path)
    try:
        table = read_table(p, (*REQUIRED_COLUMNS, "F_true"), require=REQUIRED_COLUMNS)
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


# -- metrics ----------------------------------------------------------------
def summarize(cols: dict[str, np.ndarray], settle: float = DEFAULT_SETTLE_S) -> dict[str, float]:
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
        share_max: fraction of rows at the run's maximum current (saturation).
        t_start: first time (s) in the window; n: rows in the window.
    """
    m = tracking_summary(cols["t"], cols["F_des"], cols["F"], cols["I"], None, settle)
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


def _summary_line(m: dict[str, float], settle_used: bool) -> str:
    window = _window_text(m, settle_used)
    nrmse = "n/a (flat F_des)" if math.isnan(m["nrmse"]) else f"{100.0 * m['nrmse']:.2f} %"
    return (f"force NRMSE {nrmse}   ·   max |ΔI| {m['max_dI']:.3f} A   ·   "
            f"I = 0: {100.0 * m['share_zero']:.1f} %   ·   I = max: {100.0 * m['share_max']:.1f} %"
            f"   ({window})")


# -- figure -----------------------------------------------------------------
def make_report(csv_path: str | os.PathLike[str], out_path: str | os.PathLike[str],
                title: str | None = None, settle: float = DEFAULT_SETTLE_S) -> None:
    """Write the Fig-5-style PNG of one run to ``out_path``.

    Uses an explicit Agg canvas (no pyplot, no global backend state) so it
    works on a headless controller and cannot disturb a caller's own matplotlib
    figures. ``title`` replaces the default title (the run file's name).
    """
    cols = load_run(csv_path)
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise ReportError("matplotlib is needed for reports: pip install 'mrctl[plot]'") from None

    m = summarize(cols, settle)
    t = cols["t"]
    settle_used = m["t_start"] > t[0]
    x_mm, v_mms = 1e3 * cols["x"], 1e3 * cols["v"]
    F_des, F, I = cols["F_des"], cols["F"], cols["I"]

    # Actual first and lighter, desired on top and dark-dashed: when tracking
    # is good the two coincide, and the reference must stay visible.
    act = dict(color="tab:red", lw=0.9, alpha=0.7, zorder=2,
               label="true $F$ (simulated plant)" if "F_measured" in cols else "actual $F$")
    des = dict(color="black", lw=1.3, ls=(0, (4, 2)), zorder=3, label="desired $F_{des}$")

    fig = Figure(figsize=(12, 8.5), dpi=200, layout="constrained")
    FigureCanvasAgg(fig)
    (ax_f, ax_i), (ax_fv, ax_fx) = fig.subplots(2, 2)

    ax_f.plot(t, F, **act)
    ax_f.plot(t, F_des, **des)
    ax_f.set(xlabel="time (s)", ylabel="force (N)", title="(a) damper force")

    ax_i.plot(t, I, color="tab:green", lw=1.0)
    ax_i.set(xlabel="time (s)", ylabel="coil current (A)", title="(b) coil current")

    for ax in (ax_f, ax_i):
        ax.set_xlim(t[0], t[-1])
        if settle_used:  # grey out what the metrics ignore
            ax.axvspan(t[0], m["t_start"], color="0.88", zorder=0, lw=0,
                       label="settling (not in metrics)")

    # Loops over the metrics window only: the start-up transient would draw
    # a stray first cycle over the steady-state loop the paper's Fig 5 shows.
    w = t >= m["t_start"]
    loops = f" ({_window_text(m, settle_used)})"
    ax_fv.plot(v_mms[w], F[w], **act)
    ax_fv.plot(v_mms[w], F_des[w], **des)
    ax_fv.set(xlabel="velocity (mm/s)", ylabel="force (N)", title="(c) force–velocity" + loops)

    ax_fx.plot(x_mm[w], F[w], **act)
    ax_fx.plot(x_mm[w], F_des[w], **des)
    ax_fx.set(xlabel="displacement (mm)", ylabel="force (N)",
              title="(d) force–displacement" + loops)

    for ax in (ax_f, ax_i, ax_fv, ax_fx):
        ax.grid(True, lw=0.5, alpha=0.5)

    # One shared legend below the panels, so no legend ever covers data
    # (above would collide with the two-line suptitle).
    handles, labels = ax_f.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(handles),
               frameon=False, fontsize="medium")
    fig.suptitle(f"{title if title is not None else Path(csv_path).name}\n"
                 f"{_summary_line(m, settle_used)}", fontsize="large")

    try:
        fig.savefig(out_path, format="png")
    except OSError as exc:
        raise ReportError(f"{out_path}: cannot write the figure: {exc.strerror or exc}") from None


# -- identification figure (paper's Figs 2 and 3) -----------------------------
__all__ += ["make_identification_report"]

#: Currents shown in the force–velocity panel (the paper's Fig 2); the nearest
#: identified current to each is drawn.
FIG2_CURRENTS_A: tuple[float, ...] = (0.0, 0.25, 0.5)

# (Θ name, label, unit scale, unit text) of the Fig 3 panels
_THETA_PANELS = (
    ("Fc", "Coulomb force $F_c$", 1.0, "N"),
    ("Fs", "stiction force $F_s$", 1.0, "N"),
    ("vs", "Stribeck velocity $v_s$", 1e3, "mm/s"),
    ("sigma0", "bristle stiffness $\\sigma_0$", 1e-3, "kN/m"),
    ("sigma1", "bristle damping $\\sigma_1$", 1.0, "N·s/m"),
    ("sigma2", "viscous coefficient $\\sigma_2$", 1.0, "N·s/m"),
)


def _as_identification_result(runs_or_result, **identify_kwargs):
    """An IdentificationResult, identifying first if given runs (paths or column dicts)."""
    if isinstance(runs_or_result, IdentificationResult):
        return runs_or_result
    items = runs_or_result
    if isinstance(items, (str, os.PathLike, dict)):
        items = [items]
    try:
        runs, names = [], []
        for k, item in enumerate(items):
            if isinstance(item, (str, os.PathLike)):
                runs.append(load_identification_run(item))
                names.append(str(item))
            else:
                runs.append(item)
                names.append(f"run {k + 1}")
        return identify(runs, sources=names, **identify_kwargs)
    except IdentificationError as exc:
        raise ReportError(str(exc)) from None


def make_identification_report(runs_or_result, out_path: str | os.PathLike[str], title: str | None = None,
                               reference=None, show_reference: bool = True, **identify_kwargs) -> None:
    """Write the identification PNG: the paper's Fig 2 and Fig 3 for this damper.

    ``runs_or_result``: an :class:`mrctl.offline.identify.IdentificationResult`, or run
    CSV path(s) / column dict(s) to identify first (``identify_kwargs`` go to
    :func:`mrctl.offline.identify.identify`).

    Top row: (a) force vs velocity at the identified currents nearest to
    0, 0.25 and 0.5 A — measured samples as dots, the per-current fit as a
    solid line, the 13-constant laws (6)–(11) dashed; (b) fit NRMSE per current
    against the sensor-noise floor. Below, (c)–(h): each of the six parameters
    vs current, identified values with ±2 standard errors (hollow where
    poorly determined) and the fitted approximating law; Table I of the paper
    (``reference``, default) as a thin grey line for comparison.
    """
    res = _as_identification_result(runs_or_result, **identify_kwargs)
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.lines import Line2D
    except ImportError:
        raise ReportError("matplotlib is needed for reports: pip install 'mrctl[plot]'") from None
    if reference is None and show_reference:
        reference = TABLE_I
    fits = res.fits
    I = res.currents

    fig = Figure(figsize=(14, 12.5), dpi=150, layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(3, 3, height_ratios=(1.35, 1.0, 1.0))
    ax_fv = fig.add_subplot(gs[0, :2])
    ax_q = fig.add_subplot(gs[0, 2])

    # (a) Fig 2: force–velocity loops
    chosen: list[int] = []
    for target in FIG2_CURRENTS_A:
        k = int(np.argmin(np.abs(I - target)))
        if k not in chosen:
            chosen.append(k)
    colors = ("tab:blue", "tab:orange", "tab:red", "tab:green", "tab:purple")
    for c, k in zip(colors, chosen):
        f = fits[k]
        v_mms = 1e3 * f.v
        ax_fv.plot(v_mms, f.F_fit, "-", lw=2.2, color=c, zorder=2, label=f"{f.current:.2f} A")
        if f.F_laws.size:
            ax_fv.plot(v_mms, f.F_laws, ls=(0, (2, 3)), lw=0.9, color="black", alpha=0.7, zorder=3)
        # measured on top, small and translucent: the noise band shows around the fit
        ax_fv.plot(v_mms, f.F_meas, ".", ms=1.6, color="0.15", alpha=0.18, zorder=4, rasterized=True)
    ax_fv.set(xlabel="velocity (mm/s)", ylabel="force (N)",
              title=f"(a) force–velocity at constant current, sine {1.0 / res.period_s:.3g} Hz (cf. paper Fig 2)")
    cur_handles, cur_labels = ax_fv.get_legend_handles_labels()
    style = [Line2D([], [], ls="none", marker=".", ms=6, color="0.15", alpha=0.5),
             Line2D([], [], color="0.5", lw=2.2),
             Line2D([], [], color="black", lw=0.9, ls=(0, (2, 3)))]
    ax_fv.legend(cur_handles + style, cur_labels + ["measured", "fit at this current", "laws (6)–(11)"],
                 loc="upper left", fontsize="small", ncol=2, framealpha=0.9)

    # (b) fit quality per current
    ax_q.plot(I, [100 * f.nrmse for f in fits], "o-", color="tab:blue", ms=4, label="per-current fit")
    ax_q.plot(I, [100 * f.nrmse_laws for f in fits], "s--", color="black", ms=3.5, mfc="none",
              label="laws (6)–(11)")
    ax_q.plot(I, [100 * f.noise_nrmse for f in fits], ":", color="tab:gray", lw=2.0, label="sensor-noise floor")
    ax_q.set(xlabel="current (A)", ylabel="NRMSE (% of peak-to-peak force)", title="(b) fit error")
    ax_q.set_ylim(bottom=0.0)
    ax_q.legend(fontsize="small")

    # (c)–(h) Fig 3: parameters vs current
    Ig = np.linspace(0.0, max(float(I.max()), 1e-3), 200)
    law = np.array([theta_from_params(res.params, float(i)) for i in Ig])
    ref = np.array([theta_from_params(reference, float(i)) for i in Ig]) if reference is not None else None
    for n, (name, label, scale, unit) in enumerate(_THETA_PANELS):
        ax = fig.add_subplot(gs[1 + n // 3, n % 3])
        j = THETA_NAMES.index(name)
        y = np.array([f.theta[name] for f in fits]) * scale
        se = np.array([f.se.get(name, np.nan) for f in fits]) * abs(scale)
        well = np.array([f.determined.get(name) == "well" for f in fits])
        if ref is not None:
            ax.plot(Ig, ref[:, j] * scale, color="0.6", lw=1.0, ls=":", zorder=1)
        ax.plot(Ig, law[:, j] * scale, color="black", lw=1.3, zorder=2)
        ax.errorbar(I, y, yerr=2 * se, fmt="none", ecolor="tab:blue", elinewidth=0.9, capsize=2, zorder=3)
        ax.plot(I[well], y[well], "o", color="tab:blue", ms=5, zorder=4)
        if (~well).any():
            ax.plot(I[~well], y[~well], "o", mfc="white", mec="tab:blue", ms=5, zorder=4)
        lf = res.laws.get(name)
        extra = f"  (law rms {100 * lf.rel_rms:.1f} %)" if lf is not None else ""
        ax.set(xlabel="current (A)", ylabel=f"{unit}", title=f"({'cdefgh'[n]}) {label}{extra}")
        ax.grid(True, lw=0.5, alpha=0.5)
        if name == "sigma1":
            ax.axhline(0.0, color="0.3", lw=0.6)
    for ax in (ax_fv, ax_q):
        ax.grid(True, lw=0.5, alpha=0.5)
    # one legend for (c)–(h), below the panels so it never covers data
    p_handles = [Line2D([], [], ls="none", marker="o", ms=5, color="tab:blue"),
                 Line2D([], [], ls="none", marker="o", ms=5, mfc="white", mec="tab:blue"),
                 Line2D([], [], color="tab:blue", lw=0.9, marker="_", ms=8),
                 Line2D([], [], color="black", lw=1.3)]
    p_labels = ["identified (well determined)", "identified, poorly determined", "±2 standard errors",
                "approximating law (6)–(11)"]
    if ref is not None:
        p_handles.append(Line2D([], [], color="0.6", lw=1.0, ls=":"))
        p_labels.append("paper, Table I")
    fig.legend(p_handles, p_labels, loc="outside lower center", ncol=len(p_handles), frameon=False,
               fontsize="medium")

    nr = [f.nrmse for f in fits]
    poor = [k for k, v in res.summary_determined().items() if v != "well"]
    head = title if title is not None else ("LuGre identification: " + ", ".join(Path(s).name for s in res.sources))
    fig.suptitle(f"{head}\n{len(fits)} currents {I.min():.2f}–{I.max():.2f} A · optimiser {res.method} · "
                 f"fit NRMSE {100 * min(nr):.2f}–{100 * max(nr):.2f} % · Fc law rms {res.laws['Fc'].rms:.3g} N"
                 + (f" · poorly determined: {', '.join(poor)}" if poor else ""), fontsize="large")
    try:
        fig.savefig(out_path, format="png")
    except OSError as exc:
        raise ReportError(f"{out_path}: cannot write the figure: {exc.strerror or exc}") from None
