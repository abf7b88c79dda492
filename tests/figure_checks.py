"""Golden properties of a drawn matplotlib figure, shared by the figure tests:
what a reviewer checks by eye, checked on the Figure's artists (never pixels)."""

from __future__ import annotations

import re

import numpy as np
from matplotlib.colors import to_hex


def axes_without_data(fig) -> list[str]:
    """Labels of the Axes that show nothing: no line with a finite point, no
    bar, image or scatter, no text (a text panel's table counts as data)."""
    empty = []
    for ax in fig.axes:
        lines = any(np.isfinite(np.asarray(ln.get_ydata(), float)).any() for ln in ax.lines
                    if len(ln.get_ydata()))
        shown = lines or ax.images or ax.collections or any(p.get_width() > 0 for p in ax.patches
                                                          if hasattr(p, "get_width")) or ax.texts
        if not shown:
            empty.append(ax.get_label() or ax.get_title())
    return empty


def doubled_units(fig) -> list[str]:
    """Axis labels that say their unit twice: ``time from 16 s (s)``, ``(s) (s)``."""
    bad = []
    for ax in fig.axes:
        for label in (ax.get_xlabel(), ax.get_ylabel()):
            units = re.findall(r"\(([^()]+)\)", label)
            if len(units) != len(set(units)):
                bad.append(label)
                continue
            for u in units:
                rest = label.replace(f"({u})", "")
                if re.search(rf"(^|[\s\d]){re.escape(u)}(\s|$)", rest):
                    bad.append(label)
    return bad


def line_key(line) -> tuple:
    """A line's look: colour, dash pattern (matplotlib keeps the unscaled one), marker and its fill."""
    drawn = line.get_linestyle() not in ("None", "none", "")
    marker = line.get_marker() if line.get_marker() not in ("None", "none", "", None) else None
    fill = (to_hex(line.get_markerfacecolor()), to_hex(line.get_markeredgecolor())) if marker else None
    return to_hex(line.get_color()) if drawn else None, line._unscaled_dash_pattern if drawn else None, marker, fill


def legends_with_lookalikes(fig) -> list[list[str]]:
    """Each legend (of the figure or of an Axes) whose line entries are not all told apart."""
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    bad = []
    for leg in legends:
        keys = [(line_key(h), t.get_text()) for h, t in zip(leg.legend_handles, leg.get_texts())
                if h.__class__.__name__ == "Line2D"]
        if len({k for k, _ in keys}) != len(keys):
            bad.append([t for _, t in keys])
    return bad
