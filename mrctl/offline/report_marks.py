"""What the run report marks on its panels, and how it tells things apart.

- Colours and line styles: Okabe & Ito's colour-blind-safe palette; one
  colour per quantity in a one-run figure (and a line style apart where two
  share a panel), one (colour, line style) per run in an overlay, never two
  legend entries alike, and black dashed reserved for the demanded force.
- Shaded stretches: faults, latched faults (0 A with the output disabled
  until ``mrctl arm``) and skipped deadlines, each from the run log's rows
  (``fault`` bits, jumps of the tick index ``k``), drawn with a minimum
  visible width and merged where closer than it; when a kind is scattered
  all over the run it is marked along the panel's edge, not tinted over
  every trace, and the legend says so.
- Values beyond an axis the report scaled (the error panel is scaled to the
  metrics window): a triangle at the edge with the value, so a start-up
  error of -44.8 N is never clipped without a mark.

matplotlib is imported only inside the drawing functions.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mrctl.runlog.format import FAULT_BITS
from mrctl.util.palette import OKABE_ITO_NAMED

_DASH = (0, (4, 2))
_DASHDOT = (0, (6, 1.5, 1.5, 1.5))
_DOT = (0, (1, 1))
_LONGDASH = (0, (8, 2))
_DASHDOTDOT = (0, (5, 1.5, 1.5, 1.5, 1.5, 1.5))
_SHORTDASH = (0, (2.5, 1.5))

#: one quantity's (colour, line style) in a one-run figure: every colour distinct, and the two
#: quantities that share a panel (F and F_des) apart in line style too; a quantity alone in its
#: panel is solid, since a dash pattern breaks a noisy 1 kHz trace into a blur
QUANTITY_STYLE: dict[str, tuple[str, Any]] = {
    "F": (OKABE_ITO_NAMED["blue"], "-"),
    "F_des": (OKABE_ITO_NAMED["black"], _DASH),
    "error": (OKABE_ITO_NAMED["vermillion"], "-"),
    "current": (OKABE_ITO_NAMED["green"], "-"),
    "body_acc": (OKABE_ITO_NAMED["purple"], "-"),
    "stroke": (OKABE_ITO_NAMED["sky"], "-"),
    "tyre": (OKABE_ITO_NAMED["orange"], "-"),
}
#: each overlaid run's (colour, line style); black dashed stays the demand's
RUN_STYLES: tuple[tuple[str, Any], ...] = (
    (OKABE_ITO_NAMED["blue"], "-"), (OKABE_ITO_NAMED["vermillion"], _DASHDOT), (OKABE_ITO_NAMED["green"], _DOT),
    (OKABE_ITO_NAMED["purple"], _DASHDOTDOT), (OKABE_ITO_NAMED["orange"], _LONGDASH),
    (OKABE_ITO_NAMED["sky"], _SHORTDASH),
)
#: the demand (black dashed) and, in an overlay, a run's own demand where it differs (its colour, dashed)
DEMAND_STYLE = (OKABE_ITO_NAMED["black"], _DASH)

#: the LATCHED bit of the run log's fault column
LATCHED_BIT = next(v for n, v, _ in FAULT_BITS if n == "LATCHED")

#: how each kind of stretch is drawn: face colour, alpha, hatch, edge of the panel used when it is everywhere
SHADES: dict[str, dict[str, Any]] = {
    "fault": {"colour": OKABE_ITO_NAMED["vermillion"], "alpha": 0.20, "hatch": "///", "edge": 0.0},
    "latched": {"colour": "#4D4D4D", "alpha": 0.22, "hatch": "x", "edge": 0.0},
    "skipped deadlines": {"colour": OKABE_ITO_NAMED["orange"], "alpha": 0.30, "hatch": None, "edge": 0.955},
}
#: narrowest drawn stretch, as a share of the time axis (~5 px on a 7-inch panel at 200 dpi)
MIN_WIDTH_SHARE = 0.005
#: a kind drawn over more than this share of the time axis in this many separate stretches or more is
#: "throughout the run": marked along the panel's edge instead of tinting every trace
EVERYWHERE_SHARE = 0.25
EVERYWHERE_STRETCHES = 8
#: the strip at a panel's edge, as a share of its height
EDGE_STRIP = 0.045


def runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
    """[first, last] row index of each run of True."""
    m = np.asarray(mask, bool)
    if not m.any():
        return []
    d = np.diff(np.concatenate(([0], m.view(np.int8), [0])))
    return list(zip(np.flatnonzero(d == 1).tolist(), (np.flatnonzero(d == -1) - 1).tolist()))


def _fault_mask(fault: np.ndarray | None, latched: bool) -> np.ndarray | None:
    if fault is None:
        return None
    f = np.asarray(fault, float)
    ok = np.isfinite(f) & (f != 0)
    bits = np.where(ok, f, 0).astype(np.int64)
    is_latched = (bits & LATCHED_BIT) != 0
    return ok & (is_latched if latched else ~is_latched)


def fault_spans(t: np.ndarray, fault: np.ndarray | None, dt: float, latched: bool = False) -> list[tuple[float, float]]:
    """Time spans (s) of rows with a fault bit set (``latched``: with the
    LATCHED bit; otherwise those without it): from the first such row's
    time to one tick after the last, so a span is as wide as its ticks."""
    m = _fault_mask(fault, latched)
    if m is None:
        return []
    return [(float(t[a]), float(t[b]) + dt) for a, b in runs_of(m)]


def fault_ticks(fault: np.ndarray | None, latched: bool = False) -> int:
    """Rows with a fault bit set (``latched``: with the LATCHED bit; otherwise without it)."""
    m = _fault_mask(fault, latched)
    return 0 if m is None else int(m.sum())


def skipped_spans(t: np.ndarray, k: np.ndarray | None, dt: float) -> list[tuple[float, float]]:
    """Time spans (s) of skipped deadlines: where the tick index jumps,
    from one tick after the row before to the row after."""
    if k is None or len(k) < 2:
        return []
    jumps = np.flatnonzero(np.diff(np.asarray(k, float)) > 1.5)
    return [(float(t[i]) + dt, float(t[i + 1])) for i in jumps]


def skipped_ticks(k: np.ndarray | None) -> int:
    """Deadlines skipped: the tick indices missing between consecutive rows."""
    if k is None or len(k) < 2:
        return 0
    d = np.diff(np.asarray(k, float))
    d = d[np.isfinite(d)]
    return int(np.sum(np.maximum(np.rint(d) - 1, 0)))


def visible_spans(spans: list[tuple[float, float]], lo: float, hi: float,
                  min_width: float) -> list[tuple[float, float]]:
    """The spans within [lo, hi] as drawn: each at least ``min_width`` wide
    (widened about its middle) and merged with a neighbour closer than it,
    so one skipped tick on a 60 s run is a visible stripe and a burst of
    them one band."""
    out: list[list[float]] = []
    for a, b in sorted(spans):
        if b < lo or a > hi:
            continue
        if b - a < min_width:
            mid = 0.5 * (a + b)
            a, b = mid - 0.5 * min_width, mid + 0.5 * min_width
        if out and a - out[-1][1] < min_width:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def is_everywhere(drawn: list[tuple[float, float]], lo: float, hi: float) -> bool:
    """Many separate stretches that together would tint a good part of the
    axis: a serial or TCP run's skipped deadlines, a flaky link's faults."""
    width = sum(b - a for a, b in drawn)
    return len(drawn) >= EVERYWHERE_STRETCHES and width > EVERYWHERE_SHARE * max(hi - lo, 1e-12)


def shade(ax: Any, kind: str, drawn: list[tuple[float, float]], everywhere: bool,
          run_colour: str | None = None) -> None:
    """Draw one kind's stretches on a time panel: full height, or a strip
    along the panel's edge when the kind is everywhere. Each patch is
    labelled with the kind (tests find them by it)."""
    s = SHADES[kind]
    colour = run_colour or s["colour"]
    from matplotlib.colors import to_rgba

    face = to_rgba(colour, s["alpha"])
    edge = to_rgba(colour if kind != "latched" or run_colour else "0.3", 0.8)
    for a, b in drawn:
        if everywhere:
            ax.axvspan(a, b, ymin=s["edge"], ymax=s["edge"] + EDGE_STRIP, facecolor=to_rgba(colour, 0.9), lw=0,
                       zorder=1.5, label=kind)  # under the traces: a strip, never a veil
        else:
            ax.axvspan(a, b, facecolor=face, edgecolor=edge, hatch=s["hatch"], lw=0,
                       zorder=0.6 if kind != "skipped deadlines" else 0.5, label=kind)  # a fault over a skip


def legend_patch(kind: str, everywhere: bool) -> Any:
    """The legend's handle of one kind of stretch, drawn as it is on the panels."""
    from matplotlib.colors import to_rgba
    from matplotlib.patches import Patch

    s = SHADES[kind]
    if everywhere:
        return Patch(facecolor=to_rgba(s["colour"], 0.9), lw=0)
    return Patch(facecolor=to_rgba(s["colour"], s["alpha"]),
                 edgecolor="0.3" if kind == "latched" else s["colour"], hatch=s["hatch"], lw=0)


