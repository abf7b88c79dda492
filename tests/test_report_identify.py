"""The identification figure (mrctl.offline.identify_figure) of mrctl's own runs: the same figure as a dataset's."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from mrctl.offline.identify_figure import FigureError, make_identification_figure
from mrctl.offline.report import make_report
from test_identify import cli_identify, identify_csvs, staircase, write_run_csv  # tests/ is on sys.path

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def run4():
    return staircase([0.0, 0.2, 0.35, 0.5], step_s=2.0)


@pytest.fixture(scope="module")
def result4(run4, tmp_path_factory):
    return identify_csvs(tmp_path_factory.mktemp("r4"), [run4])


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_the_summary_page_reads_at_a_glance(result4, tmp_path):
    """Four levels: one page of at most twelve panels (scores, the worst
    held-out record and its loop, the six parameters), none empty, no unit
    said twice on an axis, every legend's entries told apart; the detail
    page has every level's force and loop."""
    from figure_checks import axes_without_data, doubled_units, legends_with_lookalikes

    from mrctl.offline.identify_figure import build_identification_figure

    fig = build_identification_figure(result4, title="synthetic")
    labels = [ax.get_label() for ax in fig.axes]
    assert len(labels) <= 12, labels
    assert {"scores", "worst-time", "worst-fv"} <= set(labels)
    assert sorted(q for q in labels if q.startswith("theta-")) == sorted(
        f"theta-{n}" for n in ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2"))
    assert not axes_without_data(fig) and not doubled_units(fig) and not legends_with_lookalikes(fig)
    # the scores panel draws every record's held-out NRMSE, per level
    scores = next(ax for ax in fig.axes if ax.get_label() == "scores")
    drawn = sorted(float(y) for ln in scores.lines if ln.get_linestyle() in ("None", "none")
                   for y in ln.get_ydata())
    assert drawn == pytest.approx(sorted(100 * (s.nrmse_laws if s.nrmse_laws is not None else s.nrmse)
                                         for s in result4.holdout))
    # the worst record is the one drawn beside
    worst = max(result4.holdout, key=lambda s: s.nrmse_laws if s.nrmse_laws is not None else s.nrmse)
    assert f"at {worst.level:.4g} A" in next(ax for ax in fig.axes if ax.get_label() == "worst-time").get_title()
    detail = build_identification_figure(result4, detail=True)
    levels = sorted(lv["level"] for lv in result4.details["levels"])
    assert sorted(ax.get_label() for ax in detail.axes if ax.get_label().startswith("time-")) == sorted(
        f"time-{lv:.4g}" for lv in levels)
    assert not axes_without_data(detail) and not doubled_units(detail)
    one = copy.copy(result4)
    one.details = {**result4.details, "levels": result4.details["levels"][:1]}
    fig1 = build_identification_figure(one)
    assert not [ax for ax in fig1.axes if ax.get_label().startswith("theta-")]  # no laws for one level
    assert not axes_without_data(fig1)


def test_cli_draws_the_detail_page_on_request(run4, tmp_path, capsys):
    csv_path = write_run_csv(tmp_path / "run.csv", run4)
    png, detail = tmp_path / "ident.png", tmp_path / "detail.png"
    from mrctl.cli import main

    assert main(["identify", str(csv_path), "--out", str(tmp_path / "p.yaml"), "--report", str(png),
                 "--report-detail", str(detail)]) == 0
    out = capsys.readouterr().out
    assert f"wrote {png}" in out and f"wrote {detail}" in out
    assert _png_size(detail)[0] > 0 and detail.read_bytes() != png.read_bytes()
    # one name for both figures is refused before anything is fitted
    assert main(["identify", str(csv_path), "--out", str(tmp_path / "q.yaml"), "--report", str(tmp_path / "x.png"),
                 "--report-detail", str(tmp_path / "x.png")]) == 2
    assert not (tmp_path / "q.yaml").exists()


def test_unwritable_output(result4, tmp_path):
    with pytest.raises(FigureError, match="cannot write the figure"):
        make_identification_figure(result4, tmp_path / "no" / "such" / "dir" / "x.png")
    with pytest.raises(FigureError, match="unknown figure format"):
        make_identification_figure(result4, tmp_path / "x.docx")


def test_fig5_report_unchanged_on_an_identification_run(run4, tmp_path):
    """The run report still reads a run CSV with the identification columns."""
    run = dict(run4)
    run["F_des"] = np.zeros_like(run["t"])
    csv_path = write_run_csv(tmp_path / "run.csv", run)
    make_report(csv_path, tmp_path / "fig5.png")
    _png_size(tmp_path / "fig5.png")


def test_cli_identify_draws_the_figure(run4, tmp_path, capsys):
    csv_path = write_run_csv(tmp_path / "run.csv", run4)
    png = tmp_path / "ident.png"
    assert cli_identify([str(csv_path)], str(tmp_path / "p.yaml"), report_png=str(png)) == 0
    assert f"wrote {png}" in capsys.readouterr().out
    _png_size(png)
