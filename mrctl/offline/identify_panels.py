"""The panels of the identification figures (:mod:`mrctl.offline.identify_figure`).

Each function draws one panel (or a set of them) on Axes it is given and
labels each Axes with what it shows (``ax.get_label()``: tests find them by
it). Colours are Okabe & Ito's colour-blind-safe palette; measured data are
black, the model vermillion and dashed, so grey print tells them apart too.
matplotlib is imported by the caller.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from mrctl.offline.identify.result import IdentificationResult, Score, Trace
from mrctl.util.palette import OKABE_ITO

__all__ = ["held_out", "scores_panel", "trace_panels", "theta_panels", "conditions_panels",
           "conditioned", "conditions_vary", "level_table", "window"]

_MEASURED = {"color": OKABE_ITO[0], "ls": "-"}
_MODEL = {"color": OKABE_ITO[5], "ls": (0, (4, 1.5))}
#: one marker per level (with its colour): told apart without colour too
_LEVEL_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">", "h", "p")
#: (Θ name, label, unit scale, unit text) of the per-level panels (the paper's Fig 3)
THETA_PANELS = (
    ("Fc", "Coulomb force $F_c$", 1.0, "N"),
    ("Fs", "stiction force $F_s$", 1.0, "N"),
    ("vs", "Stribeck velocity $v_s$", 1e3, "mm/s"),
    ("sigma0", "bristle stiffness $\\sigma_0$", 1e-3, "kN/m"),
    ("sigma1", "bristle damping $\\sigma_1$", 1.0, "N·s/m"),
    ("sigma2", "viscous coefficient $\\sigma_2$", 1.0, "N·s/m"),
)


def held_out(s: Score) -> float:
    """A record's held-out NRMSE through the written set (its laws) where it has one."""
    return s.nrmse_laws if s.nrmse_laws is not None else s.nrmse


def level_style(k: int) -> dict[str, Any]:
    """Level k's colour and marker."""
    return {"color": OKABE_ITO[1 + k % 7], "marker": _LEVEL_MARKERS[k % len(_LEVEL_MARKERS)]}


def window(tr: Trace, show_s: float) -> slice:
    """The first ``show_s`` seconds of the trace, up to its first gap (segments are concatenated)."""
    dt = np.diff(tr.t)
    if dt.size == 0:
        return slice(0, tr.t.size)
    step = float(np.median(dt))
    n = int(round(show_s / step)) if step > 0 else tr.t.size
    gaps = np.flatnonzero(dt > 1.5 * step)
    end = int(gaps[0]) + 1 if gaps.size else tr.t.size
    return slice(0, max(2, min(n, end)))


