"""The identification figure (mrctl.offline.identify_figure) of mrctl's own runs: the same figure as a dataset's."""

from __future__ import annotations

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


def test_every_level_and_the_parameter_panels(result4, tmp_path):
    out = tmp_path / "ident.png"
    make_identification_figure(result4, out, title="synthetic")
    w, h = _png_size(out)
    # four levels in one row of force and F-v panels, and two rows of the six parameters per level
    assert w > 1500 and h > 1500
    single = tmp_path / "one.png"
    import copy

    one = copy.copy(result4)
    one.details = {**result4.details, "levels": result4.details["levels"][:1]}
    make_identification_figure(one, single)
    assert _png_size(single)[1] < h  # no parameter panels for a single level


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
