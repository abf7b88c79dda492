"""``mrctl report RESULTS``: a sweep's figure.

- Monte Carlo (the table has draws): the empirical CDF and a box plot of
  the metric per grid cell (e.g. per law), with the fraction of points at
  or below a bound ("force_nrmse ≤ 0.01: closed 97 %, smooth 31 %");
- a grid of two or more axes: a heat map of the metric over the first two
  (one panel per value of the others, at most 6); one axis: a line.

Failed points (status other than ok) carry no metric and are counted.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from mrctl.errors import BadInput
from mrctl.sweep.table import TAIL, read_results
from mrctl.util.palette import OKABE_ITO

MAX_PANELS = 6


def _num(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan


def _sort_key(v: str) -> tuple[int, Any]:
    x = _num(v)
    return (0, x) if math.isfinite(x) else (1, v)


def summarise(cols: list[str], rows: list[dict[str, str]], metric: str, bound: float
              ) -> tuple[list[str], list[str], dict[tuple[str, ...], np.ndarray], list[str]]:
    """(grid axes, random axes, metric per grid cell, text lines) of a results table."""
    if metric not in cols:
        raise BadInput(f"--metric {metric}: not in this table (its metrics: "
                       f"{', '.join(c for c in cols[cols.index('seed') + 1:] if c not in TAIL)})")
    axes = cols[cols.index("config_hash") + 1: cols.index("seed")]
    mc = any(r.get("seed", "") != "" for r in rows)
    # a draw's values are the same in every grid cell (common random numbers): the axes that vary
    # among the rows of one draw are the grid's, the others are drawn
    seeds = Counter(r.get("seed", "") for r in rows)
    one = [r for r in rows if r.get("seed", "") == seeds.most_common(1)[0][0]]  # a partial table: the fullest draw
    grid = [a for a in axes if len({r[a] for r in one}) > 1]
    rand = [a for a in axes if mc and a not in grid and len({r[a] for r in rows}) > 1]
    cells: dict[tuple[str, ...], list[float]] = {}
    for r in rows:
        v = _num(r[metric]) if r["status"] in ("ok", "fault") else math.nan
        cells.setdefault(tuple(r[a] for a in grid), []).append(v)
    arrays = {k: np.asarray(v, float) for k, v in sorted(cells.items(), key=lambda kv: [_sort_key(x) for x in kv[0]])}
    failed = sum(r["status"] not in ("ok",) for r in rows)
    lines = [f"{len(rows)} points, {failed} not ok" + (f"; {len(rows) // max(1, len(arrays))} draws per cell" if mc else "")]
    if mc:
        parts = []
        for k, a in arrays.items():
            good = np.isfinite(a)
            n_ok = int(np.sum(good & (np.where(good, a, np.inf) <= bound)))
            parts.append(f"{' '.join(k) or 'all'} {n_ok} of {a.size} points ({100 * n_ok / max(1, a.size):.0f} %)")
        lines.append(f"{metric} ≤ {bound:g}: " + ", ".join(parts))
    return grid, rand, arrays, lines


#: print resolution of the sweep figures (a paper's figure: 200 dpi or more)
DPI = 200
LINE_STYLES = ("-", "--", "-.", ":")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
#: units of the key paths a sweep varies most, for axis labels
_KEY_UNITS = {"demand.c_des": "N·s/m", "plant.driver_tau_s": "s", "safety.I_max": "A", "rate_hz": "Hz",
              "excitation.amplitude_m": "m", "excitation.frequency_hz": "Hz", "inverse.law": ""}


def metric_label(metric: str, width: int = 52) -> str:
    """An axis label for ``metric``: its name and meaning (mrctl.sweep.metrics.METRIC_DOCS)
    without a closing remark in brackets (a unit stays), wrapped to ``width``
    characters so it never runs off the figure."""
    import textwrap

    from mrctl.sweep.metrics import METRIC_DOCS

    doc = METRIC_DOCS.get(metric)
    if not doc:
        return metric
    head, _, tail = doc.rpartition(" (")
    if head and tail.endswith(")") and len(tail) > 8:  # "(mrctl simulate's force NRMSE)": a remark, not a unit
        doc = head
    return "\n".join(textwrap.wrap(f"{metric}: {doc}", width))


def key_label(key: str) -> str:
    """An axis label for a key path: the path and its unit, where the path says it (``_s``, ``_A``, ...)."""
    unit = _KEY_UNITS.get(key)
    if unit is None:
        tail = key.rsplit(".", 1)[-1]
        unit = next((u for suffix, u in (("_s", "s"), ("_A", "A"), ("_m", "m"), ("_hz", "Hz"), ("_N", "N"),
                                         ("_mps", "m/s")) if tail.endswith(suffix)), "")
    return f"{key} ({unit})" if unit else key


def make_sweep_report(path: str, out: str, metric: str = "force_nrmse", bound: float = 0.01,
                      title: str | None = None) -> list[str]:
    """Draw the figure of a results table into ``out``; the summary lines (also in the figure)."""
    suffix = Path(out).suffix.lower()
    if suffix not in (".png", ".pdf", ".svg"):
        raise BadInput(f"--out {out}: the figure's format is its name's: .png, .pdf or .svg")
    cols, rows = read_results(path)
    if "config_hash" not in cols or not rows:
        raise BadInput(f"{path}: no sweep results in it")
    grid, rand, arrays, lines = summarise(cols, rows, metric, bound)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    label_of = metric_label(metric)
    if rand:
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
        drawn: list[tuple[str, np.ndarray]] = []
        for n, (k, a) in enumerate(arrays.items()):
            good = np.sort(a[np.isfinite(a)])
            label = " ".join(k) or "all"
            n_ok = int(np.sum(np.isfinite(a) & (np.nan_to_num(a, nan=np.inf) <= bound)))
            same = next((other for other, b in drawn if np.array_equal(b, good)), None)
            text = f"{label}: {n_ok} of {a.size} ≤ {bound:g}" + (f" (identical to {same})" if same else "")
            # overlapping laws stay visible: each its colour, line style and markers, the markers
            # staggered along the curve so an identical curve's never sit on another's
            every = max(1, good.size // 8)
            ax1.step(good, np.arange(1, good.size + 1) / max(1, a.size), where="post", color=OKABE_ITO[n % 8],
                     ls=LINE_STYLES[n % len(LINE_STYLES)], lw=1.4, marker=MARKERS[n % len(MARKERS)],
                     markevery=((n * every) // max(1, len(arrays)) % every, every), ms=5, label=text)
            drawn.append((label, good))
        ax1.axvline(bound, color="k", lw=0.8, ls="--")
        ax1.set_xscale("log")
        ax1.set_xlabel(label_of)
        ax1.set_ylabel("fraction of points")
        ax1.legend(fontsize=8)
        ax1.grid(alpha=0.3)
        ax2.boxplot([a[np.isfinite(a)] for a in arrays.values()], whis=(5, 95), showfliers=False)
        ax2.set_xticks(range(1, len(arrays) + 1), [" ".join(k) or "all" for k in arrays], rotation=20, fontsize=8)
        ax2.axhline(bound, color="k", lw=0.8, ls="--")
        ax2.set_yscale("log")
        ax2.set_ylabel(f"{metric} (its meaning: left)\nbox: quartiles, whiskers 5–95 %")
    elif len(grid) >= 2:
        xa, ya, rest = grid[0], grid[1], grid[2:]
        xs = sorted({k[0] for k in arrays}, key=_sort_key)
        ys = sorted({k[1] for k in arrays}, key=_sort_key)
        groups = sorted({k[2:] for k in arrays}, key=lambda g: [_sort_key(x) for x in g])[:MAX_PANELS]
        fig, axs = plt.subplots(1, len(groups), figsize=(4.5 * len(groups) + 1.5, 4), squeeze=False,
                                layout="constrained")
        maps = []
        for g in groups:
            m = np.full((len(ys), len(xs)), np.nan)
            for (i, y), (j, x) in itertools.product(enumerate(ys), enumerate(xs)):
                a = arrays.get((x, y, *g))
                if a is not None and np.isfinite(a).any():
                    m[i, j] = float(np.nanmedian(a))
            maps.append(m)
        finite = [v for m in maps for v in m[np.isfinite(m)].tolist()]
        from matplotlib.colors import Normalize

        norm = Normalize(min(finite), max(finite)) if finite else Normalize(0.0, 1.0)  # one scale, every panel
        cmap = plt.get_cmap("viridis")
        im = None
        for ax, g, m in zip(axs[0], groups, maps):
            im = ax.imshow(m, origin="lower", aspect="auto", cmap=cmap, norm=norm)
            for (i, j), v in np.ndenumerate(m):
                r, gr, b, _ = cmap(norm(v)) if not math.isnan(v) else (1.0, 1.0, 1.0, 1.0)
                light = 0.2126 * r + 0.7152 * gr + 0.0722 * b > 0.5  # dark text on a light cell
                ax.text(j, i, "fail" if math.isnan(v) else f"{v:.3g}", ha="center", va="center", fontsize=8,
                        color="black" if light else "white")
            ax.set_xticks(range(len(xs)), xs, fontsize=8)
            ax.set_yticks(range(len(ys)), ys, fontsize=8)
            ax.set_xlabel(key_label(xa))
            ax.set_ylabel(key_label(ya))
            ax.set_title(", ".join(f"{key_label(a)} = {v}" for a, v in zip(rest, g)), fontsize=9)
        fig.colorbar(im, ax=list(axs[0]), label=f"{label_of} (median per cell)")
    else:
        fig, ax = plt.subplots(figsize=(6, 4))
        keys = list(arrays)
        ax.plot(range(len(keys)), [float(np.nanmedian(a)) if np.isfinite(a).any() else np.nan
                                   for a in arrays.values()], "o-")
        ax.set_xticks(range(len(keys)), [" ".join(k) for k in keys], rotation=20, fontsize=8)
        ax.set_xlabel(key_label(grid[0]) if grid else "")
        ax.set_ylabel(label_of)
        ax.grid(alpha=0.3)
    fig.suptitle((title or Path(path).name) + "\n" + "\n".join(lines), fontsize=9)
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    fig.savefig(out, dpi=DPI)
    plt.close(fig)
    return lines
