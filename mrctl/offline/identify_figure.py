"""The figures of an identification: a summary page, and per-level detail on request.

:func:`make_identification_figure` draws, by default, the summary a reader
takes in at a glance: the held-out NRMSE of every record (per level for
constant input), the worst held-out record's force over time and its
force–velocity loop; for constant input with two levels or more the six
parameters per level (±2 standard errors) with the paper's laws and the
table (the paper's Fig 3); where the records differ in stroke or frequency,
the held-out NRMSE against each with a per-level table. Broadband: the
held-out records (the worst and the best of more than two) and their NRMSE.
``detail=True`` (``mrctl identify --report-detail FIG``) draws every level's
(or held-out record's) force and F–v loop, two levels a row, with every
held-out score under its record's whole name. :func:`make_conditions_figure`
draws the NRMSE against stroke and frequency alone. The format follows the
file's extension (.png, .pdf, .svg). matplotlib is imported only here
(``mrctl[plot]``); the identification package never imports this module.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

from mrctl.errors import BadInput
from mrctl.offline.identify.result import IdentificationResult, Score, Trace
from mrctl.offline.identify_panels import (conditioned, conditions_panels, conditions_vary, held_out, level_table,
                                           scores_panel, theta_panels, trace_panels)
from mrctl.offline.report_figure import palette_png
from mrctl.runlog.files import write_outputs

__all__ = ["make_identification_figure", "make_conditions_figure", "score_table", "FORMATS"]

FORMATS = ("png", "pdf", "svg")
#: held-out records shown for broadband data (detail); levels (or records) per row of the detail page
_MAX_TRACES = 12
_PER_ROW = 2
#: seconds of the force shown over time: broadband records are long
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


def _figure_classes() -> tuple[Any, Any]:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise FigureError("matplotlib is needed for figures: pip install 'mrctl[plot]'") from None
    return Figure, FigureCanvasAgg


def _ext(out_path: str | os.PathLike[str]) -> str:
    ext = Path(out_path).suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise FigureError(f"{out_path}: unknown figure format {ext or '(none)'!r}; use .png, .pdf or .svg")
    return ext


def _head(res: IdentificationResult, title: str | None, what: str) -> str:
    """The suptitle: what was fitted, the written laws, the bench terms."""
    p = res.params
    extra = f", inertia {res.inertia_kg:.3g} kg" if res.inertia_kg else ""
    head = title if title is not None else f"{res.name}: {res.protocol} identification, {res.input} input"
    bench = ("per level (table)" if p.table is not None and p.table.has_bench()
             else f"F_offset {p.F_offset:.4g} N, k_x {p.k_x:.4g} N/m")
    return (f"{head}, laws: {p.laws} ({what})\n{bench}, tau_input {1e3 * p.tau_input:.3g} ms{extra}"
            f"{_terms_text(p)}; model: " + ("fitted at each level, on held-out cycles where a record has them"
                                            if res.protocol == "constant_input" else "on data the fit never saw"))


def _scores(res: IdentificationResult) -> dict[tuple[str, float | None, str], Score]:
    """Each (record, level, part)'s score, the first where two share one."""
    out: dict[tuple[str, float | None, str], Score] = {}
    for s in res.holdout + res.train:
        out.setdefault((s.record, s.level, s.part), s)
    return out


def _trace_head(res: IdentificationResult, tr: Trace, prefix: str = "") -> str:
    sc = _scores(res).get((tr.record, tr.level, tr.part))
    lv = "" if tr.level is None else f" at {tr.level:.4g} {res.unit}"
    what = "held out" if tr.part == "holdout" else "fitted"
    return f"{prefix}{tr.record}{lv}, {what}" + (f": NRMSE {100 * sc.nrmse:.2f} %" if sc else "")


def _worst(res: IdentificationResult) -> Trace | None:
    """The trace of the worst held-out record (through the written set) that has one."""
    for s in sorted(res.holdout, key=held_out, reverse=True):
        tr = next((t for t in res.traces if (t.record, t.level, t.part) == (s.record, s.level, "holdout")), None)
        if tr is not None:
            return tr
    return None


