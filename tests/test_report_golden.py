"""The run report's golden properties, checked on the drawn figure (not its
pixels): legend entries told apart by colour and line style, no panel
without data, every value beyond an axis marked with its value, shading as
wide as the ticks it stands for (and at least visible), latched faults apart
from ordinary ones, scattered skipped deadlines marked along an edge rather
than tinting every trace, overlaid runs told apart and labelled."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from matplotlib.colors import to_hex

from mrctl.offline.report import build_figure
from mrctl.offline.report_marks import EDGE_STRIP, LATCHED_BIT, MIN_WIDTH_SHARE

DT = 1e-3


def _write(path: Path, cols: dict[str, np.ndarray], law: str = "smooth", settle: float = 0.5,
           demand: str = "viscous") -> Path:
    names = list(cols)
    rows = [",".join(names)] + [",".join(repr(float(cols[c][i])) for c in names) for i in range(len(cols["t"]))]
    path.write_text("\n".join(rows) + "\n")
    path.with_suffix(".json").write_text(json.dumps({"law": law, "I_max_A": 0.6, "settle_s": settle,
                                                     "verdict": "ok", "config": {"demand": {"type": demand}}}))
    return path


def _sine_run(seconds: float = 2.0, gain: float = 1.0, kick: float = 0.0,
              keep: np.ndarray | None = None, fault: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """A 1 Hz, 500 N·s/m run at 1 kHz with a known tracking error; ``kick`` N
    of error at t = 0 (a start-up transient); rows ``keep`` (the others are
    skipped deadlines); ``fault`` bits per tick."""
    k = np.arange(int(round(seconds / DT)), dtype=float)
    t = k * DT
    v = 0.01 * 2 * np.pi * np.cos(2 * np.pi * t)
    F_des = 500.0 * v
    F = gain * F_des + 0.3 * np.sin(40 * np.pi * t)
    F[0] += kick
    cols = {"t": t, "x": 0.01 * np.sin(2 * np.pi * t), "v": v, "F_des": F_des, "F": F,
            "I": np.clip(np.abs(F_des) / 60.0, 0.0, 0.5), "k": k,
            "fault": np.zeros_like(t) if fault is None else fault.astype(float)}
    if keep is not None:
        cols = {c: a[keep] for c, a in cols.items()}
    return cols


def _axes(fig) -> dict:
    return {ax.get_label(): ax for ax in fig.axes}


def _style(artist) -> tuple:
    """An artist's (colour, dash pattern) as drawn (matplotlib keeps the unscaled pattern)."""
    return to_hex(artist.get_color()), artist._unscaled_dash_pattern


def _drawn_lines(fig) -> list:
    return [h for h in fig.legends[0].legend_handles
            if h.__class__.__name__ == "Line2D" and h.get_linestyle() not in ("None", "none", "")]


def _has_data(ax) -> bool:
    for ln in ax.lines:
        y = np.asarray(ln.get_ydata(), float)
        if y.size > 1 and np.isfinite(y).any() and ln.get_gid() != "clipped":
            return True
    return False


def test_one_run_every_quantity_has_its_own_colour_and_line_style(tmp_path):
    """The report of one run used to draw F, F - F_des and I in one red: now
    every legend entry has its own colour, and the lines that share a panel
    differ in line style too (grey print)."""
    path = _write(tmp_path / "run.csv", _sine_run())
    fig, _ = build_figure(path)
    lines = _drawn_lines(fig)
    labels = [t.get_text() for t, h in zip(fig.legends[0].get_texts(), fig.legends[0].legend_handles)
              if h in lines]
    assert len(lines) >= 4, labels  # actual, desired, error, current
    styles = [_style(h) for h in lines]
    assert len(set(styles)) == len(styles), dict(zip(labels, styles))
    assert len({c for c, _ in styles}) == len(styles)  # colours alone tell them apart
    for ax in fig.axes:  # within a panel, line styles alone tell them apart
        drawn = [_style(ln) for ln in ax.lines if ln.get_gid() != "clipped" and not ln.get_label().startswith("_")]
        assert len({d for _, d in drawn}) == len(drawn), (ax.get_label(), drawn)


def test_no_panel_without_data_in_any_layout(tmp_path):
    """No empty panel: the default five panels, time panels alone, loops alone."""
    path = _write(tmp_path / "run.csv", _sine_run())
    for panels in (None, ["force", "error", "current"], ["fv", "fx"], ["force", "fx"], ["current"]):
        fig, _ = build_figure(path, panels=panels)
        assert [ax.get_label() for ax in fig.axes] == list(panels or ("force", "error", "current", "fv", "fx"))
        empty = [ax.get_label() for ax in fig.axes if not _has_data(ax)]
        assert not empty, (panels, empty)


