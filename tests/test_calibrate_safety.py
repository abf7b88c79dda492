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


class _LatchingBench:
    """An exchange device for calibrate: noisy x and F, a current monitor that follows the command
    with a 5 ms lag, and a latching status: ESTOP from exchange ``estop_from`` on (the input stays
    open), a watchdog trip an earlier run left (cleared by CLEAR_FAULTS). Records what it is sent."""

    split = False

    def __init__(self, estop_from: int = 10**9, tripped: bool = False) -> None:
        self.rng = np.random.default_rng(2)
        self.timeout_s = 0.01
        self.estop_from, self.tripped = estop_from, tripped
        self.sent: list[float] = []
        self.clears = self.closed = 0
        self.I = 0.0

    def device_key(self) -> None:
        return None

    def describe(self) -> str:
        return "latching bench"

    def open(self) -> None:
        pass

    def close(self) -> None:
        self.closed += 1

    def request_clear_faults(self) -> bool:
        self.clears += 1
        self.tripped = False
        return True

    def exchange(self, current_A: float) -> Sample:
        from mrctl.io.base import Status

        self.sent.append(current_A)
        self.I += (current_A - self.I) * (1.0 - math.exp(-2e-3 / 5e-3))
        status = (int(Status.ESTOP) if len(self.sent) >= self.estop_from else 0) \
            | (int(Status.WATCHDOG_TRIPPED) if self.tripped else 0)
        x, F = self.rng.normal(0.0, 2e-6), self.rng.normal(0.0, 0.5)
        return Sample(len(self.sent), 0.0, float(x), math.nan, float(F), status,
                      self.I + float(self.rng.normal(0.0, 1e-3)))


def _latching_exp(tmp_path, link):
    from mrctl.config import load_experiment
    from mrctl.experiment import build

    exp = build(load_experiment(_exp(tmp_path)))
    exp.make_link = lambda: link
    return exp


def test_an_e_stop_during_the_current_steps_stops_calibrate_at_0A(tmp_path):
    """The E-stop opens in the middle of the current steps: calibrate stops at that sample, sends
    no further step (its close commands 0 A, output disabled), and writes nothing (exit 3)."""
    from mrctl.daemon.calibrate import CalibrationOptions, calibrate
    from mrctl.errors import LinkFailure

    opts = CalibrationOptions(rest_s=0.1, steps=8, step_A=0.3, step_s=0.02, rate_hz=500.0)
    n_rest = 50
    link = _LatchingBench(estop_from=1 + n_rest + 25)  # the start's read, the rest, then into the steps
    with pytest.raises(LinkFailure, match=r"stopped at 0 A: the E-stop input is open \(during the current steps"):
        calibrate(_latching_exp(tmp_path, link), opts, say=lambda m: None)
    assert len(link.sent) == link.estop_from and max(link.sent) == 0.3  # it was stepping: no step after the E-stop
    assert link.closed == 1


def test_calibrate_refuses_to_start_with_the_e_stop_open_and_clears_what_an_earlier_run_left(tmp_path):
    from mrctl.daemon.calibrate import CalibrationOptions, calibrate
    from mrctl.errors import LinkFailure

    opts = CalibrationOptions(rest_s=0.1, steps=2, step_A=0.3, step_s=0.02, rate_hz=500.0)
    link = _LatchingBench(estop_from=1)
    with pytest.raises(LinkFailure, match="refusing to start: the E-stop input is open; close it"):
        calibrate(_latching_exp(tmp_path, link), opts, say=lambda m: None)
    assert set(link.sent) == {0.0} and link.closed == 1
    link = _LatchingBench(tripped=True)  # a watchdog trip an earlier run left: cleared, then calibrated
    cal = calibrate(_latching_exp(tmp_path, link), CalibrationOptions(rest_s=0.1, steps=0, rate_hz=500.0),
                    say=lambda m: None)
    assert link.clears >= 1 and not link.tripped and cal["channels"]["x"]["noise_V"] > 0.0
