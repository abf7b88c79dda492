"""The run report's figure: its panels, their layout, lines, shading and legend.

:func:`draw_runs` draws runs that :mod:`mrctl.offline.report` has read and
measured: the time panels stacked on one time axis with the loops beside
them (no empty panel), each quantity or run in its own colour and line
style, faults, latched faults and skipped deadlines shaded
(:mod:`mrctl.offline.report_marks`), a value beyond the error axis marked
with its value, one legend below the panels. matplotlib is imported only
inside the functions.
"""

from __future__ import annotations

import math
import textwrap
from typing import Any, Sequence

import numpy as np

from mrctl.errors import BadInput
from mrctl.offline.report_marks import (DEMAND_STYLE, MIN_WIDTH_SHARE, QUANTITY_STYLE, RUN_STYLES, SHADES,
                                        clipped_handle, is_everywhere, legend_patch, mark_clipped, shade,
                                        visible_spans)



class ReportError(BadInput):
    """A run file cannot be reported on; the message says why, for the CLI user."""


__all__ = ["ReportError", "PANELS", "TIME_PANELS", "DEFAULT_PANELS", "QUARTER_CAR_PANELS", "check_panels",
           "draw_runs", "count_text", "events_line", "palette_png"]

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
#: a one-run figure's legend name of each drawn quantity
_QUANTITY_LABEL = {"error": "tracking error $F - F_{des}$", "current": "coil current $I$",
                   "body_acc": "body acceleration", "stroke": "suspension stroke", "tyre": "tyre deflection"}
#: the kinds of shaded stretch, in the legend's order
_KINDS = ("latched", "fault", "skipped deadlines")


def check_panels(panels: Sequence[str]) -> list[str]:
    """``--panels`` as a list; ReportError naming any unknown panel (checked
    before any file is touched)."""
    panels = list(panels)
    unknown = [q for q in panels if q not in PANELS]
    if unknown or not panels:
        raise ReportError(f"--panels: unknown panel(s) {', '.join(unknown) or '(none given)'}; "
                          f"choose from {', '.join(PANELS)}")
    return panels


def count_text(kind: str, m: dict[str, Any]) -> str:
    """What a kind of stretch counts, said: ``fault: 100 ticks (5.0 % of rows)``."""
    n = m["ticks"][kind]
    if kind == "skipped deadlines":
        return f"skipped deadlines: {n} ({100.0 * n / max(1, m['deadlines']):.2g} % of deadlines)"
    what = "latched (0 A, output off until mrctl arm)" if kind == "latched" else "fault"
    return f"{what}: {n} tick{'s' if n != 1 else ''} ({100.0 * n / max(1, m['rows']):.2g} % of rows)"


def events_line(m: dict[str, Any]) -> str:
    """The caption's line of a run's faults and skipped deadlines ('' when it had none)."""
    parts = [count_text(kind, m) for kind in _KINDS if m["ticks"][kind]]
    return "   ·   ".join(parts)


def _layout(fig: Any, panels: Sequence[str]) -> dict[str, Any]:
    """One Axes per panel, none empty: the time panels stacked on one time
    axis (left), the loops beside them (right), each labelled with its name."""
    time = [q for q in panels if q in TIME_PANELS]
    loops = [q for q in panels if q not in TIME_PANELS]
    nt, nl = max(1, len(time)), max(1, len(loops))
    if time and loops:
        gs = fig.add_gridspec(nt * nl, 2, width_ratios=(1.85, 1.0))
    else:
        gs = fig.add_gridspec(nt if time else 1, 1 if time else nl)
    axes: dict[str, Any] = {}
    first = None
    for q in panels:
        if q in time:
            i = time.index(q)
            spec = gs[i * nl:(i + 1) * nl, 0] if loops else gs[i, 0]
            axes[q] = fig.add_subplot(spec, label=q, sharex=first)
            first = first or axes[q]
        else:
            j = loops.index(q)
            axes[q] = fig.add_subplot(gs[j * nt:(j + 1) * nt, 1] if time else gs[0, j], label=q)
    return axes