def test_a_time_window_without_rows_is_refused_not_drawn_empty(tmp_path):
    from mrctl.offline.report import ReportError

    path = _write(tmp_path / "run.csv", _sine_run())
    with pytest.raises(ReportError, match=r"--time 5,6: no run has two rows there \(the runs span 0–1.999 s\)"):
        build_figure(path, time=(5.0, 6.0))


def test_a_start_up_error_beyond_the_axis_is_marked_with_its_value(tmp_path):
    """The error panel is scaled to the metrics window; a -44.8 N start-up
    error used to be clipped off it without a mark."""
    path = _write(tmp_path / "run.csv", _sine_run(kick=-44.8))
    fig, _ = build_figure(path)
    ax = _axes(fig)["error"]
    lo, hi = ax.get_ylim()
    assert lo > -5.0  # the axis stays on the error the metrics judge
    marks = [ln for ln in ax.lines if ln.get_gid() == "clipped"]
    assert len(marks) == 1
    assert list(marks[0].get_xdata()) == [0.0] and list(marks[0].get_ydata()) == [lo]  # at the lower edge, at t = 0
    assert marks[0].get_marker() == "v"
    texts = [t.get_text() for t in ax.texts if t.get_gid() == "clipped"]
    assert texts == ["\u221244.8 N at t = 0 s"]
    legend = " ".join(t.get_text() for t in fig.legends[0].get_texts())
    assert "beyond the error axis" in legend
    # every value outside the limits is marked: none when nothing is outside
    quiet = _write(tmp_path / "quiet.csv", _sine_run())
    fig2, _ = build_figure(quiet)
    assert not [ln for ln in _axes(fig2)["error"].lines if ln.get_gid() == "clipped"]


def _patches(ax, label: str) -> list[tuple[float, float, float, float]]:
    """(x0, x1, y0, y1) of the shaded patches with this label (y in axes fraction)."""
    return sorted((p.get_x(), p.get_x() + p.get_width(), p.get_y(), p.get_y() + p.get_height())
                  for p in ax.patches if p.get_label() == label)


def test_fault_shading_is_as_wide_as_its_ticks_and_always_visible(tmp_path):
    """Fault stretches of 1, 3 and 250 ticks on a 20 s run: the spans' total
    width is the fault ticks' time, every fault tick lies under a drawn
    patch, and a one-tick fault is drawn at least MIN_WIDTH_SHARE of the axis wide."""
    n = 20_000
    fault = np.zeros(n)
    fault[5000] = 1  # one tick
    fault[9000:9003] = 4  # three
    fault[14000:14250] = 2  # 250 ticks = 0.25 s
    path = _write(tmp_path / "run.csv", _sine_run(seconds=20.0, fault=fault))
    fig, (m,) = build_figure(path)
    assert sum(b - a for a, b in m["fault_spans"]) == pytest.approx(254 * DT)
    assert m["ticks"]["fault"] == 254
    min_w = MIN_WIDTH_SHARE * 20.0 * (1 - 1e-3)
    for name in ("force", "error", "current"):
        drawn = _patches(_axes(fig)[name], "fault")
        assert len(drawn) == 3
        assert all(x1 - x0 >= min_w * 0.999 for x0, x1, _, _ in drawn)
        assert all((y0, y1) == (0.0, 1.0) for _, _, y0, y1 in drawn)  # full height: a fault is not missed
        for tk in np.flatnonzero(fault):
            assert any(x0 <= tk * DT <= x1 for x0, x1, _, _ in drawn), tk
        wide = [x1 - x0 for x0, x1, _, _ in drawn if x1 - x0 > min_w * 1.01]
        assert wide == [pytest.approx(0.25)]  # a stretch wider than the minimum is drawn as wide as it is
    legend = [t.get_text().replace("\n", " ") for t in fig.legends[0].get_texts()]
    assert "fault: 254 ticks (1.3 % of rows)" in legend


def test_latched_stretches_are_drawn_apart_from_ordinary_faults(tmp_path):
    """The E-stop (256) latches: its ticks carry LATCHED (1024); the
    stretch before the latch (a link fault, 1) is an ordinary fault."""
    fault = np.zeros(4000)
    fault[1500:1520] = 1
    fault[1520:2600] = 256 | LATCHED_BIT
    path = _write(tmp_path / "run.csv", _sine_run(seconds=4.0, fault=fault))
    fig, (m,) = build_figure(path)
    ax = _axes(fig)["force"]
    latched, ordinary = _patches(ax, "latched"), _patches(ax, "fault")
    assert [(round(a, 9), round(b, 9)) for a, b, _, _ in latched] == [(1.52, 2.6)]
    assert [(round(a, 9), round(b, 9)) for a, b, _, _ in ordinary] == [(1.5, 1.52)]
    hatch = {p.get_label(): (p.get_hatch(), to_hex(p.get_facecolor())) for p in ax.patches}
    assert hatch["latched"] != hatch["fault"]
    assert m["ticks"] == {"fault": 20, "latched": 1080, "skipped deadlines": 0}
    legend = " ".join(t.get_text().replace("\n", " ") for t in fig.legends[0].get_texts())
    assert "latched (0 A, output off until mrctl arm): 1080 ticks" in legend
    assert "fault: 20 ticks" in legend


