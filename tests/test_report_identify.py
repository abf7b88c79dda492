"""The identification figure (paper's Figs 2 and 3) added to mrctl.offline.report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mrctl.offline.identify import identify
from mrctl.offline.report import ReportError, make_identification_report, make_report
from test_identify import cli_identify, staircase, write_run_csv  # tests/ is on sys.path (rootdir-less test modules)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def run4():
    return staircase([0.0, 0.2, 0.35, 0.5], step_s=1.5)


@pytest.fixture(scope="module")
def result4(run4):
    return identify([run4])


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_from_result(result4, tmp_path):
    out = tmp_path / "ident.png"
    make_identification_report(result4, out, title="synthetic")
    w, h = _png_size(out)
    assert w > 1500 and h > 1500


def test_from_csv_path_and_without_reference(run4, tmp_path):
    csv_path = write_run_csv(tmp_path / "run.csv", run4)
    out = tmp_path / "ident.png"
    make_identification_report(str(csv_path), out, show_reference=False)
    _png_size(out)


def test_from_run_dicts_with_identify_options(run4, tmp_path):
    out = tmp_path / "ident.png"
    make_identification_report([run4], out, fit_periods=1)
    _png_size(out)


def test_bad_runs_are_report_errors(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,v,F\n0,0,0\n0.001,0.1,1\n")
    with pytest.raises(ReportError, match="current column 'I'"):
        make_identification_report(bad, tmp_path / "x.png")
    with pytest.raises(ReportError, match="no such file"):
        make_identification_report(tmp_path / "missing.csv", tmp_path / "x.png")


def test_unwritable_output(result4, tmp_path):
    with pytest.raises(ReportError, match="cannot write the figure"):
        make_identification_report(result4, tmp_path / "no" / "such" / "dir" / "x.png")


def test_fig5_report_unchanged_on_an_identification_run(run4, tmp_path):
    """The existing report still reads a run CSV with the identification columns."""
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
