"""mrctl sweep: expansion, failed points, resumption, local vs Dask, the schema's errors, the report."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from mrctl.cli import main
from mrctl.config import ConfigError, load_yaml
from mrctl.sweep import runner
from mrctl.sweep.runner import SweepInterrupted, run_sweep
from mrctl.sweep.spec import Point, expand, load_sweep

ROOT = Path(__file__).resolve().parents[1]
EXP = ROOT / "config" / "experiments"


def _base(tmp_path: Path, name: str = "fig5_robust.yaml", duration: float = 0.5) -> Path:
    data = load_yaml(EXP / name)
    data["duration_s"] = duration
    p = tmp_path / "base.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _sweep(tmp_path: Path, body: dict, name: str = "s.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump({"base": "base.yaml", **body}))
    return p


def _table(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_grid_times_random_expansion_applies_values_as_plain_data(tmp_path):
    _base(tmp_path)
    s = load_sweep(_sweep(tmp_path, {
        "grid": {"demand.c_des": [250, 750], "inverse.law": ["smooth", "closed"]},
        "random": {"n": 3, "seed": 7, "plant.parameters.F0": {"factor_uniform": [0.8, 1.2]},
                   "plant.driver_tau_s": {"uniform": [0.0, 0.01]}}}))
    points = list(expand(s))
    assert len(points) == s.size() == 12 and all(isinstance(p, Point) for p in points)
    assert [p.index for p in points] == list(range(12))
    assert len({p.hash for p in points}) == 12
    by_draw: dict[int, set] = {}
    for p in points:
        cfg = p.config
        assert cfg["demand"]["c_des"] == p.values["demand.c_des"]
        assert cfg["inverse"]["law"] == p.values["inverse.law"]
        if p.values["inverse.law"] == "smooth":  # another law: the closed law's keys are gone
            assert cfg["inverse"] == {"law": "smooth"}
        F0 = cfg["plant"]["parameters"]["F0"]
        assert 0.8 * 2.90 <= F0 <= 1.2 * 2.90 and F0 == p.values["plant.parameters.F0"]
        assert cfg["parameters"]["F0"] == 2.90  # the law's set is untouched: plain numbers, no file
        assert 0.0 <= cfg["plant"]["driver_tau_s"] <= 0.01
        by_draw.setdefault(p.seed, set()).add((F0, cfg["plant"]["driver_tau_s"]))
    assert sorted(by_draw) == [0, 1, 2]
    assert all(len(v) == 1 for v in by_draw.values())  # a draw is the same in every grid cell
    assert len({next(iter(v)) for v in by_draw.values()}) == 3
    again = [p.hash for p in expand(load_sweep(tmp_path / "s.yaml"))]
    assert again == [p.hash for p in points]  # seeded: the same points every time


def test_named_axes_and_several_bases(tmp_path):
    _base(tmp_path)
    (tmp_path / "other.yaml").write_text((tmp_path / "base.yaml").read_text())
    (tmp_path / "plants").mkdir()
    (tmp_path / "plants" / "m.yaml").write_text((ROOT / "config/plants/table1_mismatched.yaml").read_text())
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump({"base": {"a": "base.yaml", "b": "other.yaml"},
                                 "grid": {"variant": {"slow": {"inverse.horizon_ticks": 0},
                                                      "lag": {"plant.parameters": "plants/m.yaml",
                                                              "plant.driver_tau_s": 0.005}}}}, sort_keys=False))
    s = load_sweep(p)
    pts = list(expand(s))
    assert s.axes == ["base", "variant"] and len(pts) == 4
    assert [(q.values["base"], q.values["variant"]) for q in pts] == [
        ("a", "slow"), ("a", "lag"), ("b", "slow"), ("b", "lag")]
    assert pts[0].config["inverse"]["horizon_ticks"] == 0
    assert pts[1].config["plant"]["parameters"]["F0"] == pytest.approx(3.48)  # the file (relative to the sweep), read
    assert pts[1].config["plant"]["driver_tau_s"] == 0.005


def test_a_failing_point_is_a_row_and_the_sweep_goes_on(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "tests" / "plugins"))
    _base(tmp_path)
    s = load_sweep(_sweep(tmp_path, {"grid": {"inverse.law": ["smooth", "bad_laws:Raises"],
                                              "safety.I_max": [0.6, 5.0]}}))
    counts = run_sweep(s, tmp_path / "r.csv", workers=1, progress=False)
    rows = _table(tmp_path / "r.csv")
    assert counts == {"ok": 1, "fault": 1, "invalid": 2, "error": 0, "skipped": 0}
    assert [r["status"] for r in rows] == ["ok", "invalid", "fault", "invalid"]
    assert "safety.I_max" in rows[1]["error"] and "out of range" in rows[1]["error"]
    assert "boom from a plugin" in rows[2]["error"]
    assert math.isfinite(float(rows[0]["force_nrmse"])) and float(rows[0]["force_nrmse"]) < 0.1


def test_resumes_after_an_interruption_and_a_half_written_row(tmp_path, monkeypatch):
    _base(tmp_path)
    path = _sweep(tmp_path, {"grid": {"demand.c_des": [200, 300, 400, 500, 600]}})
    real = runner.run_point
    calls = []

    def flaky(task):
        calls.append(task["index"])
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(task)

    monkeypatch.setattr(runner, "run_point", flaky)
    with pytest.raises(SweepInterrupted):
        run_sweep(load_sweep(path), tmp_path / "r.csv", workers=1, progress=False)
    rows = _table(tmp_path / "r.csv")
    assert [r["point"] for r in rows] == ["0", "1"]  # a valid partial table
    with open(tmp_path / "r.csv", "a") as fh:
        fh.write("4,deadbeef,600,,0.0")  # what a kill in the middle of a row leaves
    monkeypatch.setattr(runner, "run_point", real)
    counts = run_sweep(load_sweep(path), tmp_path / "r.csv", workers=1, progress=False)
    assert counts["skipped"] == 2 and counts["ok"] == 3
    rows = _table(tmp_path / "r.csv")
    assert [r["point"] for r in rows] == ["0", "1", "2", "3", "4"]  # once each, in point order
    assert all(r["status"] == "ok" for r in rows)


def test_a_killed_sweep_resumes(tmp_path):
    _base(tmp_path, duration=1.0)
    path = _sweep(tmp_path, {"grid": {"demand.c_des": [100 * i for i in range(1, 31)]}})
    out = tmp_path / "r.csv"
    proc = subprocess.Popen([sys.executable, "-m", "mrctl", "sweep", str(path), "--out", str(out), "--workers", "1",
                             "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        import time

        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not out.exists() or out.read_text().count("\n") < 4):
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait()
    done = len(_table(out))
    assert 3 <= done < 30
    assert main(["sweep", str(path), "--out", str(out), "--no-progress", "--workers", "1"]) == 0
    rows = _table(out)
    assert [int(r["point"]) for r in rows] == list(range(30))


def test_local_processes_and_a_dask_cluster_give_the_same_table(tmp_path):
    import distributed
    _base(tmp_path)
    s = load_sweep(_sweep(tmp_path, {"grid": {"inverse.law": ["paper", "closed"]},
                                     "random": {"n": 3, "plant.parameters.Ac": {"factor_uniform": [0.8, 1.2]},
                                                "plant.sensors.F_noise_N": {"uniform": [0.0, 1.0]}}}))
    run_sweep(s, tmp_path / "local.csv", workers=2, progress=False)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as c, \
            distributed.Client(c) as client:
        run_sweep(s, tmp_path / "dask.csv", scheduler=client, progress=False)
    a, b = _table(tmp_path / "local.csv"), _table(tmp_path / "dask.csv")
    assert len(a) == 6
    for r in a + b:
        r.pop("wall_s")
    assert a == b


def test_batched_points_give_the_same_table_as_one_process(tmp_path):
    """Points go to the workers several at a time (a compiled point is ~8 ms): the rows are the same."""
    assert runner.batch_size(10_000, 2) == runner.MAX_BATCH and runner.batch_size(6, 2) == 1
    assert runner.batch_size(40, 2) == 5
    _base(tmp_path, duration=0.2)
    s = load_sweep(_sweep(tmp_path, {"random": {"n": 40, "plant.parameters.Ac": {"factor_uniform": [0.8, 1.2]}}}))
    run_sweep(s, tmp_path / "one.csv", workers=1, progress=False)
    run_sweep(s, tmp_path / "two.csv", workers=2, progress=False)
    a, b = _table(tmp_path / "one.csv"), _table(tmp_path / "two.csv")
    for r in a + b:
        r.pop("wall_s")
    assert len(a) == 40 and a == b and len({r["force_nrmse"] for r in a}) == 40


@pytest.mark.parametrize("body, expect", [
    ({"grid": {"demnd.c_des": [1, 2]}}, "grid.demnd.c_des: 'demnd' is not an experiment key"),
    ({"grid": {"demand.c_des": []}}, "grid.demand.c_des: must list at least one value"),
    ({"grid": {"demand.c_des": 500}}, "grid.demand.c_des: must be a list of values"),
    ({"random": {"n": 5, "plant.driver_tau_s": {"gauss": [0, 1]}}}, "random.plant.driver_tau_s.gauss: unknown"),
    ({"random": {"n": 5, "plant.driver_tau_s": {"uniform": [1, 0]}}}, "needs lo <= hi"),
    ({"random": {"n": 5, "plant.driver_tau_s": {"log_uniform": [0, 1]}}}, "log-uniform needs lo > 0"),
    ({"random": {"plant.driver_tau_s": {"uniform": [0, 1]}}}, "random.n: missing required key"),
    ({"random": {"n": 0, "plant.driver_tau_s": {"uniform": [0, 1]}}}, "random.n: 0 out of range"),
    ({"metrics": ["force_nrmse", "nrmse"]}, "metrics[1]: 'nrmse' unknown"),
    ({"base": "nope.yaml"}, "base: no such file"),
    ({"colour": 1}, "colour: unknown key"),
])
def test_schema_errors_name_the_key_path(tmp_path, body, expect, capsys):
    _base(tmp_path)
    p = _sweep(tmp_path, body)
    with pytest.raises(ConfigError) as ei:
        load_sweep(p)
    assert any(expect in e for e in ei.value.errors), ei.value.errors
    assert main(["check", str(p)]) == 2
    assert expect in capsys.readouterr().err


def test_check_accepts_the_shipped_sweeps(capsys):
    for p in sorted((ROOT / "config" / "sweeps").glob("*.yaml")):
        assert main(["check", str(p)]) == 0, p
        assert "OK" in capsys.readouterr().out


def test_report_of_a_grid_and_of_a_monte_carlo(tmp_path, capsys):
    _base(tmp_path)
    grid = _sweep(tmp_path, {"grid": {"demand.c_des": [250, 500], "plant.driver_tau_s": [0.0, 0.01]}}, "g.yaml")
    mc = _sweep(tmp_path, {"grid": {"inverse.law": ["smooth", "closed"]},
                           "random": {"n": 4, "plant.parameters.F0": {"factor_uniform": [0.8, 1.2]}}}, "m.yaml")
    assert main(["sweep", str(grid), "--out", str(tmp_path / "g.csv"), "--no-progress"]) == 0
    assert main(["sweep", str(mc), "--out", str(tmp_path / "m.csv"), "--no-progress"]) == 0
    assert main(["report", str(tmp_path / "g.csv"), "--out", str(tmp_path / "g.png")]) == 0
    assert main(["report", str(tmp_path / "m.csv"), "--out", str(tmp_path / "m.png"), "--bound", "0.02"]) == 0
    out = capsys.readouterr().out
    assert "4 draws per cell" in out and "force_nrmse ≤ 0.02: closed" in out
    assert (tmp_path / "g.png").stat().st_size > 1000 and (tmp_path / "m.png").stat().st_size > 1000
    assert main(["report", str(tmp_path / "m.csv"), "--out", str(tmp_path / "x.png"), "--metric", "nope"]) == 2


def test_bad_options_are_refused_before_any_point(tmp_path):
    _base(tmp_path)
    p = _sweep(tmp_path, {"grid": {"demand.c_des": [250]}})
    assert main(["sweep", str(p), "--out", str(tmp_path / "r.csv"), "--workers", "0"]) == 2
    assert main(["sweep", str(p), "--out", str(tmp_path / "r.csv"), "--scheduler", "localhost:1"]) == 2
    (tmp_path / "r.csv").write_text("point,config_hash,other\n")
    assert main(["sweep", str(p), "--out", str(tmp_path / "r.csv"), "--no-progress"]) == 2  # another sweep's table


def test_a_parquet_table_resumes_and_reads_back(tmp_path, monkeypatch):
    import pyarrow  # noqa: F401 - a test dependency: missing, the test fails
    _base(tmp_path)
    path = _sweep(tmp_path, {"grid": {"demand.c_des": [200, 300, 400]}})
    out = tmp_path / "r.parquet"
    real = runner.run_point
    calls = []

    def flaky(task):
        calls.append(task["index"])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(task)

    monkeypatch.setattr(runner, "run_point", flaky)
    with pytest.raises(SweepInterrupted):
        run_sweep(load_sweep(path), out, workers=1, progress=False)
    from mrctl.sweep.table import read_results

    assert [r["point"] for r in read_results(out)[1]] == ["0"]  # a valid partial Parquet file
    monkeypatch.setattr(runner, "run_point", real)
    counts = run_sweep(load_sweep(path), out, workers=1, progress=False)
    assert counts["skipped"] == 1 and counts["ok"] == 2
    cols, rows = read_results(out)
    assert [r["point"] for r in rows] == ["0", "1", "2"] and all(r["status"] == "ok" for r in rows)
    assert not (tmp_path / "r.parquet.partial.csv").exists()
    assert main(["report", str(out), "--out", str(tmp_path / "p.png")]) == 0


def test_more_draws_run_only_the_new_ones(tmp_path):
    _base(tmp_path)
    body = {"grid": {"inverse.law": ["smooth"]}, "random": {"n": 2, "plant.parameters.F0": {"factor_uniform": [0.8, 1.2]}}}
    path = _sweep(tmp_path, body)
    for suffix in ("csv", "parquet"):
        if suffix == "parquet":
            import pyarrow  # noqa: F401 - a test dependency: missing, the test fails
        out = tmp_path / f"r.{suffix}"
        path.write_text(yaml.safe_dump({"base": "base.yaml", **body}))
        assert run_sweep(load_sweep(path), out, workers=1, progress=False)["ok"] == 2
        body2 = {**body, "random": {**body["random"], "n": 3}}
        path.write_text(yaml.safe_dump({"base": "base.yaml", **body2}))
        counts = run_sweep(load_sweep(path), out, workers=1, progress=False)
        assert counts["skipped"] == 2 and counts["ok"] == 1, suffix


def test_a_bouc_wen_base_ships_its_constants_not_its_file(tmp_path):
    from mrctl.config import validate_experiment

    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump({"base": str(EXP / "robust" / "bouc_wen_c500.yaml"),
                                 "grid": {"plant.model.parameters.n": [1.0, 2.0]}}))
    pts = list(expand(load_sweep(p, allow_outside=True)))  # a base outside the sweep's folder: allowed here
    for q, n in zip(pts, (1.0, 2.0)):
        bw = q.config["plant"]["model"]["parameters"]
        assert isinstance(bw, dict) and bw["n"] == n
        assert isinstance(q.config["parameters"], dict)
        cfg = validate_experiment(q.config, tmp_path)  # no file needed where it runs
        assert cfg.plant.model.parameters.n == n


def test_check_lists_the_points_that_will_fail(tmp_path, capsys):
    _base(tmp_path)
    p = _sweep(tmp_path, {"grid": {"safety.I_max": [0.6, 5.0, 7.0]}})
    assert main(["check", str(p)]) == 0
    out = capsys.readouterr().out
    assert "will fail" in out and "safety.I_max" in out and "OK (2 point(s) invalid" in out
