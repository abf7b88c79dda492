"""The figure of an identification: held-out force, F–v loops, the parameters per level.

:func:`make_identification_figure` draws the measured and the predicted force over
time and the force–velocity loops: for constant input one record fitted at
every level (its held-out cycles where it has some, else its fitted ones),
for broadband the held-out parts of the first records, each with its NRMSE
in its title; for constant input with two levels or more, the six
parameters per level (±2 standard errors) with the paper's laws and the
table (the paper's Fig 3) and the held-out NRMSE of every record against
its stroke and its frequency, one colour per level
(:func:`make_conditions_figure` draws those two alone); a last panel lists
the held-out NRMSE of every record and level under its whole name. The format
follows the file's extension (.png, .pdf, .svg). matplotlib is imported only
here (``mrctl[plot]``); the identification package never imports this module.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from mrctl.errors import BadInput
from mrctl.offline.identify.result import IdentificationResult, Trace
from mrctl.runlog.files import write_outputs

__all__ = ["make_identification_figure", "make_conditions_figure", "score_table", "FORMATS"]

FORMATS = ("png", "pdf", "svg")
#: records shown for broadband data; panels per row (constant input shows every level)
_MAX_TRACES = 4
#: seconds of the held-out force shown over time: broadband records are long
#: and fast, a constant-input one shows a few cycles
_SHOW_S = {"broadband": 1.0, "constant_input": 5.0}


class FigureError(BadInput):
    """The figure cannot be made or written (exit code 2)."""


def _pick(traces: list[Trace]) -> list[Trace]:
    """Constant input: one trace per level, every level, of a record fitted at
    it (the longest; its held-out cycles when it has some, else its fitted
    ones); broadband: the held-out parts of the first records, up to
    _MAX_TRACES."""
    if any(tr.level is not None for tr in traces):
        fitted = {(tr.record, tr.level) for tr in traces if tr.part == "fit"}
        best: dict[float, Trace] = {}
        for tr in traces:
            k = float(tr.level)  # type: ignore[arg-type]
            key = ((tr.record, tr.level) in fitted, tr.part == "holdout", tr.t.size)
            old = best.get(k)
            if old is None or key > ((old.record, old.level) in fitted, old.part == "holdout", old.t.size):
                best[k] = tr
        return [best[k] for k in sorted(best)]
    return [tr for tr in traces if tr.part == "holdout"][:_MAX_TRACES]


def score_table(res: IdentificationResult, max_rows: int = 40) -> str:
    """The figure's table of held-out scores: every record under its whole name."""
    if not res.holdout:
        return "no held-out data"
    shown = res.holdout[:max_rows]
    width = max([len("record")] + [len(s.record) for s in shown]) + 1
    laws = any(s.nrmse_laws is not None for s in shown)
    rows = [f"{'record':<{width}}{'level':>8}{'NRMSE':>8}" + (f"{'laws':>8}" if laws else "")]
    for s in shown:
        lv = "-" if s.level is None else f"{s.level:.4g}"
        rows.append(f"{s.record:<{width}}{lv:>8}{100 * s.nrmse:7.2f}%"
                    + (f"{100 * s.nrmse_laws:7.2f}%" if s.nrmse_laws is not None else ""))
    if len(res.holdout) > len(shown):
        rows.append(f"… {len(res.holdout) - len(shown)} more (JSON summary)")
    head = "held-out force NRMSE" + (f" (laws: the written {res.params.laws} laws)" if laws else "")
    return head + "\n\n" + "\n".join(rows)


def _window(tr: Trace, show_s: float) -> slice:
    """The first ``show_s`` seconds of the trace, up to its first gap (segments are concatenated)."""
    dt = np.diff(tr.t)
    if dt.size == 0:
        return slice(0, tr.t.size)
    step = float(np.median(dt))
    n = int(round(show_s / step)) if step > 0 else tr.t.size
    gaps = np.flatnonzero(dt > 1.5 * step)
    end = int(gaps[0]) + 1 if gaps.size else tr.t.size
    return slice(0, max(2, min(n, end)))