def _run_style(n: int) -> tuple[str, Any]:
    """Run n's (colour, line style) in an overlay: distinct for the first 36 runs."""
    colour, _ = RUN_STYLES[n % len(RUN_STYLES)]
    return colour, RUN_STYLES[(n + n // len(RUN_STYLES)) % len(RUN_STYLES)][1]


def draw_runs(loaded: list[tuple[dict[str, np.ndarray], dict[str, Any]]], quantity: str, panels: Sequence[str],
              title: str | None = None, size: tuple[float, float] | None = None,
              time: tuple[float, float] | None = None) -> Any:
    """The Figure of runs read and measured by :func:`mrctl.offline.report.build_figure`:
    ``loaded`` is each run's columns and figures (its ``label``, ``caption``,
    ``window``, spans and tick counts); ``quantity`` the force drawn (``F_true`` or ``F``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    single = len(loaded) == 1
    n_time = sum(q in TIME_PANELS for q in panels)
    if size is None:
        size = (12.0, (2.3 * n_time if n_time else 4.2) + 1.7 + 0.5 * len(loaded))
    fig = Figure(figsize=size, dpi=200, layout="constrained")
    FigureCanvasAgg(fig)
    axes = _layout(fig, panels)
    t_lo = min(float(c["t"][0]) for c, _ in loaded)
    t_hi = max(float(c["t"][-1]) for c, _ in loaded)
    if time is not None:
        t_lo, t_hi = time
    time_axes = [axes[q] for q in panels if q in TIME_PANELS]
    min_w = MIN_WIDTH_SHARE * (t_hi - t_lo)
    lines = []
    for n, (cols, m) in enumerate(loaded):
        t = cols["t"]
        colour, style = _run_style(n)
        sel = (t >= t_lo) & (t <= t_hi)
        w = sel & (t >= m["t_start"])  # loops over the metrics window only (no stray start-up cycle)

        def look(q: str, **kw: Any) -> dict[str, Any]:
            """A quantity's line: its own colour and style in a one-run figure, the run's in an overlay."""
            c, ls = QUANTITY_STYLE[q] if single else (colour, style)
            label = (_QUANTITY_LABEL.get(q, q) if single else m["label"])
            return {"color": c, "ls": ls, "lw": 1.1, "zorder": 2 + n, "label": label, **kw}
        act = look("F", lw=1.7 if single else 1.1, alpha=0.85 if single else 0.9,
                   **({"label": "true $F$ (simulated plant)" if quantity == "F_true" else "load-cell $F$"}
                      if single else {}))
        des = None if n and _same_demand(loaded, n) else dict(
            color=DEMAND_STYLE[0] if n == 0 else colour, ls=DEMAND_STYLE[1], lw=1.1, zorder=20, alpha=0.9,
            label="desired $F_{des}$" if n == 0 else f"desired $F_{{des}}$, {m['label']}")
        F, F_des = cols["F"], cols["F_des"]
        draw = {
            "force": lambda ax: (ax.plot(t[sel], F[sel], **act),
                                 des is not None and ax.plot(t[sel], F_des[sel], **des)),
            "error": lambda ax: ax.plot(t[sel], (F - F_des)[sel], **look("error")),
            "current": lambda ax: ax.plot(t[sel], cols["I"][sel], **look("current")),
            "fv": lambda ax: (ax.plot(1e3 * cols["v"][w], F[w], **act),
                              des is not None and ax.plot(1e3 * cols["v"][w], F_des[w], **des)),
            "fx": lambda ax: (ax.plot(1e3 * cols["x"][w], F[w], **act),
                              des is not None and ax.plot(1e3 * cols["x"][w], F_des[w], **des)),
            "body_acc": lambda ax: ax.plot(t[sel], cols["a_sprung"][sel], **look("body_acc")),
            "stroke": lambda ax: ax.plot(t[sel], 1e3 * cols["x"][sel], **look("stroke")),
            "tyre": lambda ax: ax.plot(t[sel], 1e3 * cols["tyre_defl"][sel], **look("tyre")),
        }
        for q in panels:
            draw[q](axes[q])
        # what happened, in every time panel: latched faults, faults, skipped deadlines, at least
        # min_w wide; along the panel's edge where a kind is everywhere
        m["drawn"] = {}
        for kind, spans in (("latched", m["latched_spans"]), ("fault", m["fault_spans"]),
                            ("skipped deadlines", m["skipped_spans"])):
            drawn = visible_spans(spans, t_lo, t_hi, min_w)
            m["drawn"][kind] = (drawn, is_everywhere(drawn, t_lo, t_hi))
            for ax in time_axes:
                shade(ax, kind, drawn, m["drawn"][kind][1], None if single else colour)
        lines.append(m["caption"] if single else f"{m['label']}: {m['caption']}")
    # the settling window (what the metrics leave out), shaded in every time panel
    t_settle = max(m["t_start"] for _, m in loaded)
    if t_settle > t_lo:
        for ax in time_axes:
            ax.axvspan(t_lo, min(t_settle, t_hi), color="0.9", zorder=0, lw=0, label="settling")
    clipped = 0
    for q, ax in axes.items():
        what, ylabel = PANELS[q]
        if q == "force":  # which force every run is drawn and judged on
            what += ": the plant's $F_{true}$" if quantity == "F_true" else ": the load cell's $F$"
        letter = "abcdefghij"[panels.index(q)]
        if q in ("fv", "fx"):
            window = f" ({loaded[0][1]['window']})" if single else " (metrics windows)"
            ax.set(xlabel="velocity (mm/s)" if q == "fv" else "displacement (mm)", ylabel=ylabel,
                   title=f"({letter}) {what}{window}")
        else:
            last = ax is time_axes[-1]
            ax.set(xlabel="time (s)" if last else "", ylabel=ylabel, title=f"({letter}) {what}")
            ax.tick_params(labelbottom=last)
            ax.set_xlim(t_lo, t_hi)
        if q == "error":
            ax.axhline(0.0, color="0.3", lw=0.6, zorder=1)
            lim = _error_limits(loaded, t_lo, t_hi)
            if lim is not None:  # scaled to the metrics window: a start-up transient is marked, not drawn
                ax.set_ylim(*lim)
                series = []
                for n, (cols, m) in enumerate(loaded):
                    sel = (cols["t"] >= t_lo) & (cols["t"] <= t_hi)
                    series.append((cols["t"][sel], (cols["F"] - cols["F_des"])[sel],
                                   QUANTITY_STYLE["error"][0] if single else _run_style(n)[0]))
                clipped = mark_clipped(ax, series, *lim, "N")
        ax.grid(True, lw=0.5, alpha=0.5)
    handles, labels = _legend(axes, loaded, single, bool(time_axes), t_settle > t_lo, clipped, Patch)
    labels = ["\n".join(textwrap.wrap(lab, 60)) for lab in labels]  # a long label wraps, never leaves the page
    fig.legend(handles, labels, loc="outside lower center", ncol=3 if len(handles) > 4 else len(handles),
               frameon=False, fontsize="medium")
    head = title if title is not None else ", ".join(m["label"] for _, m in loaded)
    width = int(size[0] * (10.0 if single else 12.0))  # characters a caption line holds at its font size
    fig.suptitle("\n".join(_wrap(line, width) for line in [head, *lines]), fontsize="large" if single else "medium")
    return fig


def _wrap(text: str, width: int) -> str:
    """A caption's lines kept within ``width`` characters, broken at its ``·``
    separators first (a figure narrower than the default keeps its caption)."""
    out = []
    for line in text.split("\n"):
        cur = ""
        for part in line.split("   ·   "):
            if cur and len(cur) + 7 + len(part) > width:
                out.append(cur)
                cur = part
            else:
                cur = f"{cur}   ·   {part}" if cur else part
        out.extend(textwrap.wrap(cur, width) or [""])
    return "\n".join(out)


def _legend(axes: dict[str, Any], loaded: list, single: bool, shaded: bool, settling: bool, clipped: int,
            Patch: Any) -> tuple[list, list[str]]:
    """One legend below the panels, so none covers data: every line once, each kind of
    stretch once with what it counts, the clipped-value marker when there is one."""
    handles, labels = [], []
    for ax in axes.values():
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels and lab not in ("settling", *_KINDS):
                handles.append(h)
                labels.append(lab)
    if shaded:
        for kind in _KINDS:
            runs = [m for _, m in loaded if m["drawn"][kind][0]]
            if not runs:
                continue
            everywhere = any(m["drawn"][kind][1] for m in runs)
            where = (" throughout the run: marked along the "
                     + ("top" if SHADES[kind]["edge"] > 0.5 else "bottom") + " edge") if everywhere else ""
            if single:
                handles.append(legend_patch(kind, everywhere))
                labels.append(count_text(kind, runs[0]) + where)
            else:  # each run's stretches in its colour; the counts are in its caption line
                s = SHADES[kind]
                handles.append(Patch(facecolor=(0.5, 0.5, 0.5, 0.9 if everywhere else s["alpha"]), edgecolor="0.2",
                                     hatch=None if everywhere else s["hatch"], lw=0))
                labels.append({"latched": "latched (0 A, output off until mrctl arm)"}.get(kind, kind)
                              + ", in the run's colour" + where)
    if settling:
        handles.append(Patch(facecolor="0.9", lw=0))
        labels.append("settling (not in metrics)")
    if clipped:
        handles.append(clipped_handle())
        labels.append("beyond the error axis: value and time written beside it")
    return handles, labels


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


def palette_png(data: bytes) -> bytes:
    """A PNG with an adaptive 256-colour palette, its resolution kept: a figure
    of many noisy traces is a third of its size, no difference to the eye
    (Pillow, which matplotlib needs anyway; the RGB file as it was without it)."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - matplotlib depends on Pillow
        return data
    import io

    img = Image.open(io.BytesIO(data))
    out = io.BytesIO()
    dpi = img.info.get("dpi")
    img.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(
        out, format="PNG", optimize=True, **({"dpi": dpi} if dpi else {}))
    return out.getvalue()