def trace_panels(ax_t: Any, ax_v: Any, tr: Trace, head: str, show_s: float, legend: bool) -> None:
    """Measured and predicted force over the first ``show_s`` seconds of a
    trace (absolute time in its record), and its force–velocity loop."""
    w = window(tr, show_s)
    ax_t.plot(tr.t[w], tr.F_meas[w], lw=1.0, label="measured", **_MEASURED)
    ax_t.plot(tr.t[w], tr.F_pred[w], lw=1.1, alpha=0.9, label="model", **_MODEL)
    ax_t.set(xlabel="time in the record (s)", ylabel="force (N)", title=head)
    step = max(1, tr.v.size // 3000)  # a few thousand points show the loop
    ax_v.plot(1e3 * tr.v[::step], tr.F_meas[::step], ".", ms=1.5, color="0.15", alpha=0.35, rasterized=True,
              label="measured")
    ax_v.plot(1e3 * tr.v[::step], tr.F_pred[::step], ".", ms=1.2, color=_MODEL["color"], alpha=0.35,
              rasterized=True, label="model")
    ax_v.set(xlabel="velocity (mm/s)", ylabel="force (N)",
             title=f"force–velocity, {'held-out' if tr.part == 'holdout' else 'fitted'} part")
    for ax in (ax_t, ax_v):
        ax.title.set_fontsize("medium")
        ax.grid(True, lw=0.5, alpha=0.5)
    if legend:
        ax_t.legend(loc="upper right", fontsize="small")


def scores_panel(ax: Any, res: IdentificationResult) -> None:
    """Held-out NRMSE of every record: per level (one column of points per
    level, its median a bar), or per record (broadband); the fitted part's
    where nothing was held out, and the title says so."""
    scores = res.holdout or res.train
    part = "held-out" if res.holdout else "fitted (nothing held out)"
    ax.set_label("scores")
    if any(s.level is not None for s in scores):
        levels = sorted({float(s.level) for s in scores if s.level is not None})
        for k, lv in enumerate(levels):
            y = np.array([100 * held_out(s) for s in scores if s.level == lv])
            st = level_style(k)
            ax.plot(np.full(y.size, k), y, ls="none", ms=6, mec="black", mew=0.5, alpha=0.9,
                    label=f"{lv:.4g} {res.unit}", **st)
            ax.plot([k - 0.3, k + 0.3], [np.median(y)] * 2, color="black", lw=2.0)
        ax.set_xticks(range(len(levels)), [f"{lv:.4g}" for lv in levels],
                      rotation=45 if len(levels) > 6 else 0)
        ax.set(xlabel=f"level ({res.unit})", title=f"{part} NRMSE per record (bar: the level's median)")
    else:
        scores = sorted(scores, key=lambda s: -s.nrmse)  # worst first, as the traces beside
        y = np.array([100 * s.nrmse for s in scores])
        ax.barh(range(len(scores)), y, height=0.35, color=OKABE_ITO[4])
        for i, v in enumerate(y):
            ax.text(v, i, f" {v:.2f} %", va="center", ha="left", fontsize="small")
        ax.set_yticks(range(len(scores)), [s.record for s in scores], fontsize="small")
        ax.set_ylim(len(scores) - 0.5, -0.5)
        ax.set(xlabel=f"{part.split(' ')[0]} NRMSE (%)", title=f"{part} NRMSE per record")
        ax.set_xlim(0.0, 1.3 * float(y.max()) if y.size and y.max() > 0 else 1.0)
        ax.title.set_fontsize("medium")
        return
    ax.set_ylabel(f"{part.split(' ')[0]} NRMSE (%)")
    ax.set_ylim(bottom=0.0)
    ax.title.set_fontsize("medium")
    ax.grid(True, axis="y", lw=0.5, alpha=0.5)


def theta_panels(axes: list[Any], res: IdentificationResult, levels: list[dict]) -> None:
    """The six parameters per level (±2 standard errors, hollow where poorly
    determined) with the paper's laws (6)–(11) and, when written, the table:
    what the laws make of the levels (the paper's Fig 3)."""
    from mrctl.offline.identify.laws import theta_from_params
    from mrctl.offline.identify.model import THETA_NAMES

    u = np.array([lv["level"] for lv in levels], float)
    grid = np.linspace(float(u.min()), float(u.max()), 200)
    paper = dataclasses.replace(res.params, table=None)
    law = np.array([theta_from_params(paper, float(g)) for g in grid])
    table = (np.array([theta_from_params(res.params, float(g)) for g in grid]) if res.params.table is not None
             else None)
    for n, (ax, (name, label, scale, unit)) in enumerate(zip(axes, THETA_PANELS)):
        ax.set_label(f"theta-{name}")
        j = THETA_NAMES.index(name)
        y = np.array([lv["theta"][name] for lv in levels]) * scale
        se = np.array([(lv.get("std_error") or {}).get(name, np.nan) for lv in levels], float) * abs(scale)
        well = np.array([(lv.get("determined") or {}).get(name) == "well" for lv in levels])
        ax.plot(grid, law[:, j] * scale, color="black", lw=1.3, ls="-", label="laws (6)–(11)")
        if table is not None:
            ax.plot(grid, table[:, j] * scale, color=OKABE_ITO[3], lw=1.2, ls=(0, (5, 1.5, 1.5, 1.5)),
                    label="laws: table (written)")
        if np.isfinite(se).any():
            ax.errorbar(u, y, yerr=2 * np.nan_to_num(se), fmt="none", ecolor=OKABE_ITO[4], elinewidth=0.9, capsize=2)
        ax.plot(u[well], y[well], "o", color=OKABE_ITO[4], ms=5, ls="none", label="per level, ±2 s.e.")
        if (~well).any():
            ax.plot(u[~well], y[~well], "o", color=OKABE_ITO[4], mfc="white", mec=OKABE_ITO[4], ms=5, ls="none",
                    label="per level, poorly determined")
        ax.set(xlabel=f"input ({res.unit})", ylabel=f"{label.rsplit(' ', 1)[1]} ({unit})", title=label)
        ax.title.set_fontsize("medium")
        ax.grid(True, lw=0.5, alpha=0.5)
        if name == "sigma1":
            ax.axhline(0.0, color="0.3", lw=0.6)
    # one legend, in the first panel, for what any panel draws (a hollow point may be in another panel only)
    from matplotlib.lines import Line2D

    handles, labels = axes[0].get_legend_handles_labels()
    poorly = any((lv.get("determined") or {}).get(name) != "well" for lv in levels
                 for name, *_ in THETA_PANELS)
    if poorly and "per level, poorly determined" not in labels:
        handles.append(Line2D([], [], ls="none", marker="o", color=OKABE_ITO[4], mfc="white", mec=OKABE_ITO[4], ms=5))
        labels.append("per level, poorly determined")
    axes[0].legend(handles, labels, fontsize="x-small", loc="best")


def conditioned(res: IdentificationResult) -> list[Score]:
    """The held-out scores that carry a test condition (stroke and frequency)."""
    return [s for s in res.holdout if s.level is not None and s.stroke_m is not None and s.frequency_hz is not None]


def conditions_vary(res: IdentificationResult, spread: float = 0.05) -> bool:
    """The records differ in stroke or frequency by more than ``spread`` of
    their median: a plot against them says something (mrctl's own runs at one
    stroke and frequency differ only by the cycles' measurement)."""
    sc = conditioned(res)
    for key in ("stroke_m", "frequency_hz"):
        x = np.array([float(getattr(s, key)) for s in sc])
        if x.size and np.ptp(x) > spread * abs(float(np.median(x))):
            return True
    return False


def conditions_panels(ax_stroke: Any, ax_freq: Any, res: IdentificationResult) -> None:
    """Held-out NRMSE against stroke and against frequency, one colour and
    marker per level: where one Θ per level holds across the conditions and
    where not. Filled: through the written set; hollow: the level's own fit,
    where it differs from the written set's."""
    scores = conditioned(res)
    levels = sorted({float(s.level) for s in scores})  # type: ignore[arg-type]
    ax_stroke.set_label("stroke")
    ax_freq.set_label("frequency")
    for k, lv in enumerate(levels):
        st = level_style(k)
        mine = sorted((s for s in scores if s.level == lv), key=lambda s: s.stroke_m)
        for ax, key, scale in ((ax_stroke, "stroke_m", 1e3), (ax_freq, "frequency_hz", 1.0)):
            x = np.array([getattr(s, key) for s in mine]) * scale
            y = np.array([100 * held_out(s) for s in mine])
            y0 = np.array([100 * s.nrmse for s in mine])
            ax.plot(x, y, ls="none", ms=6, mec="black", mew=0.5, label=f"{lv:.4g} {res.unit}", **st)
            differ = np.abs(y - y0) > 1e-3
            if differ.any():
                ax.plot(x[differ], y0[differ], ls="none", mfc="white", mec=st["color"], marker=st["marker"], ms=5)
    for ax, label in ((ax_stroke, "stroke, peak to peak (mm)"), (ax_freq, "frequency (Hz)")):
        ax.set(xlabel=label, ylabel="held-out NRMSE (%)",
               title=f"held-out NRMSE against {label.split(',')[0].split(' (')[0]}")
        ax.title.set_fontsize("medium")
        ax.grid(True, lw=0.5, alpha=0.5)
        ax.set_ylim(bottom=0.0)
    # below the points: NRMSE rarely nears 0, and the axis starts there
    ax_stroke.legend(fontsize="small", title="level", loc="lower right", ncol=min(4, max(1, len(levels))))


def level_table(ax: Any, res: IdentificationResult) -> None:
    """Per level: records, the held-out NRMSE's median and range, as text."""
    ax.set_label("levels-table")
    ax.axis("off")
    levels = sorted({float(s.level) for s in res.holdout if s.level is not None})
    rows = [f"{'level':>9} {'records':>7} {'median':>7} {'range':>13}"]
    for lv in levels:
        y = np.array([100 * held_out(s) for s in res.holdout if s.level == lv])
        rows.append(f"{lv:>7.4g} {res.unit} {y.size:>7d} {np.median(y):6.2f}% {y.min():5.2f}–{y.max():5.2f}%")
    worst = max(res.holdout, key=held_out)
    text = ("held-out force NRMSE per level\n(through the written set, laws: " f"{res.params.laws})\n\n"
            + "\n".join(rows) + f"\n\nworst record: {worst.record}\n  at {worst.level:.4g} {res.unit}: "
            f"{100 * held_out(worst):.2f} %\nevery record: the JSON summary's holdout")
    ax.text(0.0, 1.0, text, va="top", ha="left", family="monospace", fontsize="small", transform=ax.transAxes)
