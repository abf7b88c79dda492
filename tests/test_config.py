"""Config errors: every rejection names the key; nothing invalid gets through."""

import textwrap
from pathlib import Path

import pytest

from mrctl.config import ConfigError, load_experiment, load_params_file, validate_experiment

GOOD = {
    "version": 1,
    "duration_s": 1.0,
    "excitation": {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0},
    "demand": {"type": "viscous", "c_des": 500},
    "inverse": {"law": "smooth"},
    "safety": {"I_max": 0.6},
}


def _errors(data, base=Path(".")):
    with pytest.raises(ConfigError) as ei:
        validate_experiment(data, base)
    return ei.value.errors


def _with(path, value):
    import copy

    data = copy.deepcopy(GOOD)
    node = data
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    return data


def test_good_config_fills_defaults():
    cfg = validate_experiment(GOOD, Path("."))
    assert cfg.rate_hz == 1000.0
    assert cfg.inverse.eps_N_per_A == 3.0 and cfg.inverse.max_slew_A_per_s == 50.0
    assert cfg.backend.type == "sim"
    assert cfg.parameters.F0 == 2.90


@pytest.mark.parametrize(
    "path,value,expect",
    [
        ("inverse.lwa", "x", "inverse.lwa: unknown key"),
        ("excitation.amplitude", 0.01, "excitation.amplitude: unknown key"),
        ("colour", "red", "colour: unknown key"),
        ("safety.I_max", -0.1, "safety.I_max: -0.1 out of range"),
        ("safety.I_max", 5.0, "safety.I_max: 5.0 out of range"),
        ("safety.I_max", "0.6", "safety.I_max: must be a number"),
        ("safety.I_max", True, "safety.I_max: must be a number"),
        ("safety.I_max", float("nan"), "safety.I_max: must be finite"),
        ("demand.c_des", -5, "demand.c_des: -5 out of range"),
        ("inverse.law", "papr", "inverse.law: 'papr' not allowed (allowed: paper, smooth, closed, constant, schedule)"),
        ("excitation.type", "square", "excitation.type: 'square' not allowed"),
        ("rate_hz", 0, "rate_hz: 0 out of range"),
        ("version", 2, "version: 2 out of range"),
        ("parameters", {"F0": "x"}, "parameters.F0: must be a finite number"),
        ("parameters", {"Fzero": 1.0}, "parameters.Fzero: unknown parameter"),
        ("parameters", {"vsB": 0.005}, "parameters: vs(I) must stay > 0"),
        ("excitation.path", "x.csv", "excitation.path: unknown key"),
        ("demand", {"type": "file", "path": "nope.csv"}, "demand.path: no such file"),
        ("inverse", {"law": "constant", "current_A": 0.9}, "inverse.current_A: 0.9 A exceeds safety.I_max"),
        ("inverse", {"law": "smooth", "max_slew_A_per_s": 0}, "inverse.max_slew_A_per_s: 0 out of range"),
        ("inverse", {"law": "schedule", "currents_A": [0.1, "x"], "step_s": 1}, "inverse.currents_A[1]: must be a number"),
        ("inverse", {"law": "schedule", "currents_A": [0.1, 0.7], "step_s": 1}, "inverse.currents_A[1]: 0.7 A exceeds"),
        ("inverse", {"law": "schedule", "currents_A": [], "step_s": 1}, "inverse.currents_A: must be a non-empty list"),
    ],
)
def test_each_error_names_its_key(path, value, expect):
    errors = _errors(_with(path, value))
    assert any(e.startswith(expect) for e in errors), errors


def test_missing_safety_section_is_an_error():
    data = dict(GOOD)
    data.pop("safety")
    assert "safety: missing required section" in _errors(data)


def test_all_errors_are_listed_at_once():
    data = _with("safety.I_max", -1)
    data["inverse"] = {"law": "nope"}
    data["junk"] = 1
    errors = _errors(data)
    assert len(errors) == 3


def test_yaml_traps(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text(textwrap.dedent("""\
        version: 1
        duration_s: 1e-1
        excitation: {type: sine, amplitude_m: 1e-2, frequency_hz: 1}
        demand: {type: viscous, c_des: 5e2}
        inverse: {law: paper}
        safety: {I_max: 0.6}
    """))
    cfg = load_experiment(p)
    assert cfg.duration_s == 0.1 and cfg.excitation.amplitude_m == 0.01 and cfg.demand.c_des == 500.0
    p.write_text(p.read_text() + "safety: {I_max: 0.9}\n")
    with pytest.raises(ConfigError, match="duplicate key 'safety'"):
        load_experiment(p)
    p.write_text("version: 1\n  bad: [indent\n")
    with pytest.raises(ConfigError, match="line 2"):
        load_experiment(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_experiment(tmp_path / "absent.yaml")


def test_params_file_and_overrides(tmp_path):
    pf = tmp_path / "p.yaml"
    pf.write_text("F0: 3.5\nAc: 60.0\nfit: {residual: 0.1}\n")
    assert load_params_file(pf).F0 == 3.5
    data = _with("parameters", {"file": "p.yaml", "Ac": 61.0})
    cfg = validate_experiment(data, tmp_path)
    assert cfg.parameters.F0 == 3.5 and cfg.parameters.Ac == 61.0
    pf.write_text("F0: 3.5\nsigmaX: 1\n")
    errors = _errors(_with("parameters", "p.yaml"), tmp_path)
    assert any("sigmaX: unknown parameter" in e for e in errors)


def test_shipped_experiments_are_valid():
    root = Path(__file__).resolve().parents[1] / "config" / "experiments"
    files = sorted(root.glob("*.yaml"))
    assert files
    for f in files:
        load_experiment(f)


def test_device_pacing_needs_a_device_clock():
    assert validate_experiment(GOOD, Path(".")).loop.pacing == "host"
    errs = _errors(_with("loop.pacing", "device"))  # backend defaults to the in-process sim
    assert len(errs) == 1 and errs[0].startswith("loop.pacing:") and "serial or Modbus" in errs[0]
    data = _with("loop.pacing", "device")
    data["backend"] = {"type": "serial", "url": "/dev/ttyUSB0"}
    assert validate_experiment(data, Path(".")).loop.pacing == "device"
    assert any(e.startswith("loop.pacing:") for e in _errors(_with("loop.pacing", "devce")))
