"""plant.model, the sensing section, the scenario set and hil_sim's benches: one model table everywhere."""

import math
from pathlib import Path

import pytest

from hil_sim.config import load_bench_config, validate_bench
from mrctl.config import ConfigError, load_experiment, load_yaml, validate_experiment
from mrctl.experiment import PLANTS, build, make_plant
from mrctl.config.plants import PLANT_MODELS
from mrctl.model.boucwen import BoucWenPlant
from mrctl.model.plant import DamperPlant
from mrctl.offline.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
EXP = ROOT / "config" / "experiments"
BW = str(ROOT / "config" / "plants" / "rd1097_bouc_wen.yaml")


def _errors(data, base=EXP):
    with pytest.raises(ConfigError) as e:
        validate_experiment(data, base)
    return e.value.errors


def _fig5(**changes):
    data = load_yaml(EXP / "fig5.yaml")
    data.update(changes)
    return data


def test_the_plant_name_table_is_the_schema_table():
    assert tuple(PLANTS) == PLANT_MODELS


def test_bouc_wen_plant_is_built_for_simulate_and_the_sim_link():
    exp = build(validate_experiment(_fig5(plant={"model": {"type": "bouc-wen", "parameters": BW}}), EXP))
    assert isinstance(exp.make_plant(), BoucWenPlant)
    bench = exp.make_bench()
    assert isinstance(bench.plant, BoucWenPlant) and bench.plant.tau_s == pytest.approx(1 / 190.0)
    res = simulate(exp, 1.5)
    assert math.isfinite(res.summary["force_nrmse"]) and res.columns["z"][-1] != 0.0
    # the default is the LuGre damper, with the law's parameters
    assert isinstance(make_plant(None, exp.params, 1e-3), DamperPlant)


@pytest.mark.parametrize("plant, expect", [
    ({"model": {"type": "bouc-wen"}}, "plant.model.parameters: missing required key"),
    ({"model": {"type": "bouc-wen", "parameters": "nope.yaml"}}, "plant.model.parameters: no such file"),
    ({"model": {"type": "spencer"}}, "plant.model.type: 'spencer' not allowed (allowed: lugre, bouc-wen)"),
    ({"model": {"type": "bouc-wen", "parameters": BW, "substeps": 0}}, "plant.model.substeps: 0 out of range"),
    ({"model": {"type": "bouc-wen", "parameters": BW}, "parameters": "table1"}, "plant.parameters: a LuGre"),
    ({"sensors": {"velocity": False}}, "plant.sensors.velocity: false leaves the controller without a velocity"),
    ({"sensors": {"load_cell": "no"}}, "plant.sensors.load_cell: must be true or false"),
])
def test_plant_errors_name_their_key(plant, expect):
    errors = _errors(_fig5(plant=plant))
    assert any(e.startswith(expect) for e in errors), errors


def test_a_bad_bouc_wen_file_is_a_config_error(tmp_path):
    p = tmp_path / "bw.yaml"
    p.write_text("c0a: 1.0\nbogus: 2\n")
    errors = _errors(_fig5(plant={"model": {"type": "bouc-wen", "parameters": str(p)}}), tmp_path)
    assert any("plant.model.parameters" in e and "unknown parameter" in e for e in errors), errors
    p.write_text(Path(BW).read_text().replace("beta: -", "beta: 9"))
    errors = _errors(_fig5(plant={"model": {"type": "bouc-wen", "parameters": str(p)}}), tmp_path)
    assert any("gamma must be >= |beta|" in e for e in errors), errors


@pytest.mark.parametrize("sensing, expect", [
    ({"velocity": "kalman"}, "sensing.velocity: 'kalman' not allowed (allowed: measured, observer)"),
    ({"velocity": "observer", "x_noise_m": 0}, "sensing.x_noise_m: 0 out of range"),
    ({"velocity": "observer", "jerk_psd": -1}, "sensing.jerk_psd: -1 out of range"),
    ({"velocity": "observer", "bogus": 1}, "sensing.bogus: unknown key"),
])
def test_sensing_errors_name_their_key(sensing, expect):
    errors = _errors(_fig5(sensing=sensing))
    assert any(e.startswith(expect) for e in errors), errors