# (Θ name, label, unit scale, unit text) of the per-level panels (the paper's Fig 3)
_THETA_PANELS = (
    ("Fc", "Coulomb force $F_c$", 1.0, "N"),
    ("Fs", "stiction force $F_s$", 1.0, "N"),
    ("vs", "Stribeck velocity $v_s$", 1e3, "mm/s"),
    ("sigma0", "bristle stiffness $\\sigma_0$", 1e-3, "kN/m"),
    ("sigma1", "bristle damping $\\sigma_1$", 1.0, "N·s/m"),
    ("sigma2", "viscous coefficient $\\sigma_2$", 1.0, "N·s/m"),
)


def _theta_panels(fig, gs, row0: int, width: int, res: IdentificationResult, levels: list[dict]) -> None:
    """The six parameters per level (±2 standard errors, hollow where poorly
    determined) with the paper's laws (6)–(11) and, when written, the table:
    what the laws make of the levels (the paper's Fig 3)."""
    import dataclasses

    from mrctl.offline.identify.laws import theta_from_params
    from mrctl.offline.identify.model import THETA_NAMES

    u = np.array([lv["level"] for lv in levels], float)
    grid = np.linspace(float(u.min()), float(u.max()), 200)
    paper = dataclasses.replace(res.params, table=None)
    law = np.array([theta_from_params(paper, float(g)) for g in grid])
    table = (np.array([theta_from_params(res.params, float(g)) for g in grid]) if res.params.table is not None
             else None)
    for n, (name, label, scale, unit) in enumerate(_THETA_PANELS):
        sub = gs[row0 + n // 3, :width].subgridspec(1, 3)
        ax = fig.add_subplot(sub[0, n % 3])
        j = THETA_NAMES.index(name)
        y = np.array([lv["theta"][name] for lv in levels]) * scale
        se = np.array([(lv.get("std_error") or {}).get(name, np.nan) for lv in levels], float) * abs(scale)
        well = np.array([(lv.get("determined") or {}).get(name) == "well" for lv in levels])
        ax.plot(grid, law[:, j] * scale, color="black", lw=1.3, label="laws (6)–(11)")
        if table is not None:
            ax.plot(grid, table[:, j] * scale, color="tab:green", lw=1.1, ls="-.", label="laws: table")
        if np.isfinite(se).any():
            ax.errorbar(u, y, yerr=2 * np.nan_to_num(se), fmt="none", ecolor="tab:blue", elinewidth=0.9, capsize=2)
        ax.plot(u[well], y[well], "o", color="tab:blue", ms=5, label="per level")
        if (~well).any():
            ax.plot(u[~well], y[~well], "o", mfc="white", mec="tab:blue", ms=5, label="poorly determined")
        ax.set(xlabel=f"input ({res.unit})", ylabel=unit, title=label)
        ax.title.set_fontsize("medium")
        ax.grid(True, lw=0.5, alpha=0.5)
        if name == "sigma1":
            ax.axhline(0.0, color="0.3", lw=0.6)
        if n == 0:
            ax.legend(fontsize="x-small", loc="best")


def _terms_text(p) -> str:
    """The optional model terms that are on, for the figure's title ('' without them)."""
    parts = []
    if p.tau_input_fall > 0.0:
        parts.append(f"falling {1e3 * p.tau_input_fall:.3g} ms")
    if p.sigma1_vd > 0.0:
        parts.append(f"σ1(v) v_d {1e3 * p.sigma1_vd:.3g} mm/s")
    if p.has_hysteresis:
        parts.append(f"hysteretic stiffness x_hys {1e3 * p.x_hys:.3g} mm")
    return (", " + ", ".join(parts)) if parts else ""


def _conditioned(res: IdentificationResult) -> list:
    """The held-out scores that carry a test condition (stroke and frequency)."""
    return [s for s in res.holdout if s.level is not None and s.stroke_m is not None and s.frequency_hz is not None]


def _conditions_panels(ax_stroke, ax_freq, res: IdentificationResult) -> None:
    """Held-out NRMSE against stroke and against frequency, one colour per
    level: where one Θ per level holds across the conditions and where not.
    Filled: through the written set; hollow: the level's own fit, where it
    differs from the written set's."""
    scores = _conditioned(res)
    levels = sorted({float(s.level) for s in scores})  # type: ignore[arg-type]
    colours = [f"C{k % 10}" for k in range(len(levels))]
    for lv, c in zip(levels, colours):
        mine = sorted((s for s in scores if s.level == lv), key=lambda s: s.stroke_m)
        for ax, key, scale in ((ax_stroke, "stroke_m", 1e3), (ax_freq, "frequency_hz", 1.0)):
            x = np.array([getattr(s, key) for s in mine]) * scale
            y = np.array([100 * (s.nrmse_laws if s.nrmse_laws is not None else s.nrmse) for s in mine])
            y0 = np.array([100 * s.nrmse for s in mine])
            ax.plot(x, y, "o", color=c, ms=6, label=f"{lv:.4g} {res.unit}")
            differ = np.abs(y - y0) > 1e-3
            if differ.any():
                ax.plot(x[differ], y0[differ], "o", mfc="white", mec=c, ms=5)
    for ax, label in ((ax_stroke, "stroke, peak to peak (mm)"), (ax_freq, "frequency (Hz)")):
        ax.set(xlabel=label, ylabel="held-out NRMSE (%)", title=f"held-out NRMSE against {label.split(',')[0].split(' (')[0]}")
        ax.title.set_fontsize("medium")
        ax.grid(True, lw=0.5, alpha=0.5)
        ax.set_ylim(bottom=0.0)
    ax_stroke.legend(fontsize="small", title="level", loc="best")


def make_conditions_figure(res: IdentificationResult, out_path: str | os.PathLike[str], dpi: int = 110,
                           force: bool = False, write: bool = True) -> bytes:
    """Held-out NRMSE against stroke and frequency per level (constant input),
    written to ``out_path`` as :func:`make_identification_figure` writes; returns its bytes."""
    ext = Path(out_path).suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise FigureError(f"{out_path}: unknown figure format {ext or '(none)'!r}; use .png, .pdf or .svg")
    if not _conditioned(res):
        raise FigureError("no held-out score with a stroke and a frequency (constant-input records only)")
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise FigureError("matplotlib is needed for figures: pip install 'mrctl[plot]'") from None
    fig = Figure(figsize=(11.0, 4.2), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    a1, a2 = fig.subplots(1, 2)
    _conditions_panels(a1, a2, res)
    fig.suptitle(f"{res.name}: held-out force NRMSE per record, laws: {res.params.laws}")
    return _save(fig, out_path, ext, force, write)


def _save(fig, out_path: str | os.PathLike[str], ext: str, force: bool, write: bool) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format=ext)
    if ext == "png":
        buf = _palette_png(buf)
    if write:
        try:
            write_outputs([(out_path, buf.getvalue())], force)
        except OSError as exc:
            raise FigureError(f"{out_path}: cannot write the figure: {exc.strerror or exc}") from None
    return buf.getvalue()


def _palette_png(buf: io.BytesIO) -> io.BytesIO:
    """The PNG with an adaptive 256-colour palette: a figure of many noisy
    traces is a third of its size, no difference to the eye (Pillow, which
    matplotlib needs anyway; the RGB file as it was without it)."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - matplotlib depends on Pillow
        return buf
    buf.seek(0)
    out = io.BytesIO()
    Image.open(buf).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(out, format="PNG",
                                                                                                optimize=True)
    return out


def make_identification_figure(res: IdentificationResult, out_path: str | os.PathLike[str], title: str | None = None,
                        dpi: int = 110, force: bool = False, write: bool = True) -> bytes:
    """Write the figure of a :class:`IdentificationResult` to ``out_path`` (.png/.pdf/.svg; ``dpi`` for PNG),
    whole or not at all (an existing file refused unless ``force``); returns its bytes.
    ``write=False`` only renders them (the CLI writes them with the parameters)."""
    ext = Path(out_path).suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise FigureError(f"{out_path}: unknown figure format {ext or '(none)'!r}; use .png, .pdf or .svg")
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise FigureError("matplotlib is needed for figures: pip install 'mrctl[plot]'") from None
    traces = _pick(res.traces)
    if not traces:
        raise FigureError("no data to draw (no fitted or held-out record)")
    n = len(traces)
    ncol = min(n, _MAX_TRACES)
    nrow = -(-n // ncol)
    levels = res.details.get("levels") or []
    theta_rows = 2 if res.protocol == "constant_input" and len(levels) >= 2 else 0
    cond_rows = 1 if _conditioned(res) else 0
    fig = Figure(figsize=(4.2 * max(ncol, 3) + 4.6, 7.2 * nrow + 3.4 * (theta_rows + cond_rows)), dpi=dpi,
                 layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(2 * nrow + theta_rows + cond_rows, max(ncol, 3) + 1,
                          width_ratios=[1.0] * max(ncol, 3) + [1.05],
                          height_ratios=[1.0] * (2 * nrow) + [0.95] * (theta_rows + cond_rows))
    scores = {(s.record, s.level, s.part): s for s in res.holdout + res.train}
    u = res.unit
    for j, tr in enumerate(traces):
        r0, c0 = 2 * (j // ncol), j % ncol
        sc = scores.get((tr.record, tr.level, tr.part))
        lv = "" if tr.level is None else f" at {tr.level:.4g} {u}"
        what = "held out" if tr.part == "holdout" else "fitted"
        head = f"{tr.record}{lv}, {what}" + (f": NRMSE {100 * sc.nrmse:.2f} %" if sc else "")
        ax = fig.add_subplot(gs[r0, c0])
        w = _window(tr, _SHOW_S.get(res.protocol, 1.0))
        t0 = tr.t[w][0]
        ax.plot(tr.t[w] - t0, tr.F_meas[w], color="0.1", lw=1.0, label="measured")
        ax.plot(tr.t[w] - t0, tr.F_pred[w], color="tab:red", lw=0.9, alpha=0.85, label="predicted")
        ax.set(xlabel=f"time from {t0:.3g} s (s)", ylabel="force (N)", title=head)
        ax.title.set_fontsize("medium")
        ax.grid(True, lw=0.5, alpha=0.5)
        if j == 0:
            ax.legend(loc="upper right", fontsize="small")
        ax2 = fig.add_subplot(gs[r0 + 1, c0])
        step = max(1, tr.v.size // 3000)  # a few thousand points show the loop
        ax2.plot(1e3 * tr.v[::step], tr.F_meas[::step], ".", ms=1.5, color="0.15", alpha=0.3, rasterized=True,
                 label="measured")
        ax2.plot(1e3 * tr.v[::step], tr.F_pred[::step], ".", ms=1.0, color="tab:red", alpha=0.3, rasterized=True,
                 label="predicted")
        ax2.set(xlabel="velocity (mm/s)", ylabel="force (N)", title=f"force–velocity, {what} part")
        ax2.title.set_fontsize("medium")
        ax2.grid(True, lw=0.5, alpha=0.5)
    if theta_rows:
        _theta_panels(fig, gs, 2 * nrow, max(ncol, 3), res, levels)
    if cond_rows:
        sub = gs[2 * nrow + theta_rows, :max(ncol, 3)].subgridspec(1, 2)
        _conditions_panels(fig.add_subplot(sub[0, 0]), fig.add_subplot(sub[0, 1]), res)
    # the table of every held-out score
    axt = fig.add_subplot(gs[:, max(ncol, 3)])
    axt.axis("off")
    axt.text(0.0, 1.0, score_table(res, 40 * nrow), va="top", ha="left", family="monospace", fontsize="small",
             transform=axt.transAxes)
    p = res.params
    extra = f", inertia {res.inertia_kg:.3g} kg" if res.inertia_kg else ""
    head = title if title is not None else f"{res.name}: {res.protocol} identification, {res.input} input"
    bench = ("per level (table)" if p.table is not None and p.table.has_bench()
             else f"F_offset {p.F_offset:.4g} N, k_x {p.k_x:.4g} N/m")
    terms = _terms_text(p)
    fig.suptitle(f"{head}, laws: {p.laws}\n{bench}, tau_input {1e3 * p.tau_input:.3g} ms"
                 f"{extra}{terms}; red: " + ("the model fitted at that level, on held-out cycles where a record has them"
                                      if res.protocol == "constant_input" else "the fitted model on data the fit "
                                      "never saw"), fontsize="large")
    return _save(fig, out_path, ext, force, write)
