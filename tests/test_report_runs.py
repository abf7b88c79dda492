"""mrctl report: torn logs, several runs overlaid, the format of the name, and
figures that mean what the daemon's mean."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mrctl.cli import main

ROOT = Path(__file__).resolve().parents[1]
EXP = ROOT / "config" / "experiments"

import matplotlib  # noqa: E402,F401 - a test dependency: missing, these tests fail


def _simulate(tmp_path: Path, name: str, duration: str = "2", text: str | None = None) -> Path:
    cfg = EXP / name
    if text is not None:
        cfg = tmp_path / name
        cfg.write_text(text)
    out = tmp_path / (Path(name).stem + ".csv")
    assert main(["simulate", str(cfg), "--out", str(out), "--duration", duration]) == 0
    return out


# -- 7. a torn last line (full disk, SIGKILL) -------------------------------------------
def test_report_and_identify_read_a_log_with_a_torn_last_line(tmp_path):
    from mrctl.config.dataset import validate_dataset
    from mrctl.offline.identify import describe_runs
    from mrctl.offline.identify.records import read_records

    csv = _simulate(tmp_path, "fig5.yaml")
    rows = len(csv.read_text().splitlines()) - 1
    with csv.open("a") as fh:
        fh.write("2.001,0.0099,-0.00")  # what a writer killed mid-line leaves
    assert main(["report", str(csv), "--out", str(tmp_path / "f.png")]) == 0
    doc = describe_runs([csv])
    doc["columns"]["input"] = None  # fig5's current is closed loop: read the columns only
    doc["files"][0]["level"] = 0.0
    rec, = read_records(validate_dataset(doc, tmp_path, allow_outside=True))
    lag = json.loads(csv.with_suffix(".json").read_text())["load_cell_delay_ticks"]
    assert rec.t.size == rows - lag  # every whole row, F moved back to its own tick
    assert rec.notes == ["its last line was cut off mid-write; dropped"]


# -- 12. the format is the name's --------------------------------------------------------
MAGIC = {"png": b"\x89PNG", "pdf": b"%PDF", "svg": b"<?xml"}


@pytest.mark.parametrize("ext", sorted(MAGIC))
def test_report_writes_the_format_its_name_says(tmp_path, ext):
    csv = _simulate(tmp_path, "fig5.yaml", "1.5")
    fig = tmp_path / f"fig.{ext}"
    assert main(["report", str(csv), "--out", str(fig)]) == 0
    assert fig.read_bytes()[:5].startswith(MAGIC[ext])


def test_report_refuses_a_format_it_cannot_write(tmp_path, capsys):
    csv = _simulate(tmp_path, "fig5.yaml", "1.5")
    assert main(["report", str(csv), "--out", str(tmp_path / "fig.docx")]) == 2
    err = capsys.readouterr().err
    assert ".docx" in err and "png" in err and "pdf" in err and "svg" in err
    assert not (tmp_path / "fig.docx").exists()


def test_report_overlays_several_runs_labelled_by_file_and_law(tmp_path):
    paper = _simulate(tmp_path, "fig5_paper.yaml")
    smooth = _simulate(tmp_path, "fig5.yaml")
    fig = tmp_path / "both.svg"
    assert main(["report", str(paper), str(smooth), "--out", str(fig)]) == 0
    from mrctl.offline.report import make_report

    runs = make_report([paper, smooth], tmp_path / "both.png")
    assert [r["label"] for r in runs] == ["fig5_paper.csv (paper)", "fig5.csv (smooth)"]
    assert runs[0]["max_dI"] > 0.3 and runs[1]["max_dI"] <= 0.05 + 1e-9  # the spikes against none


def test_report_share_at_I_max_is_the_daemons(tmp_path):
    """A run that never reaches I_max has 0 % there, in the daemon's summary and
    in the report (which used to count the run's own largest current)."""
    from mrctl.offline.report import make_report

    text = (EXP / "fig5.yaml").read_text().replace("safety: {I_max: 0.6}", "safety: {I_max: 1.0}")
    csv = _simulate(tmp_path, "high_limit.yaml", text=text)
    side = json.loads(csv.with_suffix(".json").read_text())
    assert side["summary"]["share_at_I_max"] == 0.0
    (r,) = make_report([csv], tmp_path / "f.png")
    assert r["share_max"] == side["summary"]["share_at_I_max"]
    assert r["I_max"] == 1.0
    # and for a daemon log: the figures of the sidecar's summary
    out = tmp_path / "run.csv"
    cfg = tmp_path / "run.yaml"
    cfg.write_text(text + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")  # timing not judged: a shared machine
    assert main(["run", str(cfg), "--out", str(out), "--duration", "2", "--quiet",
                 "--status-socket", str(tmp_path / "s.sock")]) == 0
    track = json.loads(out.with_suffix(".json").read_text())["summary"]["tracking"]
    (r,) = make_report([out], tmp_path / "g.png")
    assert r["share_max"] == track["share_at_I_max"] == 0.0
    assert r["share_zero"] == pytest.approx(track["share_at_zero"])
