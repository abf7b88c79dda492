"""Identification from mrctl's own run CSVs: synthetic Table I data in, Table I back out.

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
    identify_runs,
    lugre_force,
    theta_from_params,
    write_result,
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


def identify_csvs(tmp_path: Path, runs, names=None, **kwargs):
    """Write ``runs`` as run CSVs (no sidecar: the load cell in step with x and v) and identify them."""
    paths = [write_run_csv(tmp_path / f"{n}.csv", r) for n, r in zip(names or [f"run{k}" for k in range(len(runs))],
                                                                     runs)]
    return identify_runs(paths, **kwargs)


@pytest.fixture(scope="module")
def result12(tmp_path_factory):
    return identify_csvs(tmp_path_factory.mktemp("r12"), [staircase(CURRENTS)])


def _levels(res):
    return res.details["levels"]


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


# -- a run CSV is a dataset mrctl describes itself ----------------------------------
def test_the_description_of_a_run(tmp_path):
    from mrctl.offline.identify import describe_runs

    run = staircase([0.0, 0.25, 0.5], step_s=3.0)
    run["F_meas"][500:503] = np.nan  # ticks without a sample: left out, not refused
    path = write_run_csv(tmp_path / "r.csv", run)
    (tmp_path / "r.json").write_text('{"format": "mrctl-run/2", "load_cell_delay_ticks": 1}')
    doc = describe_runs([path])
    assert doc["protocol"] == "constant_input" and doc["input"] == "current"
    assert doc["columns"]["input"] == "I" and doc["columns"]["velocity"] == "v_meas"
    assert doc["columns"]["displacement"] == "x_meas" if "x_meas" in run else doc["columns"]["displacement"] == "x"
    assert doc["columns"]["force"] == {"name": "F_meas", "delay_samples": 1}  # the sidecar's load-cell delay
    (t0, t1), = doc["files"][0]["exclude"]  # rows 500-502 hold the force of samples 499-501
    assert run["t"][498] < t0 < run["t"][499] and run["t"][501] < t1 < run["t"][502]
    res = identify_runs([path])
    assert [round(lv["level"], 6) for lv in _levels(res)] == [0.0, 0.25, 0.5]
    assert res.settings["dataset"]["files"][0]["exclude"] == [[t0, t1]]


# -- accuracy on Table I data -------------------------------------------------------
def test_fit_reproduces_measured_force_at_every_current(result12):
    levels = _levels(result12)
    assert [round(lv["level"], 6) for lv in levels] == CURRENTS
    for lv in levels:
        assert lv["nrmse_fit"] < 0.02, lv
        # noise-limited: within a few percent of the load cell's own noise
        assert lv["nrmse_fit"] < 1.1 * lv["nrmse_noise_floor"] + 1e-3, lv
        assert all(s["period_s"] == pytest.approx(0.5, rel=2e-3) for s in lv["segments"])
    # on cycles the fit never saw, through the written laws
    assert len(result12.holdout) == 12
    assert all(s.nrmse_laws < 0.02 for s in result12.holdout), result12.holdout


def test_laws_recover_table_I(result12):
    p = result12.params
    for I in np.linspace(0.05, 0.55, 51):
        assert p.Fc(I) == pytest.approx(TABLE_I.Fc(I), rel=0.05)
    assert p.F0 == pytest.approx(TABLE_I.F0, rel=0.05)
    # the well-determined linear laws, within a few percent over the range
    for name in ("sigma2", "Fs", "vs"):
        for I in (0.05, 0.3, 0.55):
            assert getattr(p, name)(I) == pytest.approx(getattr(TABLE_I, name)(I), rel=0.05), name
    assert result12.details["laws"]["Fc"]["rel_rms"] < 0.02


def test_identifiability_flags_presliding_parameters(result12):
    summary = result12.details["identifiability"]["summary"]
    for k in ("Fc", "Fs", "vs", "sigma2"):
        assert summary[k] == "well", summary
    assert summary["sigma1"] in ("poor", "mixed")
    for lv in _levels(result12):
        sens = lv["sensitivity_1pct"]
        # σ0, σ1 are far less sensitive than Fc: a 1 % force change hides a much bigger change
        assert sens["sigma0"] > 3 * sens["Fc"] and sens["sigma1"] > 3 * sens["Fc"]
        # the standard errors are honest for white noise: truth within 4.5 SE
        truth = theta_from_params(TABLE_I, lv["level"])
        for j, k in enumerate(THETA_NAMES):
            assert abs(lv["theta"][k] - truth[j]) < 4.5 * lv["std_error"][k] + 1e-12, (lv["level"], k)
        C = np.array(lv["correlation"])
        assert C.shape == (6, 6) and np.allclose(np.diag(C), 1.0, atol=1e-6)


def test_starting_values_come_from_the_data(result12):
    for lv in _levels(result12):
        truth = theta_from_params(TABLE_I, lv["level"])
        # Fc and σ2 from the high-|v| branch are already close
        assert lv["start"]["Fc"] == pytest.approx(truth[3], rel=0.1)
        assert lv["start"]["sigma2"] == pytest.approx(truth[2], rel=0.25)


# -- output --------------------------------------------------------------------
def test_written_yaml_loads_as_parameters(result12, tmp_path):
    import json

    out = tmp_path / "params" / "identified.yaml"
    write_result(result12, out)
    p = load_params_file(out)
    assert isinstance(p, LuGreParams)
    assert p == result12.params
    data = load_yaml(out)
    assert [k for k in LuGreParams.names() if k in data] == list(LuGreParams.names())
    assert data["input"] == "current" and data["fit"]["summary"] == "identified.json"
    summary = json.loads(out.with_suffix(".json").read_text())
    assert len(summary["details"]["levels"]) == 12
    assert set(summary["details"]["levels"][0]["theta"]) == set(THETA_NAMES)
    assert summary["details"]["laws"]["Fc"]["coefficients"]["Ac"] == pytest.approx(p.Ac, rel=1e-5)
    assert set(summary["details"]["identifiability"]["summary"]) == set(THETA_NAMES)
    assert summary["settings"]["method"] == "trf" and summary["settings"]["dataset"]["protocol"] == "constant_input"


# -- bad input -------------------------------------------------------------------
def test_no_current_column(tmp_path):
    run = {k: v for k, v in staircase([0.0, 0.3], step_s=2.0).items() if k not in ("I", "I_applied")}
    with pytest.raises(IdentificationError, match="no current column 'I'"):
        identify_csvs(tmp_path, [run])


def test_steps_too_short(tmp_path):
    with pytest.raises(IdentificationError, match=r"(?s)no steady cycles to fit.*step_s.*at 0\.2 \(t = 0\.6"):
        identify_csvs(tmp_path, [staircase([0.0, 0.2, 0.4, 0.1], step_s=0.6)])


def test_a_damper_that_did_not_move(tmp_path):
    run = staircase([0.0, 0.3], step_s=2.0)
    run["v_meas"] = np.zeros_like(run["v"])
    with pytest.raises(IdentificationError, match=r"(?s)no steady cycles.*0 whole cycle"):
        identify_csvs(tmp_path, [run])


def test_closed_loop_run_is_refused(tmp_path):
    run = staircase(CURRENTS[:4])
    run["I"] = 0.3 * np.abs(np.sin(2 * np.pi * run["t"]))  # a current that changes every tick
    with pytest.raises(IdentificationError, match="not a closed-loop run"):
        identify_csvs(tmp_path, [run])


def test_time_not_increasing(tmp_path):
    run = staircase([0.0, 0.3], step_s=2.0)
    run["t"][100] = run["t"][99]
    with pytest.raises(IdentificationError, match="strictly increasing at sample 100"):
        identify_csvs(tmp_path, [run])


def test_skipped_ticks_are_filled_and_said(tmp_path):
    run = staircase([0.0, 0.25, 0.5], step_s=2.0)
    keep = np.ones(run["t"].size, bool)
    keep[[700, 701, 3300]] = False  # three ticks the loop skipped
    res = identify_csvs(tmp_path, [{k: v[keep] for k, v in run.items()}])
    assert any("3 missing sample(s) in 2 gap(s) filled" in w for w in res.warnings), res.warnings
    assert all(s.nrmse < 0.02 for s in res.holdout)


def test_unknown_method(tmp_path):
    with pytest.raises(IdentificationError, match="unknown method"):
        identify_csvs(tmp_path, [staircase([0.0, 0.3], step_s=2.0)], method="simplex")


# -- several runs, decimation -------------------------------------------------------
def test_same_current_in_two_runs_is_fitted_jointly(tmp_path):
    a = staircase([0.0, 0.25, 0.5], seed=5)
    b = staircase([0.25], step_s=2.0, seed=6)
    res = identify_csvs(tmp_path, [a, b], names=["a", "b"])
    lv25 = _levels(res)[1]
    assert lv25["level"] == pytest.approx(0.25)
    assert sorted(s["record"] for s in lv25["segments"]) == ["a", "b"]
    assert {s.record for s in res.holdout if s.level == pytest.approx(0.25)} == {"a", "b"}


def test_decimation_of_fast_records(tmp_path):
    res = identify_csvs(tmp_path, [staircase([0.0, 0.25, 0.5], dt=5e-4, step_s=2.0)], names=["fast"])
    assert "fast: decimated by 2 to 1000 Hz (anti-aliased)" in res.warnings  # to the loop's rate
    assert res.settings["records"]["fast"]["fit_rate_hz"] == pytest.approx(1000.0)
    assert all(lv["nrmse_fit"] < 0.02 for lv in _levels(res))


# -- end to end: the experiment file, the lead's schedule law, the CLI entry ------------
def test_identify_yaml_simulated_and_identified(tmp_path, capsys):
    from mrctl.cli import main
    from mrctl.config import validate_experiment
    from mrctl.experiment import build
    from mrctl.offline.simulate import simulate

    csv_path = tmp_path / "identify.csv"
    assert main(["simulate", str(ROOT / "config" / "experiments" / "identify.yaml"), "--out", str(csv_path),
                 "-q"]) == 0
    out = tmp_path / "params.yaml"
    capsys.readouterr()
    assert cli_identify([str(csv_path)], str(out)) == 0
    captured = capsys.readouterr()
    assert captured.err.count("identify (levels):") >= 5  # progress lines, not a redrawn bar, off a terminal
    text = captured.out
    assert "Fc (N)" in text and "held-out force NRMSE" in text and f"wrote {out}" in text
    p = load_params_file(out)
    for I in np.linspace(0.05, 0.55, 11):
        assert p.Fc(I) == pytest.approx(TABLE_I.Fc(I), rel=0.05)
    fit = load_yaml(out)["fit"]
    assert len(fit["holdout"]) == 12 and all(h["nrmse"] < 0.02 for h in fit["holdout"])
    import json

    summary = json.loads(out.with_suffix(".json").read_text())
    for lv in summary["details"]["levels"]:  # F_noise 0.1 N: the fit is at the noise floor, under 2 %
        assert lv["nrmse_fit"] < 1.1 * lv["nrmse_noise_floor"] + 1e-3 and lv["nrmse_fit"] < 0.02
    # the sidecar's one-tick load-cell delay is in the description mrctl wrote
    assert summary["settings"]["dataset"]["columns"]["force"] == {"name": "F", "delay_samples": 1}

    # the chain closes: fig5 with the law on the fitted set, the damper still Table I
    fig5 = load_yaml(ROOT / "config" / "experiments" / "fig5.yaml")
    base = simulate(build(validate_experiment(fig5, ROOT / "config" / "experiments")), 4.0)
    fig5["parameters"] = {"file": out.name}
    fig5["plant"] = {"parameters": "table1"}
    exp2 = build(validate_experiment(fig5, tmp_path))  # the fitted set beside the experiment
    assert exp2.params != exp2.plant_params  # really a different set in the law
    fitted = simulate(exp2, 4.0)
    assert fitted.summary["force_nrmse"] <= 1.5 * base.summary["force_nrmse"]


def test_describe_writes_a_description_that_fits_the_same(tmp_path, capsys):
    from mrctl.cli import main

    run = staircase([0.0, 0.25, 0.5], step_s=2.0)
    path = write_run_csv(tmp_path / "run.csv", run)
    desc = tmp_path / "run-dataset.yaml"
    assert main(["identify", str(path), "--describe", str(desc)]) == 0
    assert not (tmp_path / "run.params.yaml").exists()  # nothing fitted
    doc = load_yaml(desc)
    assert doc["files"][0]["path"] == "run.csv" and doc["protocol"] == "constant_input"
    assert main(["identify", str(path), "--out", str(tmp_path / "a.yaml"), "-q", "--no-progress"]) == 0
    assert main(["identify", "--dataset", str(desc), "--out", str(tmp_path / "b.yaml"), "-q", "--no-progress"]) == 0
    assert load_params_file(tmp_path / "a.yaml") == load_params_file(tmp_path / "b.yaml")


def test_cli_bad_inputs(tmp_path, capsys):
    out = str(tmp_path / "p.yaml")
    assert cli_identify([str(tmp_path / "missing.csv")], out) == 2
    err = capsys.readouterr().err
    assert "no such file" in err and "Traceback" not in err
    bad = tmp_path / "bad.csv"
    bad.write_text("t,v,F\n0,0,0\n0.001,0.1,1\n")
    assert cli_identify([str(bad)], out) == 2
    assert "current column 'I'" in capsys.readouterr().err
    garbled = tmp_path / "garbled.csv"
    garbled.write_text("t,I,v,F\n0,0,0,0\n0.001,0,x,1\n0.002,0,0,1\n0.003,0,0,1\n")
    assert cli_identify([str(garbled)], out) == 2
    assert "line 3" in capsys.readouterr().err
    assert cli_identify([], out) == 2
    assert not Path(out).exists()


def test_cli_reads_csv_with_extra_columns(tmp_path, capsys):
    run = staircase([0.0, 0.25, 0.5], step_s=2.0)
    path = write_run_csv(tmp_path / "run.csv", run, extra_text_column=True)
    out = tmp_path / "p.yaml"
    assert cli_identify([str(path)], str(out)) == 0
    assert load_params_file(out).Fc(0.5) == pytest.approx(TABLE_I.Fc(0.5), rel=0.05)


# -- what a real run log holds: bad input values, noise, gaps, sidecars ---------------
def _level_values(res):
    return [round(lv["level"], 3) for lv in _levels(res)]


@pytest.mark.parametrize("bad", [math.inf, math.nan])
def test_a_non_finite_current_sample_is_left_out_not_spread(tmp_path, bad):
    run = staircase([0.0, 0.25, 0.5], step_s=3.0)
    run["I"][4000] = bad  # one corrupt sample inside the 0.25 A step
    res = identify_csvs(tmp_path, [run])
    assert _level_values(res) == [0.0, 0.25, 0.5]
    assert all(s.nrmse < 0.02 for s in res.holdout)


@pytest.mark.parametrize("noise_A", [0.002, 0.004])
def test_a_measured_noisy_lagging_current_gives_the_levels(tmp_path, noise_A):
    from mrctl.config.dataset import validate_dataset
    from mrctl.offline.identify import identify_dataset

    run = staircase([0.0, 0.1, 0.2, 0.3, 0.4, 0.5], step_s=3.0, driver_tau_s=0.01)
    run["I_meas"] = run["I_applied"] + np.random.default_rng(3).normal(0.0, noise_A, run["t"].size)
    path = write_run_csv(tmp_path / "meas.csv", run)
    ds = validate_dataset({"version": 1, "protocol": "constant_input", "files": [str(path)],
                           "columns": {"time": "t", "velocity": "v_meas", "displacement": "x", "force": "F_meas",
                                       "input": "I_meas"}}, tmp_path)
    res = identify_dataset(ds)
    assert [round(x, 2) for x in _level_values(res)] == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    # a constant measured current with noise is one level, not a closed-loop run
    const = staircase([0.3], step_s=6.0)
    const["I_meas"] = 0.3 + np.random.default_rng(4).normal(0.0, noise_A, const["t"].size)
    write_run_csv(tmp_path / "meas.csv", const)
    assert [round(x, 2) for x in _level_values(identify_dataset(ds))] == [0.3]


def test_gaps_are_filled_before_the_load_cell_is_moved_back(tmp_path):
    """Skipped ticks at a reversal: the delayed force is paired with its own tick on the tick grid."""
    from mrctl.config.dataset import validate_dataset
    from mrctl.offline.identify.records import read_records

    n = 400
    k = np.arange(n)
    f = (k / 100.0) ** 2  # the force of tick k; the load cell reports it one tick later
    rows = {"t": k * 1e-3, "v": np.sin(k / 20.0), "F": np.concatenate(([0.0], f[:-1])), "I": np.zeros(n)}
    keep = np.ones(n, bool)
    keep[100:105] = False  # five skipped ticks
    write_run_csv(tmp_path / "g.csv", {c: a[keep] for c, a in rows.items()})
    ds = validate_dataset({"version": 1, "protocol": "constant_input", "files": ["g.csv"],
                           "columns": {"time": "t", "velocity": "v", "force": {"name": "F", "delay_samples": 1},
                                       "input": "I"}, "format": {"max_gap_samples": 10},
                           "model": {"stiffness": False}}, tmp_path)
    rec, = read_records(ds)
    assert rec.t.size == n - 1
    for j in (97, 98, 104, 105, 300):  # forces measured either side of the gap (ticks 99-103 read in it)
        assert rec.F[j] == pytest.approx(f[j], abs=1e-9), j
    assert rec.notes == ["5 missing sample(s) in 1 gap(s) filled by linear interpolation (format.max_gap_samples)"]


def test_a_nan_beside_a_gap_is_excluded_and_the_gap_filled(tmp_path):
    run = staircase([0.0, 0.25, 0.5], step_s=3.0)
    run["F_meas"][1000] = np.nan
    keep = np.ones(run["t"].size, bool)
    keep[1001:1003] = False
    res = identify_csvs(tmp_path, [{c: a[keep] for c, a in run.items()}])
    assert _level_values(res) == [0.0, 0.25, 0.5]
    assert any("2 missing sample(s) in 1 gap(s)" in w for w in res.warnings)


def test_sidecars_that_cannot_be_used(tmp_path):
    run = staircase([0.0, 0.25], step_s=3.0)
    path = write_run_csv(tmp_path / "r.csv", run)
    (tmp_path / "r.json").write_text('{"load_cell_delay_ticks": 200000}')
    with pytest.raises(IdentificationError, match="load_cell_delay_ticks 200000 is longer than the run"):
        identify_runs([path])
    (tmp_path / "r.json").write_text('{"load_cell_delay_ticks": ')  # torn
    res = identify_runs([path])
    assert any("r.csv: its sidecar cannot be read" in w and "no delay" in w for w in res.warnings), res.warnings
    (tmp_path / "r.json").write_text('{"load_cell_delay_ticks": "one"}')
    assert any("is not a tick count" in w for w in identify_runs([path]).warnings)


def test_an_empty_force_column_falls_back_or_is_named(tmp_path):
    from mrctl.offline.identify import describe_runs

    run = staircase([0.0, 0.25], step_s=3.0)
    run["F_meas"] = np.full(run["t"].size, np.nan)  # no load cell reading in this column: F has it
    path = write_run_csv(tmp_path / "r.csv", run)
    assert describe_runs([path])["columns"]["force"] == "F"
    del run["F"]
    path = write_run_csv(tmp_path / "r.csv", run)
    with pytest.raises(IdentificationError, match="column F_meas has no value in any row"):
        describe_runs([path])


def test_the_same_run_twice_is_refused(tmp_path):
    path = write_run_csv(tmp_path / "r.csv", staircase([0.0, 0.25], step_s=3.0))
    with pytest.raises(IdentificationError, match="given twice"):
        identify_runs([path, tmp_path / "." / "r.csv"])


def test_describe_refuses_what_is_for_the_fit(tmp_path, capsys):
    from mrctl.cli import main

    path = write_run_csv(tmp_path / "r.csv", staircase([0.0, 0.25], step_s=3.0))
    for extra in (["--out", str(tmp_path / "p.yaml")], ["--holdout", "none"], ["--no-offset"], ["--method", "lm"]):
        assert main(["identify", str(path), "--describe", str(tmp_path / "d.yaml"), *extra]) == 2
        assert "--describe writes the description and fits nothing" in capsys.readouterr().err
    assert main(["identify", str(path), "--describe", str(tmp_path / "no" / "d.yaml")]) == 2
    assert "--mkdir" in capsys.readouterr().err
    assert main(["identify", str(path), str(tmp_path / "d.yaml")]) == 2
    assert "a description among run CSVs" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.yaml"))
