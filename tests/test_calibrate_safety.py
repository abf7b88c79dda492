"""`mrctl calibrate` is a device owner like `mrctl run` (the same lock, refused
naming the owner before a byte goes out), and it refuses a calibration built on
an input that read one constant value at rest (a disconnected or stuck input)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from mrctl.cli import main as mrctl_main
from mrctl.io.base import Sample

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENT = ROOT / "config" / "experiments" / "labjack_t7.yaml"


def _exp(tmp_path: Path, host: str = "127.0.0.1", port: int = 5021) -> Path:
    data = yaml.safe_load(EXPERIMENT.read_text())
    data["backend"].update(host=host, port=port)
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


@pytest.mark.parametrize("spelling", ["127.0.0.1", "0.0.0.0", "localhost"])
def test_calibrate_beside_an_owner_is_refused_naming_it_before_opening(tmp_path, monkeypatch, capsys, spelling):
    """A daemon owns the T7 served here at 127.0.0.1:P; calibrate of the same device by any
    local spelling exits 3 naming the owner. Nothing listens on P: had it tried to open the
    link, the error would be "cannot open" instead."""
    from mrctl.daemon.ownership import acquire
    from mrctl.io.device_keys import network_device_key

    monkeypatch.setenv("MRCTL_LOCK_DIR", str(tmp_path / "locks"))
    lock = acquire(network_device_key("modbus-tcp", "127.0.0.1", 1), "mrctl run owner.yaml")
    try:
        code = mrctl_main(["calibrate", str(_exp(tmp_path, spelling, 1)), "--out", str(tmp_path / "cal.yaml")])
    finally:
        lock.release()
    err = capsys.readouterr().err
    assert code == 3, err
    assert "in use by another mrctl" in err and "cannot open" not in err, err
    assert not (tmp_path / "cal.yaml").exists()


class _ConstantMonitorLink:
    """A split link whose x and F are noisy but whose current monitor reads one value."""

    split = True

    def __init__(self) -> None:
        self.rng = np.random.default_rng(1)
        self.timeout_s = 0.01
        self.opened = self.closed = 0

    def device_key(self) -> None:
        return None

    def describe(self) -> str:
        return "fake T7"

    def open(self) -> None:
        self.opened += 1

    def close(self) -> None:
        self.closed += 1

    def write(self, current_A: float) -> None:
        pass

    def read(self) -> Sample:
        x, F = self.rng.normal(0.0, 2e-6), self.rng.normal(0.0, 0.5)
        return Sample(0, 0.0, float(x), math.nan, float(F), 0, 0.0)


def _fake_exp(tmp_path):
    from mrctl.config import load_experiment
    from mrctl.experiment import build

    exp = build(load_experiment(_exp(tmp_path)))
    link = _ConstantMonitorLink()
    exp.make_link = lambda: link
    return exp, link


def test_a_constant_input_at_rest_is_refused_unless_accepted(tmp_path):
    from mrctl.daemon.calibrate import CalibrationOptions, DeadChannels, calibrate

    exp, link = _fake_exp(tmp_path)
    with pytest.raises(DeadChannels, match=r"current_monitor \(AIN2\) read 0 V on all"):
        calibrate(exp, CalibrationOptions(rest_s=0.1, steps=0, rate_hz=500.0), say=lambda m: None)
    assert link.closed == link.opened == 1  # closed (0 A) on the way out
    said: list[str] = []
    cal = calibrate(exp, CalibrationOptions(rest_s=0.1, steps=0, rate_hz=500.0, accept_dead_channels=True),
                    say=said.append)
    assert cal["channels"]["current_monitor"]["noise_V"] == 0.0 and cal["channels"]["x"]["noise_V"] > 0.0
    assert any("constant at rest (accepted)" in m for m in said)