def _summary(fig: Any, res: IdentificationResult, cond: bool) -> None:
    """The summary page; ``cond``: with the panels against the test conditions (:func:`conditions_vary`)."""
    show = _SHOW_S.get(res.protocol, 1.0)
    if res.protocol != "constant_input":  # broadband: the held-out records, the worst and the best of more
        scores = _scores(res)

        def worst_first(t: Trace) -> float:
            sc = scores.get((t.record, t.level, t.part))
            return -(held_out(sc) if sc else 0.0)

        held = sorted([t for t in res.traces if t.part == "holdout"] or res.traces, key=worst_first)
        shown = held if len(held) <= 2 else [held[0], held[-1]]
        gs = fig.add_gridspec(len(shown), 3, width_ratios=(1.35, 1.0, 0.75))
        for i, tr in enumerate(shown):
            ax_t, ax_v = fig.add_subplot(gs[i, 0], label=f"record-time-{i}"), fig.add_subplot(gs[i, 1],
                                                                                                label=f"record-fv-{i}")
            prefix = "" if len(held) <= 2 else ("worst: " if i == 0 else "best: ")
            trace_panels(ax_t, ax_v, tr, _trace_head(res, tr, prefix), show, legend=i == 0)
        scores_panel(fig.add_subplot(gs[:, 2]), res)
        return
    levels = res.details.get("levels") or []
    theta = len(levels) >= 2
    gs = fig.add_gridspec(1 + 2 * theta + cond, 3, height_ratios=[1.15] + [1.0] * (2 * theta + cond))
    scores_panel(fig.add_subplot(gs[0, 0]), res)
    tr = _worst(res) or _pick(res.traces)[0]
    trace_panels(fig.add_subplot(gs[0, 1], label="worst-time"), fig.add_subplot(gs[0, 2], label="worst-fv"), tr,
                 _trace_head(res, tr, "worst: " if len(res.holdout) > 1 else ""), show, legend=True)
    if theta:
        theta_panels([fig.add_subplot(gs[1 + n // 3, n % 3]) for n in range(6)], res, levels)
    if cond:
        r = 2 * theta + 1
        conditions_panels(fig.add_subplot(gs[r, 0]), fig.add_subplot(gs[r, 1]), res)
        level_table(fig.add_subplot(gs[r, 2]), res)


def _detail(fig: Any, res: IdentificationResult, traces: list[Trace]) -> None:
    nrow = -(-len(traces) // _PER_ROW)
    ncol = 2 * min(_PER_ROW, len(traces))
    gs = fig.add_gridspec(nrow, ncol + 1, width_ratios=[1.0] * ncol + [1.1])
    for j, tr in enumerate(traces):
        r, c = j // _PER_ROW, 2 * (j % _PER_ROW)
        key = f"{tr.level:.4g}" if tr.level is not None else tr.record
        trace_panels(fig.add_subplot(gs[r, c], label=f"time-{key}"), fig.add_subplot(gs[r, c + 1], label=f"fv-{key}"),
                     tr, _trace_head(res, tr), _SHOW_S.get(res.protocol, 1.0), legend=j == 0)
    axt = fig.add_subplot(gs[:, ncol], label="scores-table")
    axt.axis("off")
    axt.text(0.0, 1.0, score_table(res, max(40, 12 * nrow)), va="top", ha="left", family="monospace",
             fontsize="small", transform=axt.transAxes)


def build_identification_figure(res: IdentificationResult, title: str | None = None, dpi: int = 110,
                                detail: bool = False) -> Any:
    """The summary page (or with ``detail`` the per-level page) as an unsaved
    Figure, each Axes labelled with what it shows: for tests and for
    :func:`make_identification_figure`."""
    Figure, Canvas = _figure_classes()
    if detail:
        traces = _pick(res.traces)
        if res.protocol != "constant_input":
            traces = traces[:_MAX_TRACES]
        if not traces:
            raise FigureError("no data to draw (no fitted or held-out record)")
        nrow = -(-len(traces) // _PER_ROW)
        fig = Figure(figsize=(4.3 * 2 * min(_PER_ROW, len(traces)) + 4.8, 3.4 * nrow + 1.2), dpi=dpi,
                     layout="constrained")
        Canvas(fig)
        _detail(fig, res, traces)
        fig.suptitle(_head(res, title, "detail: every level" if res.protocol == "constant_input"
                           else "detail: the held-out records"), fontsize="large")
        return fig
    if not res.traces:
        raise FigureError("no data to draw (no fitted or held-out record)")
    levels = res.details.get("levels") or []
    constant = res.protocol == "constant_input"
    cond = constant and conditions_vary(res)  # conditions_vary is False without a conditioned score
    if constant:
        rows = 1.15 + 2.0 * (len(levels) >= 2) + cond
        size = (15.0, 3.6 * rows + 1.3)
    else:
        size = (15.0, 3.6 * min(2, sum(t.part == "holdout" for t in res.traces) or 1) + 1.3)
    fig = Figure(figsize=size, dpi=dpi, layout="constrained")
    Canvas(fig)
    _summary(fig, res, cond)
    fig.suptitle(_head(res, title, "summary; every level: --report-detail" if constant
                       else "summary; every held-out record: --report-detail"), fontsize="large")
    return fig


def make_identification_figure(res: IdentificationResult, out_path: str | os.PathLike[str], title: str | None = None,
                               dpi: int = 110, force: bool = False, write: bool = True, detail: bool = False) -> bytes:
    """Write the summary figure of a :class:`IdentificationResult` (``detail``:
    the per-level page) to ``out_path`` (.png/.pdf/.svg; ``dpi`` for PNG),
    whole or not at all (an existing file refused unless ``force``); returns
    its bytes. ``write=False`` only renders them (the CLI writes them with the
    parameters)."""
    ext = _ext(out_path)
    return _save(build_identification_figure(res, title, dpi, detail), out_path, ext, force, write)


def make_conditions_figure(res: IdentificationResult, out_path: str | os.PathLike[str], dpi: int = 110,
                           force: bool = False, write: bool = True) -> bytes:
    """Held-out NRMSE against stroke and frequency per level (constant input),
    written to ``out_path`` as :func:`make_identification_figure` writes; returns its bytes."""
    ext = _ext(out_path)
    if not conditioned(res):
        raise FigureError("no held-out score with a stroke and a frequency (constant-input records only)")
    Figure, Canvas = _figure_classes()
    fig = Figure(figsize=(11.0, 4.2), dpi=dpi, layout="constrained")
    Canvas(fig)
    a1, a2 = fig.subplots(1, 2)
    conditions_panels(a1, a2, res)
    fig.suptitle(f"{res.name}: held-out force NRMSE per record, laws: {res.params.laws}")
    return _save(fig, out_path, ext, force, write)


def _save(fig, out_path: str | os.PathLike[str], ext: str, force: bool, write: bool) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format=ext)
    if ext == "png":
        buf = io.BytesIO(palette_png(buf.getvalue()))
    if write:
        try:
            write_outputs([(out_path, buf.getvalue())], force)
        except OSError as exc:
            raise FigureError(f"{out_path}: cannot write the figure: {exc.strerror or exc}") from None
    return buf.getvalue()