def test_every_robust_scenario_and_fig5_robust_validate():
    files = sorted((EXP / "robust").glob("*.yaml"))
    assert len(files) == 33
    for p in files + [EXP / "fig5_robust.yaml", EXP / "hil_closed_serial.yaml", EXP / "hil_closed_modbus_tcp.yaml"]:
        cfg = load_experiment(p)
        assert cfg.inverse.law == "closed", p


def test_scenario_files_are_what_the_generator_writes():
    import sys

    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import robust_scenarios as rs
    finally:
        sys.path.pop(0)
    for name in rs.SCENARIOS:
        for c in rs.C_VALUES:
            p = EXP / "robust" / f"{name}_c{c:g}.yaml"
            assert load_yaml(p) == load_yaml(_write(rs, name, c, p.parent)), p


def _write(rs, name, c, where):
    import tempfile

    text = "\n".join(f"{k}: {rs._flow(v)}" for k, v in rs.config_dict(name, c).items())
    d = Path(tempfile.mkdtemp())
    (d / "x.yaml").write_text(text + "\n")
    return d / "x.yaml"


@pytest.mark.parametrize("bench", ["hil_mismatch_bench.yaml", "hil_bouc_wen_bench.yaml"])
def test_hil_sim_builds_its_bench_through_the_experiment(bench):
    cfg = load_bench_config(ROOT / "config" / bench)
    b = cfg.make_bench()
    want = BoucWenPlant if "bouc" in bench else DamperPlant
    assert isinstance(b.plant, want)
    if want is DamperPlant:
        assert cfg.params.F0 == pytest.approx(3.48)  # the mismatched set
    for k in range(50):
        b.begin_tick(k)
        b.command(0.3)
    x, v, F = b.sample()
    assert math.isfinite(F) and b.I_applied > 0.0


def test_hil_sim_bench_schema_rejects_what_the_experiment_rejects(tmp_path):
    data = load_yaml(ROOT / "config" / "hil_bouc_wen_bench.yaml")
    data["plant"]["model"] = {"type": "bouc-wen"}
    with pytest.raises(ConfigError, match="plant.model.parameters: missing required key"):
        validate_bench(data, ROOT / "config")
    data = load_yaml(ROOT / "config" / "hil_mismatch_bench.yaml")
    data["plant"]["sensors"]["velocity"] = False
    cfg = validate_bench(data, ROOT / "config")
    b = cfg.make_bench()
    b.begin_tick(0)
    assert math.isnan(b.sample()[1])  # a displacement-only DAQ


def test_the_robust_sweeps_are_the_scenario_set_and_the_ablation():
    import sys

    from mrctl.sweep.spec import load_sweep

    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import robust_scenarios as rs
    finally:
        sys.path.pop(0)
    s = load_sweep(ROOT / "config" / "sweeps" / "robust.yaml")
    assert list(s.bases) == list(rs.SCENARIOS)
    assert s.grid == {"demand.c_des": [250, 500, 750], "inverse.law": list(rs.LAWS)}
    assert {"force_nrmse", "max_current_step_A", "reach_floor", "noise_floor"} <= set(s.metrics)
    a = load_sweep(ROOT / "config" / "sweeps" / "robust_ablation.yaml")
    assert list(a.bases) == [f"{n} {c:g}" for n, c in rs.ABLATION_CASES]
    assert list(a.grid["variant"]) == [label for label, _ in rs.ABLATIONS]
    for label, kw in rs.ABLATIONS:
        assert {k.removeprefix("inverse."): v for k, v in (a.grid["variant"][label] or {}).items()} == kw, label