def mark_clipped(ax: Any, series: list[tuple[np.ndarray, np.ndarray, str]], lo: float, hi: float, unit: str,
                 max_labels: int = 4) -> int:
    """Mark the values beyond [lo, hi] of each ``(t, y, colour)``: a
    triangle at the edge at each stretch's extreme, in the line's colour;
    the largest ``max_labels`` values written beside them (once where runs
    share one), stacked where they would overlap. Returns the number of
    stretches marked (their markers' and texts' gid is ``clipped``)."""
    marks = []
    for t, y, colour in series:
        yy = np.asarray(y, float)
        over = np.isfinite(yy) & ((yy > hi) | (yy < lo))
        for a, b in runs_of(over):
            j = a + int(np.argmax(np.abs(yy[a:b + 1] - 0.5 * (lo + hi))))
            marks.append((float(t[j]), float(yy[j]), colour))
    if not marks:
        return 0
    from matplotlib.transforms import blended_transform_factory

    for colour in dict.fromkeys(c for _, _, c in marks):
        for up in (True, False):
            pts = [x for x, v, c in marks if c == colour and (v > hi) == up]
            if pts:
                ax.plot(pts, [hi if up else lo] * len(pts), "^" if up else "v", color=colour, ms=7, mec="black",
                        mew=0.6, clip_on=False, zorder=30, gid="clipped", label="_beyond the axis")
    trans = blended_transform_factory(ax.transData, ax.transAxes)
    x0, x1 = ax.get_xlim()
    texts: dict[str, tuple[float, bool, str]] = {}
    for x, v, colour in sorted(marks, key=lambda m: -abs(m[1])):
        text = f"{v:.3g} {unit} at t = {x:.3g} s".replace("-", "\u2212")
        if text not in texts and len(texts) < max_labels:
            texts[text] = (x, v > hi, colour)
    placed: list[tuple[float, bool]] = []
    for text, (x, up, colour) in sorted(texts.items(), key=lambda kv: kv[1][0]):
        near = sum(1 for px, pu in placed if pu == up and abs(px - x) < 0.2 * abs(x1 - x0))
        placed.append((x, up))
        dy = 4 + 12 * near
        ax.annotate(text, (x, 1.0 if up else 0.0), xycoords=trans, xytext=(6, -dy if up else dy),
                    textcoords="offset points", va="top" if up else "bottom", ha="left", fontsize="small",
                    color=colour, zorder=31, gid="clipped",  # in its line's colour: whose value it is
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})
    return len(marks)


def clipped_handle() -> Any:
    """The legend's handle for the clipped-value markers."""
    from matplotlib.lines import Line2D

    return Line2D([], [], ls="none", marker="v", color="0.5", mec="black", mew=0.6, ms=7)
