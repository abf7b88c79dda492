"""The sweep heat map as a reviewer reads it, checked on the drawn figure:
200 dpi, one colour scale across panels, key paths with their units, and
cell numbers dark on light cells and light on dark ones."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

from mrctl.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_heat_map_panels_share_one_scale_at_200_dpi(tmp_path, monkeypatch, capsys):
    base = tmp_path / "base.yaml"
    base.write_text((ROOT / "config" / "experiments" / "fig5.yaml").read_text()
                    .replace("duration_s: 4.0", "duration_s: 1.5"))
    sweep = tmp_path / "s.yaml"
    sweep.write_text("version: 1\nname: s\nbase: base.yaml\ngrid:\n  demand.c_des: [250, 750]\n"
                     "  plant.driver_tau_s: [0.0, 0.01]\n  inverse.law: [smooth, paper]\nmetrics: [force_nrmse]\n")
    table = tmp_path / "r.csv"
    assert main(["sweep", str(sweep), "--out", str(table), "--workers", "1", "-q"]) == 0
    import matplotlib.figure

    drawn = []
    real = matplotlib.figure.Figure.savefig

    def keep(fig, *a, **k):
        drawn.append((fig, k))
        return real(fig, *a, **k)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    out = tmp_path / "map.png"
    assert main(["report", str(table), "--out", str(out)]) == 0, capsys.readouterr().err
    (fig, kw), = drawn
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
