"""The figure of an identification from a dataset: held-out force and F–v loops.

:func:`make_dataset_report` draws, for the records the fit never saw (or
their held-out part), the measured and the predicted force over time and
the force–velocity loops, with each record's held-out NRMSE in its title;
a last panel lists the held-out NRMSE of every record and level. The format
follows the file's extension (.png, .pdf, .svg). matplotlib is imported only
here (``mrctl[plot]``); the identification package never imports this module.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from mrctl.errors import BadInput
from mrctl.offline.identify.dataset_result import DatasetResult, Trace
from mrctl.runlog.files import write_outputs

__all__ = ["make_dataset_report", "FORMATS"]

FORMATS = ("png", "pdf", "svg")
#: panels of held-out traces at most (one per level for constant-input data)
_MAX_TRACES = 4
#: seconds of the held-out force shown over time: broadband records are long
#: and fast, a constant-input one shows a few cycles
_SHOW_S = {"broadband": 1.0, "constant_input": 5.0}


class FigureError(BadInput):
    """The figure cannot be made or written (exit code 2)."""


def _pick(traces: list[Trace]) -> list[Trace]:
    """One trace per level (the longest), or the first records, up to _MAX_TRACES."""
    if any(tr.level is not None for tr in traces):
        best: dict[float, Trace] = {}
        for tr in traces:
            k = float(tr.level)  # type: ignore[arg-type]
            if k not in best or tr.t.size > best[k].t.size:
                best[k] = tr
        chosen = [best[k] for k in sorted(best)]
        if len(chosen) > _MAX_TRACES:
            idx = np.linspace(0, len(chosen) - 1, _MAX_TRACES).round().astype(int)
            chosen = [chosen[i] for i in idx]
        return chosen
    return traces[:_MAX_TRACES]


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


def make_dataset_report(res: DatasetResult, out_path: str | os.PathLike[str], title: str | None = None,
                        dpi: int = 110, force: bool = False, write: bool = True) -> bytes:
    """Write the figure of a :class:`DatasetResult` to ``out_path`` (.png/.pdf/.svg; ``dpi`` for PNG),
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
    traces = _pick([tr for tr in res.traces if tr.part == "holdout"])
    if not traces:
        raise FigureError("no held-out data to draw (holdout fraction 0 and no record with role: holdout)")
    n = len(traces)
    fig = Figure(figsize=(4.2 * n + 3.8, 7.2), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(2, n + 1, width_ratios=[1.0] * n + [0.85])
    scores = {(s.record, s.level): s for s in res.holdout}
    u = res.unit
    for j, tr in enumerate(traces):
        sc = scores.get((tr.record, tr.level))
        lv = "" if tr.level is None else f" at {tr.level:.4g} {u}"
        head = f"{tr.record}{lv}" + (f": NRMSE {100 * sc.nrmse:.2f} %" if sc else "")
        ax = fig.add_subplot(gs[0, j])
        w = _window(tr, _SHOW_S.get(res.protocol, 1.0))
        t0 = tr.t[w][0]
        ax.plot(tr.t[w] - t0, tr.F_meas[w], color="0.1", lw=1.0, label="measured")
        ax.plot(tr.t[w] - t0, tr.F_pred[w], color="tab:red", lw=0.9, alpha=0.85, label="predicted")
        ax.set(xlabel=f"time from {t0:.3g} s (s)", ylabel="force (N)", title=head)
        ax.title.set_fontsize("medium")
        ax.grid(True, lw=0.5, alpha=0.5)
        if j == 0:
            ax.legend(loc="upper right", fontsize="small")
        ax2 = fig.add_subplot(gs[1, j])
        step = max(1, tr.v.size // 3000)  # a few thousand points show the loop
        ax2.plot(1e3 * tr.v[::step], tr.F_meas[::step], ".", ms=1.5, color="0.15", alpha=0.3, rasterized=True,
                 label="measured")
        ax2.plot(1e3 * tr.v[::step], tr.F_pred[::step], ".", ms=1.0, color="tab:red", alpha=0.3, rasterized=True,
                 label="predicted")
        ax2.set(xlabel="velocity (mm/s)", ylabel="force (N)", title="force–velocity, held-out part")
        ax2.title.set_fontsize("medium")
        ax2.grid(True, lw=0.5, alpha=0.5)
    # the table of every held-out score
    axt = fig.add_subplot(gs[:, n])
    axt.axis("off")
    rows = [f"{'record':<14}{'level':>8}{'NRMSE':>8}"]
    for s in res.holdout[:40]:
        lv = "-" if s.level is None else f"{s.level:.4g}"
        rows.append(f"{s.record[:14]:<14}{lv:>8}{100 * s.nrmse:7.2f}%")
    if len(res.holdout) > 40:
        rows.append(f"… {len(res.holdout) - 40} more (JSON summary)")
    axt.text(0.0, 1.0, "held-out force NRMSE\n\n" + "\n".join(rows), va="top", ha="left", family="monospace",
             fontsize="small", transform=axt.transAxes)
    p = res.params
    extra = f", inertia {res.inertia_kg:.3g} kg" if res.inertia_kg else ""
    head = title if title is not None else f"{res.name}: {res.protocol} identification, {res.input} input"
    fig.suptitle(f"{head}\nF_offset {p.F_offset:.4g} N, k_x {p.k_x:.4g} N/m, tau_input {1e3 * p.tau_input:.3g} ms"
                 f"{extra}; red: the fitted model on data the fit never saw", fontsize="large")
    buf = io.BytesIO()
    fig.savefig(buf, format=ext)
    if write:
        try:
            write_outputs([(out_path, buf.getvalue())], force)
        except OSError as exc:
            raise FigureError(f"{out_path}: cannot write the figure: {exc.strerror or exc}") from None
    return buf.getvalue()
