"""Identification (mrctl.offline.identify): synthetic Table I data in, Table I back out.

The data generator lives here, not in the package: a DamperPlant (the
forward LuGre model with the daemon's tick protocol) driven by a sine stroke
through a staircase of constant currents, with seeded sensor noise — what
``mrctl simulate config/experiments/identify.yaml`` records.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mrctl.config import load_params_file, load_yaml
from mrctl.offline.identify import (
    THETA_NAMES,
    IdentificationError,
    estimate_period,
    identify,
    lugre_force,
    theta_from_params,
    write_params_yaml,
)
from mrctl.model.lugre import LuGreModel
from mrctl.model.params import TABLE_I, LuGreParams
from mrctl.model.plant import DamperPlant, Sensors

ROOT = Path(__file__).resolve().parents[1]
CURRENTS = [round(0.05 * k, 2) for k in range(12)]  # the paper's twelve, 0–0.55 A


def staircase(currents, step_s=2.0, amplitude_m=0.008, freq_hz=2.0, dt=1e-3, F_noise_N=0.05,
              v_noise_mps=1e-4, seed=1, params=TABLE_I, driver_tau_s=0.0):
    """A 2 Hz / 8 mm sine through constant-current steps (one record, like the schedule law)."""
    per_step = int(round(step_s / dt))
    n = per_step * len(currents)
    t = np.arange(n) * dt
    w = 2.0 * math.pi * freq_hz
    x, v = amplitude_m * np.sin(w * t), amplitude_m * w * np.cos(w * t)
    I = np.repeat(np.asarray(currents, float), per_step)
    plant = DamperPlant(params, dt, driver_tau_s)
    sensors = Sensors(seed, 0.0, v_noise_mps, F_noise_N)
    F, Ia = np.empty(n), np.empty(n)
    for k, (vk, Ik) in enumerate(zip(v.tolist(), I.tolist())):
        F[k] = plant.tick(vk, Ik)
        Ia[k] = plant.I_applied
    return {"t": t, "x": x, "v": v, "F": F, "I": I, "I_applied": Ia,
            "v_meas": np.array([sensors.v(q) for q in v.tolist()]),
            "F_meas": np.array([sensors.F(q) for q in F.tolist()])}


def cli_identify(paths, out, report_png=None) -> int:
    """``mrctl identify PATHS --out OUT [--report PNG]``: mrctl.cli's parser and
    cmd_identify, an error reported as mrctl.cli.main reports every MrctlError
    (``mrctl: <message>`` on stderr, its exit_code). Output on stdout/stderr."""
    from mrctl.cli import main

    argv = ["identify", *map(str, paths), "--out", str(out)] + (["--report", str(report_png)] if report_png else [])
    try:
        return main(argv)
    except SystemExit as exc:  # a usage error, e.g. no run CSV: argparse exits 2
        return exc.code


def write_run_csv(path: Path, run: dict, extra_text_column: bool = False) -> Path:
    cols = list(run)
    with path.open("w") as fh:
        fh.write("# synthetic identification run\n")
        fh.write(",".join(cols + (["fault"] if extra_text_column else [])) + "\n")
        for k in range(run["t"].size):
            row = [f"{run[c][k]:.10g}" for c in cols]
            fh.write(",".join(row + (["ok"] if extra_text_column else [])) + "\n")
    return path


@pytest.fixture(scope="module")
def run12():
    return staircase(CURRENTS)


@pytest.fixture(scope="module")
def result12(run12):
    calls = []
    res = identify([run12], progress=lambda *a: calls.append(a))
    res.calls = calls
    return res


# -- the model the fit uses ------------------------------------------------------
def test_vectorised_model_equals_lugre_model_tick_by_tick():
    dt = 1e-3
    t = np.arange(0.0, 1.0, dt)
    v = 0.1 * np.cos(4 * np.pi * t) + 0.002 * np.sin(50 * t)
    for I in (0.0, 0.27, 0.55):
        th = theta_from_params(TABLE_I, I)
        m = LuGreModel(TABLE_I)
        m.z, m.v_prev = 1e-5, v[0]
        F = [m.force(v[0], I)]
        for vk in v[1:].tolist():
            m.advance(vk, I, dt)
            F.append(m.force(vk, I))
        np.testing.assert_allclose(lugre_force(th, v, dt, z0=1e-5), F, rtol=0, atol=1e-9)


def test_period_estimate(run12):
    assert estimate_period(run12["t"], run12["v_meas"]) == pytest.approx(0.5, rel=1e-3)


# -- accuracy on Table I data -------------------------------------------------------
def test_fit_reproduces_measured_force_at_every_current(result12):
    assert [round(f.current_cmd, 6) for f in result12.fits] == CURRENTS
    for f in result12.fits:
        assert f.nrmse < 0.02, (f.current, f.nrmse)
        # noise-limited: within a few percent of the load cell's own noise
        assert f.nrmse < 1.1 * f.noise_nrmse + 1e-3, (f.current, f.nrmse, f.noise_nrmse)
        assert f.nrmse_laws < 0.02
        assert f.periods == pytest.approx(3.0, rel=1e-3)  # 4 periods per step, 1 dropped


def test_laws_recover_table_I(result12):
    p = result12.params
    for I in np.linspace(0.05, 0.55, 51):
        assert p.Fc(I) == pytest.approx(TABLE_I.Fc(I), rel=0.05)
    assert p.F0 == pytest.approx(TABLE_I.F0, rel=0.05)
    # the well-determined linear laws, within a few percent over the range
    for name in ("sigma2", "Fs", "vs"):
        for I in (0.05, 0.3, 0.55):
            assert getattr(p, name)(I) == pytest.approx(getattr(TABLE_I, name)(I), rel=0.05), name
    assert result12.laws["Fc"].rel_rms < 0.02


def test_identifiability_flags_presliding_parameters(result12):
    summary = result12.summary_determined()
    for k in ("Fc", "Fs", "vs", "sigma2"):
        assert summary[k] == "well", summary
    assert summary["sigma1"] in ("poor", "mixed")
    for f in result12.fits:
        # σ0, σ1 are far less sensitive than Fc: a 1 % force change hides a much bigger change
        assert f.sensitivity["sigma0"] > 3 * f.sensitivity["Fc"]
        assert f.sensitivity["sigma1"] > 3 * f.sensitivity["Fc"]
        # the standard errors are honest for white noise: truth within 4.5 SE
        truth = theta_from_params(TABLE_I, f.current)
        for j, k in enumerate(THETA_NAMES):
            assert abs(f.theta[k] - truth[j]) < 4.5 * f.se[k] + 1e-12, (f.current, k)
        C = np.array(f.corr)
        assert C.shape == (6, 6) and np.allclose(np.diag(C), 1.0, atol=1e-6)


def test_starting_values_come_from_the_data(result12):
    for f in result12.fits:
        assert set(f.start_notes) == set(THETA_NAMES)
        truth = theta_from_params(TABLE_I, f.current)
        # Fc and σ2 from the high-|v| branch are already close
        assert f.theta0["Fc"] == pytest.approx(truth[3], rel=0.1)
        assert f.theta0["sigma2"] == pytest.approx(truth[2], rel=0.25)


def test_progress_called_once_per_current(result12):
    calls = result12.calls
    assert [c[0] for c in calls] == list(range(1, 13))
    assert all(c[1] == 12 for c in calls)
    assert [round(c[2], 6) for c in calls] == CURRENTS
    elapsed = [c[3] for c in calls]
    assert elapsed == sorted(elapsed) and elapsed[-1] < 60.0
    assert all(0.0 < c[4] < 0.02 for c in calls)


# -- output --------------------------------------------------------------------
def test_written_yaml_loads_as_parameters(result12, tmp_path):
    out = tmp_path / "params" / "identified.yaml"
    write_params_yaml(result12, out)
    p = load_params_file(out)
    assert isinstance(p, LuGreParams)
    assert p == result12.params
    data = load_yaml(out)
    names = [k for k in data if k not in ("version", "description", "source", "fit")]
    assert names == list(LuGreParams.names())
    fit = data["fit"]
    assert len(fit["per_current"]) == 12
    assert set(fit["per_current"][0]["theta"]) == set(THETA_NAMES)
    assert fit["laws"]["Fc"]["coefficients"]["Ac"] == pytest.approx(p.Ac, rel=1e-5)
    assert set(fit["identifiability"]["summary"]) == set(THETA_NAMES)
    assert fit["optimiser"] == "trf"


# -- bad input -------------------------------------------------------------------
def test_no_current_column(run12):
    run = {k: v for k, v in run12.items() if k not in ("I", "I_applied")}
    with pytest.raises(IdentificationError, match="current column 'I'"):
        identify([run])


def test_single_current():
    with pytest.raises(IdentificationError, match=r"1 distinct current\(s\) \(0.3 A\).*at least 3"):
        identify([staircase([0.3], step_s=3.0)])


def test_segment_too_short():
    run = staircase([0.0, 0.2, 0.4, 0.1], step_s=0.6)
    with pytest.raises(IdentificationError, match=r"current 0 A is held for only 0.6 s .*needs ≥ 1 s per current.*step_s"):
        identify([run])


def test_non_periodic_or_still_velocity(run12):
    run = dict(run12)
    run["v_meas"] = np.zeros_like(run12["v"])
    with pytest.raises(IdentificationError, match="not moved"):
        identify([run])
    t = run12["t"]
    run["v_meas"] = np.cos(2 * np.pi * (1.0 + 0.2 * t) * t)  # a chirp
    with pytest.raises(IdentificationError, match="periodic"):
        identify([run])


def test_closed_loop_run_is_refused(run12):
    run = dict(run12)
    run["I"] = 0.3 * np.abs(np.sin(2 * np.pi * run12["t"]))  # a current that changes every tick
    with pytest.raises(IdentificationError, match="not a closed-loop run"):
        identify([run])


def test_time_not_increasing(run12):
    run = dict(run12)
    run["t"] = run12["t"].copy()
    run["t"][100] = run["t"][99]
    with pytest.raises(IdentificationError, match="strictly increasing at sample 100"):
        identify([run])


def test_unknown_method(run12):
    with pytest.raises(IdentificationError, match="unknown method"):
        identify([run12], method="simplex")


# -- several runs, fragments, decimation -------------------------------------------
def test_runs_split_and_trailing_fragment():
    a = staircase([0.0, 0.1, 0.2], seed=3)
    b = staircase([0.3, 0.4, 0.5], seed=4)
    # a trailing sample at 0 A (what a schedule that ends on 0 A logs) is ignored with a warning
    for k in b:
        b[k] = np.append(b[k], b[k][-1])
    b["I"][-1] = 0.0
    b["t"][-1] = b["t"][-2] + 1e-3
    res = identify([a, b], sources=["a.csv", "b.csv"])
    assert [round(f.current_cmd, 6) for f in res.fits] == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    assert any("fragment" in w for w in res.warnings)
    assert all(f.nrmse < 0.02 for f in res.fits)
    assert res.sources == ["a.csv", "b.csv"]


def test_same_current_in_two_runs_is_fitted_jointly():
    a = staircase([0.0, 0.25, 0.5], seed=5)
    b = staircase([0.25], step_s=2.0, seed=6)
    res = identify([a, b], fit_periods=1)
    f25 = res.fits[1]
    assert len(f25.segments) == 2 and f25.periods == pytest.approx(2.0, rel=1e-3)


def test_decimation_of_fast_records():
    run = staircase([0.0, 0.25, 0.5], dt=5e-4, step_s=1.5)
    res = identify([run], max_rate_hz=1000.0)
    assert any("decimated by 2" in w for w in res.warnings)
    assert res.dt_s == pytest.approx(1e-3)
    assert all(f.nrmse < 0.02 for f in res.fits)


# -- end to end: the experiment file, the lead's schedule law, the CLI entry ------------
def test_identify_yaml_simulated_and_identified(tmp_path, capsys):
    from mrctl.config import load_experiment, validate_experiment
    from mrctl.experiment import build
    from mrctl.offline.simulate import run_duration, simulate, write_csv

    exp = build(load_experiment(ROOT / "config" / "experiments" / "identify.yaml"))
    assert exp.config.inverse.law == "schedule"
    assert exp.config.inverse.currents_A == pytest.approx(CURRENTS)
    sim = simulate(exp, run_duration(exp))
    csv_path = tmp_path / "identify.csv"
    write_csv(sim, csv_path)
    out = tmp_path / "params.yaml"
    capsys.readouterr()
    assert cli_identify([str(csv_path)], str(out)) == 0
    text = capsys.readouterr().out
    assert text.count("] I = ") == 12  # a progress line per current
    assert "Fc (N)" in text and "NRMSE" in text and f"wrote {out}" in text
    p = load_params_file(out)
    for I in np.linspace(0.05, 0.55, 11):
        assert p.Fc(I) == pytest.approx(TABLE_I.Fc(I), rel=0.05)
    fit = load_yaml(out)["fit"]
    for f in fit["per_current"]:  # F_noise 0.1 N: the fit is at the noise floor, under 2 %
        assert f["nrmse"] < 1.1 * f["nrmse_noise_floor"] + 1e-3
        assert f["nrmse"] < 0.02
    assert not fit["warnings"]

    # the chain closes: fig5 with the law on the fitted set, the damper still Table I
    fig5 = load_yaml(ROOT / "config" / "experiments" / "fig5.yaml")
    base = simulate(build(validate_experiment(fig5, ROOT / "config" / "experiments")), 4.0)
    fig5["parameters"] = {"file": str(out)}
    fig5["plant"] = {"parameters": "table1"}
    exp2 = build(validate_experiment(fig5, ROOT / "config" / "experiments"))
    assert exp2.params != exp2.plant_params  # really a different set in the law
    fitted = simulate(exp2, 4.0)
    assert fitted.summary["force_nrmse"] <= 1.5 * base.summary["force_nrmse"]


def test_cli_bad_inputs(tmp_path, capsys, run12):
    out = str(tmp_path / "p.yaml")
    assert cli_identify([str(tmp_path / "missing.csv")], out) == 2
    err = capsys.readouterr().err
    assert "no such file" in err and "Traceback" not in err
    bad = tmp_path / "bad.csv"
    bad.write_text("t,v,F\n0,0,0\n0.001,0.1,1\n")
    assert cli_identify([str(bad)], out) == 2
    assert "current column 'I'" in capsys.readouterr().err
    garbled = tmp_path / "garbled.csv"
    garbled.write_text("t,I,v,F\n0,0,0,0\n0.001,0,x,1\n")
    assert cli_identify([str(garbled)], out) == 2
    assert "line 3: column v is not a number" in capsys.readouterr().err
    assert cli_identify([], out) == 2
    assert not Path(out).exists()


def test_cli_reads_csv_with_extra_columns(tmp_path, capsys):
    run = staircase([0.0, 0.25, 0.5], step_s=1.5)
    path = write_run_csv(tmp_path / "run.csv", run, extra_text_column=True)
    out = tmp_path / "p.yaml"
    assert cli_identify([str(path)], str(out)) == 0
    assert capsys.readouterr().out.count("] I = ") == 3
    assert load_params_file(out).Fc(0.5) == pytest.approx(TABLE_I.Fc(0.5), rel=0.05)
