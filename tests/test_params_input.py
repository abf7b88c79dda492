"""What a parameter set's laws take (current or voltage), and the driver's match.

A parameters file may say ``input: voltage`` (laws in volts, identified from a
driver's command voltage) and ``input_range``; an experiment's
``backend.input`` must match, or the config is refused naming both keys.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mrctl.cli import main
from mrctl.config import ConfigError, load_params_file, validate_experiment
from mrctl.config.params import read_params_file
from mrctl.model.params import TABLE_I

GOOD = {
    "version": 1,
    "duration_s": 0.2,
    "excitation": {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0},
    "demand": {"type": "viscous", "c_des": 500},
    "inverse": {"law": "smooth"},
    "safety": {"I_max": 0.6},
}


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _voltage_set(tmp_path: Path) -> Path:
    return _write(tmp_path / "v.yaml", "input: voltage\ninput_range: [0.0, 2.5]\nvsA: -0.005\nF_offset: 12.0\ntau_input: 0.009\n")


def test_input_kind_and_range_are_read(tmp_path):
    pf = read_params_file(_voltage_set(tmp_path))
    assert pf.input == "voltage" and pf.unit == "V" and pf.input_range == (0.0, 2.5)
    assert pf.params.F_offset == 12.0 and pf.params.tau_input == 0.009
    assert load_params_file(tmp_path / "v.yaml") == pf.params
    plain = read_params_file(_write(tmp_path / "c.yaml", "F0: 3.0\n"))
    assert plain.input == "current" and plain.input_range is None


@pytest.mark.parametrize("text, expect", [
    ("input: amps\n", "input: 'amps' not allowed (allowed: current, voltage"),
    ("input_range: [2.0, 1.0]\n", "input_range: must be [lo, hi] with lo < hi"),
    ("input_range: [0, x]\n", "input_range: must be [lo, hi]"),
    ("input_range: 3\n", "input_range: must be [lo, hi]"),
    # a set whose law leaves the physical range inside its own identified range
    ("input: voltage\ninput_range: [0, 3.0]\nvsA: -0.02\nvsB: 0.03\n",
     "input_range: vs(I) must stay > 0 for I in [0, 3] V"),
])
def test_bad_metadata_is_a_config_error(tmp_path, text, expect):
    with pytest.raises(ConfigError, match=re.escape(expect)):
        read_params_file(_write(tmp_path / "p.yaml", text))


def test_current_driver_refuses_a_voltage_set(tmp_path):
    _voltage_set(tmp_path)
    data = {**GOOD, "parameters": "v.yaml"}
    with pytest.raises(ConfigError) as ei:
        validate_experiment(data, tmp_path)
    msg = str(ei.value)
    assert "parameters: the set in" in msg and "input: voltage" in msg and "backend.input is 'current'" in msg
    # the simulated damper's own set is checked too
    data = {**GOOD, "plant": {"parameters": "v.yaml"}}
    with pytest.raises(ConfigError, match="plant.parameters: .*backend.input is 'current'"):
        validate_experiment(data, tmp_path)


def test_matching_driver_input_is_accepted(tmp_path):
    _voltage_set(tmp_path)
    cfg = validate_experiment({**GOOD, "parameters": "v.yaml", "backend": {"type": "sim", "input": "voltage"}},
                              tmp_path)
    assert cfg.backend.input == "voltage" and cfg.parameters.F_offset == 12.0
    # Table I takes a current: a voltage driver refuses it
    with pytest.raises(ConfigError, match="parameters: the set in table1 takes a current"):
        validate_experiment({**GOOD, "backend": {"type": "sim", "input": "voltage"}}, tmp_path)
    assert validate_experiment(GOOD, tmp_path).backend.input == "current"


def test_cli_check_exits_2_naming_both_keys(tmp_path, capsys):
    _voltage_set(tmp_path)
    cfg = _write(tmp_path / "exp.yaml", "version: 1\nparameters: v.yaml\nexcitation: {type: sine, amplitude_m: 0.01, "
                 "frequency_hz: 1.0}\ndemand: {type: viscous, c_des: 500}\ninverse: {law: smooth}\n"
                 "safety: {I_max: 0.6}\nbackend: {type: sim}\n")
    assert main(["check", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "parameters:" in err and "backend.input" in err and "Traceback" not in err


def test_check_range_over_an_input_range():
    assert TABLE_I.check_range(0.55) == []
    bad = TABLE_I.with_overrides(vsA=0.02, vsB=-0.001)  # vs < 0 below 0.05 A only
    assert bad.check_range(0.55, I_min=0.1) == []
    problems = bad.check_range(0.55, I_min=0.0, unit="V")
    assert len(problems) == 1 and "[0, 0.55] V" in problems[0]