def test_skipped_deadlines_everywhere_are_marked_along_the_edge_not_tinted(tmp_path):
    """A serial or TCP run skips deadlines all over: a strip along the top
    edge and the legend says so, instead of a tint over every trace; a
    quiet run's single skipped tick is still a visible band."""
    rng = np.random.default_rng(7)
    keep = rng.random(10_000) >= 0.03
    keep[0] = keep[-1] = True
    path = _write(tmp_path / "busy.csv", _sine_run(seconds=10.0, keep=keep))
    fig, (m,) = build_figure(path)
    assert m["ticks"]["skipped deadlines"] == int((~keep).sum())
    for name in ("force", "error", "current"):
        strip = _patches(_axes(fig)[name], "skipped deadlines")
        assert strip and all(y1 - y0 <= EDGE_STRIP + 1e-9 and y0 > 0.9 for _, _, y0, y1 in strip)
    legend = " ".join(t.get_text().replace("\n", " ") for t in fig.legends[0].get_texts())
    assert "throughout the run: marked along the top edge" in legend
    assert f"skipped deadlines: {int((~keep).sum())} (" in legend
    # one skipped tick on a quiet 10 s run: a band of full height, at least the minimum width
    keep = np.ones(10_000, bool)
    keep[6000] = False
    quiet = _write(tmp_path / "quiet.csv", _sine_run(seconds=10.0, keep=keep))
    fig, (m,) = build_figure(quiet)
    (band,) = _patches(_axes(fig)["force"], "skipped deadlines")
    assert band[3] - band[2] == 1.0 and band[1] - band[0] >= MIN_WIDTH_SHARE * 10.0 * 0.999
    assert band[0] <= 6.0 <= band[1]
    assert "throughout" not in " ".join(t.get_text() for t in fig.legends[0].get_texts())


def test_overlaid_runs_are_told_apart_and_labelled(tmp_path):
    """Three runs (two of one file name in two folders): each its own colour and
    line style in every time panel, labelled by folder where names clash, and
    a legend of distinct (colour, style) pairs."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    paths = [_write(tmp_path / "a" / "fig5.csv", _sine_run(), law="paper"),
             _write(tmp_path / "b" / "fig5.csv", _sine_run(gain=0.97)),
             _write(tmp_path / "closed.csv", _sine_run(gain=1.01, kick=-30.0), law="closed")]
    fig, runs = build_figure(paths)
    assert [r["label"] for r in runs] == ["a/fig5.csv (paper)", "b/fig5.csv (smooth)", "closed.csv (closed)"]
    for name in ("force", "error", "current"):
        ax = _axes(fig)[name]
        mine = [ln for ln in ax.lines if ln.get_label() in {r["label"] for r in runs}]
        assert len(mine) == 3
        assert len({_style(ln) for ln in mine}) == 3
        assert len({to_hex(ln.get_color()) for ln in mine}) == 3
    lines = _drawn_lines(fig)
    assert len({_style(h) for h in lines}) == len(lines)
    # the third run's start-up kick is marked in its colour
    err = _axes(fig)["error"]
    (mark,) = [ln for ln in err.lines if ln.get_gid() == "clipped"]
    third = next(ln for ln in err.lines if ln.get_label() == runs[2]["label"])
    assert to_hex(mark.get_color()) == to_hex(third.get_color())


def test_quarter_car_overlay_labels_the_demand_where_it_differs(tmp_path):
    """Skyhook beside groundhook through the same inverse law: the label says which is which."""
    a = _write(tmp_path / "sky.csv", _sine_run(), demand="skyhook")
    b = _write(tmp_path / "gnd.csv", _sine_run(gain=0.9), demand="groundhook")
    _, runs = build_figure([a, b])
    assert [r["label"] for r in runs] == ["sky.csv (skyhook + smooth)", "gnd.csv (groundhook + smooth)"]


def test_the_caption_fits_a_narrow_figure(tmp_path):
    """--size 7,5: the caption's lines are broken at their separators to the
    figure's width (about 10 characters per inch at its font size), nothing cut."""
    fault = np.zeros(2000)
    fault[1500:1510] = 1
    path = _write(tmp_path / "run.csv", _sine_run(fault=fault))
    fig, _ = build_figure(path, size=(7.0, 5.0))
    caption = fig.get_suptitle()
    assert all(len(line) <= 70 for line in caption.splitlines()), caption
    flat = " ".join(caption.split())
    for text in ("force NRMSE", "max |ΔI|", "I = I_max (0.6 A)", "verdict: ok", "fault: 10 ticks (0.5 % of rows)"):
        assert text in flat, text
