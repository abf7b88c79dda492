"""The sweep figures as a reviewer reads them, checked on the drawn figure:
the heat map at 200 dpi, one colour scale across panels, key paths with
their units, cell numbers dark on light cells and light on dark ones; the
Monte Carlo CDFs with overlapping laws kept visible and the overlap said."""

from __future__ import annotations

from pathlib import Path

import matplotlib.figure
import numpy as np

from mrctl.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _swept_and_drawn(tmp_path, monkeypatch, capsys, sweep_text: str, report_args: list[str]):
    """fig5 at 1.5 s swept as ``sweep_text`` says (its base: base.yaml), then ``mrctl report`` of the
    table with ``report_args``: the (figure, savefig keywords) of each figure it saved."""
    (tmp_path / "base.yaml").write_text((ROOT / "config" / "experiments" / "fig5.yaml").read_text()
                                        .replace("duration_s: 4.0", "duration_s: 1.5"))
    sweep, table = tmp_path / "s.yaml", tmp_path / "r.csv"
    sweep.write_text(sweep_text)
    assert main(["sweep", str(sweep), "--out", str(table), "--workers", "1", "-q"]) == 0
    drawn = []
    real = matplotlib.figure.Figure.savefig

    def keep(fig, *a, **k):
        drawn.append((fig, k))
        return real(fig, *a, **k)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    assert main(["report", str(table), *report_args]) == 0, capsys.readouterr().err
    return drawn


def test_heat_map_panels_share_one_scale_at_200_dpi(tmp_path, monkeypatch, capsys):
    out = tmp_path / "map.png"
    (fig, kw), = _swept_and_drawn(
        tmp_path, monkeypatch, capsys,
        "version: 1\nname: s\nbase: base.yaml\ngrid:\n  demand.c_des: [250, 750]\n"
        "  plant.driver_tau_s: [0.0, 0.01]\n  inverse.law: [smooth, paper]\nmetrics: [force_nrmse]\n",
        ["--out", str(out)])
    assert kw["dpi"] == 200
    panels = [ax for ax in fig.axes if ax.images]
    assert len(panels) == 2
    assert len({ax.images[0].get_clim() for ax in panels}) == 1  # one colour scale
    assert len([ax for ax in fig.axes if ax.get_label() == "<colorbar>"]) == 1
    assert panels[0].get_xlabel() == "demand.c_des (N·s/m)" and panels[0].get_ylabel() == "plant.driver_tau_s (s)"
    lo, hi = panels[0].images[0].get_clim()
    for ax in panels:
        im = ax.images[0]
        for t in ax.texts:
            if t.get_text() == "fail":
                continue
            r, g, b, _ = im.cmap(im.norm(float(t.get_text())))
            light = 0.2126 * r + 0.7152 * g + 0.0722 * b > 0.5
            assert t.get_color() == ("black" if light else "white"), t.get_text()
    from PIL import Image

    assert round(Image.open(out).info["dpi"][0]) == 200


def test_monte_carlo_cdfs_keep_overlapping_laws_visible_and_say_so(tmp_path, monkeypatch, capsys):
    """Two grid cells with identical results (a key that changes no figure) and
    a third that differs: each CDF in its own colour, line style and marker,
    markers staggered so an identical curve's do not cover the other's, the
    overlap said in the legend, and the shares saying what they count."""
    (fig, _), = _swept_and_drawn(
        tmp_path, monkeypatch, capsys,
        "version: 1\nname: mc\nbase: base.yaml\ngrid:\n"
        "  acceptance.max_fault_share: [0.02, 0.5]\n"  # judged after the run: the same figures
        "random:\n  n: 20\n  seed: 3\n  plant.driver_tau_s: {uniform: [0.0, 0.01]}\nmetrics: [force_nrmse]\n",
        ["--out", str(tmp_path / "cdf.png"), "--bound", "0.01"])
    cdf = fig.axes[0]
    curves = [ln for ln in cdf.lines if len(ln.get_xdata()) > 2]
    assert len(curves) == 2
    a, b = curves
    np.testing.assert_array_equal(a.get_xdata(), b.get_xdata())  # the same draws, the same figures
    assert a.get_color() != b.get_color() and a.get_linestyle() != b.get_linestyle()
    assert a.get_marker() != b.get_marker()
    xa = set(np.asarray(a.get_xdata())[_marked(a)].tolist())
    xb = set(np.asarray(b.get_xdata())[_marked(b)].tolist())
    assert xa and xb and not (xa & xb)  # staggered: neither hides the other's markers
    legend = [t.get_text() for t in cdf.get_legend().get_texts()]
    assert sum("identical to" in t for t in legend) == 1, legend
    assert all(" of 20 ≤ 0.01" in t for t in legend), legend  # n of N points, per cell
    assert "40 points, 0 not ok; 20 draws per cell" in fig.get_suptitle()
    labels = [lab for ax in fig.axes for lab in (ax.get_xlabel(), ax.get_ylabel())]
    assert labels[0].startswith("force_nrmse: RMS(F − F_des)")
    assert all(len(line) <= 60 for lab in labels for line in lab.splitlines()), labels  # none runs off the page


def _marked(line) -> np.ndarray:
    """Indices of a line's points that carry a marker (its markevery)."""
    n = len(line.get_xdata())
    every = line.get_markevery()
    if every is None:
        return np.arange(n)
    if isinstance(every, tuple):
        start, step = every
        return np.arange(start, n, step)
    return np.arange(0, n, every)
