"""A run log replays: it is an excitation file (t, x, v read, the rest
ignored), and ``mrctl simulate --replay`` re-runs its motion with another law."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mrctl.cli import main
from mrctl.runlog.read import read_run

ROOT = Path(__file__).resolve().parents[1]
FIG5 = str(ROOT / "config" / "experiments" / "fig5.yaml")


def _log(tmp_path: Path, seconds: str = "0.5") -> Path:
    out = tmp_path / "sim.csv"
    assert main(["simulate", FIG5, "--duration", seconds, "--out", str(out), "-q"]) == 0
    return out


def test_a_run_log_is_an_excitation_file(tmp_path, capsys):
    """simulate's log has late_us/compute_us NaN in every row and a fault
    column: only t, x, v are read; a missing sample (NaN x) is skipped."""
    log = _log(tmp_path)
    text = log.read_text().splitlines()
    assert ",nan," in text[1]  # what made the old reader refuse it
    text[5] = ",".join(["nan" if i in (1, 2) else f for i, f in enumerate(text[5].split(","))])
    log.write_text("\n".join(text) + "\n")
    cfg = tmp_path / "replay.yaml"
    cfg.write_text(Path(FIG5).read_text().replace(
        "excitation: {type: sine, amplitude_m: 0.010, frequency_hz: 1.0}", f"excitation: {{type: file, path: {log}}}")
        .replace("duration_s: 4.0", "duration_s: 0.5"))
    assert "type: file" in cfg.read_text()
    out = tmp_path / "again.csv"
    assert main(["simulate", str(cfg), "--out", str(out)]) == 0, capsys.readouterr().err
    a, b = read_run(log), read_run(out)
    n = min(len(a["t"]), len(b["t"]))
    keep = np.isfinite(a["x"][:n])
    assert np.allclose(a["x"][:n][keep], b["x"][:n][keep], atol=1e-9)  # the same motion


def test_simulate_replay_reruns_the_motion_with_another_law(tmp_path, capsys):
    log = _log(tmp_path)
    out = tmp_path / "paper.csv"
    assert main(["simulate", "--replay", str(log), "--law", "paper", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "law paper" in text and "replay of sim.csv" in text
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["law"] == "paper" and side["replay_of"] == str(log.resolve())
    assert side["config"]["safety"]["I_max"] == 0.6  # the rest is the logged experiment's
    a, b = read_run(log), read_run(out)
    assert len(b["t"]) >= len(a["t"]) - 1
    n = len(a["t"])
    assert np.allclose(a["x"], b["x"][:n], atol=1e-9) and np.allclose(a["v"], b["v"][:n], atol=1e-9)
    assert not np.allclose(a["I"], b["I"][:n])  # another law, another current
    # the same law again reproduces the log's current
    same = tmp_path / "same.csv"
    assert main(["simulate", "--replay", str(log), "--out", str(same), "-q"]) == 0
    assert np.allclose(read_run(same)["I"][:n], a["I"], atol=1e-6)


def test_replay_with_a_config_and_the_errors(tmp_path, capsys):
    log = _log(tmp_path, "0.3")
    assert main(["simulate", FIG5, "--replay", str(log), "--law", "closed"]) == 0
    assert "law closed" in capsys.readouterr().out
    assert main(["simulate", "--replay", str(tmp_path / "none.csv")]) == 2
    assert "no such run log" in capsys.readouterr().err
    log.with_suffix(".json").unlink()
    assert main(["simulate", "--replay", str(log)]) == 2
    err = capsys.readouterr().err
    assert "sidecar" in err and "CONFIG" in err and "Traceback" not in err
    assert main(["simulate", "--replay", str(log), "--law", "nosuch"]) == 2
    assert main(["simulate"]) == 2
    assert "--replay" in capsys.readouterr().err
