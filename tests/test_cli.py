"""The mrctl command line: simulate, report, check; clean errors, exit codes."""

import json
from pathlib import Path

import numpy as np
import pytest

from mrctl.cli import main

ROOT = Path(__file__).resolve().parents[1]
FIG5 = str(ROOT / "config" / "experiments" / "fig5.yaml")


def test_simulate_writes_csv_sidecar_and_summary(tmp_path, capsys):
    out = tmp_path / "run.csv"
    assert main(["simulate", FIG5, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "force NRMSE" in text and "largest current step" in text and "ticks at 0 A" in text
    lines = [l for l in out.read_text().splitlines() if not l.startswith("#")]
    header = lines[0].split(",")
    assert header[:6] == ["t", "x", "v", "F_des", "F", "I"]
    data = np.loadtxt(out, delimiter=",", skiprows=1)  # the header only: no comment line since 2026-11
    assert data.shape[0] == 4001
    assert np.allclose(np.diff(data[:, 0]), 0.001)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["config"]["inverse"]["law"] == "smooth"
    assert meta["summary"]["max_current_step_A"] <= 0.05 + 1e-12


def test_report_draws_a_png(tmp_path):
    import matplotlib  # noqa: F401 - a test dependency: missing, the test fails
    out = tmp_path / "run.csv"
    assert main(["simulate", FIG5, "--out", str(out), "--duration", "2"]) == 0
    png = tmp_path / "fig.png"
    assert main(["report", str(out), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_config_exits_2_with_key_and_no_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(Path(FIG5).read_text().replace("law: smooth", "law: smoth"))
    assert main(["simulate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "inverse.law" in err and "Traceback" not in err
    assert main(["check", str(bad)]) == 2
    assert main(["check", FIG5]) == 0


def test_report_of_missing_file_is_a_clean_error(tmp_path, capsys):
    import matplotlib  # noqa: F401 - a test dependency: missing, the test fails
    assert main(["report", str(tmp_path / "none.csv"), "--out", str(tmp_path / "x.png")]) == 2
    assert "none.csv" in capsys.readouterr().err


def test_check_refuses_a_link_that_cannot_do_the_rate(tmp_path, capsys):
    cfg = tmp_path / "rtu.yaml"
    text = Path(FIG5).read_text().replace(
        "backend: {type: sim}", "backend: {type: modbus-rtu, url: /dev/ttyUSB0, baudrate: 115200}")
    cfg.write_text(text)
    assert main(["check", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "does not fit 1000 Hz" in err and "100 Hz" in err
    cfg.write_text(text.replace("115200", "921600"))
    assert main(["check", str(cfg)]) == 0
    cfg.write_text(text + "link: {on_infeasible: reduce_rate}\n")
    assert main(["check", str(cfg)]) == 0  # a warning, the run would go at 100 Hz
    assert "warning" in capsys.readouterr().err


def test_report_of_a_daemon_run_with_faults(tmp_path):
    """NaN rows (sample faults, 0 A held) are gaps, not errors."""
    import matplotlib  # noqa: F401 - a test dependency: missing, the test fails
    cfg = tmp_path / "f.yaml"
    cfg.write_text("version: 1\nduration_s: 1.5\n"
                   "excitation: {type: sine, amplitude_m: 0.01, frequency_hz: 1.0}\n"
                   "demand: {type: viscous, c_des: 500}\ninverse: {law: smooth}\n"
                   "safety: {I_max: 0.6, hold_ticks: 2, v_range_mps: [-0.05, 0.05], auto_resume: true}\n")
    out = tmp_path / "run.csv"
    assert main(["run", str(cfg), "--out", str(out), "--quiet", "--status-socket", str(tmp_path / "s")]) == 5
    text = out.read_text()
    assert "nan" in text  # the supervisor did fault (|v| > 0.05 m/s near the peaks)
    png = tmp_path / "r.png"
    assert main(["report", str(out), "--out", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_simulate_sidecar_with_sets_and_ranges_in_the_config(tmp_path, capsys):
    """rt.cpus (a set) and safety ranges (tuples) must reach the JSON sidecar."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(Path(FIG5).read_text().replace("safety: {I_max: 0.6}",
                   "safety: {I_max: 0.6, x_range_m: [-0.05, 0.05]}") + "rt: {cpus: [0]}\n")
    out = tmp_path / "run.csv"
    assert main(["simulate", str(cfg), "--out", str(out), "--duration", "0.5"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["config"]["rt"]["cpus"] == [0]
    assert meta["config"]["safety"]["x_range_m"] == [-0.05, 0.05]
