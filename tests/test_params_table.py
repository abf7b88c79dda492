"""``laws: table``: per-level Θ interpolated piecewise linearly, beside the paper's laws (6)–(11).

A real damper's per-level Θ need not follow the paper's shapes (a squared
Langevin function, straight lines); a table passes through every level. It
loads from a parameters file (the input strictly increasing, Θ physical),
runs in the model, the plant and the inverse laws, pickles and round-trips
through a sweep's inline mapping, and identification writes it when it
predicts the levels it was not fitted to better than the paper's laws.
"""

from __future__ import annotations

import math
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from identify_synth import TRUTH, sine_levels_record
from mrctl.config.params import params_check, read_params_file
from mrctl.model.lugre import LuGreModel, force
from mrctl.model.mapping import params_from_mapping
from mrctl.model.params import TABLE_I, TABLE_NAMES, ThetaTable
from mrctl.model.plant import DamperPlant
from mrctl.util.schema import ConfigError

ROOT = Path(__file__).resolve().parents[1]
LEVELS = [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]


def _table_of(p, levels, bench=None) -> ThetaTable:
    cols = [tuple(getattr(p, k)(u) for u in levels) for k in TABLE_NAMES]
    if bench is not None:
        cols += [tuple(b[0] for b in bench), tuple(b[1] for b in bench)]
    return ThetaTable(tuple(levels), tuple(cols))


def _yaml(tmp_path, table: str, laws: str = "table"):
    f = tmp_path / "p.yaml"
    f.write_text(f"version: 1\ninput: current\nlaws: {laws}\nsigma0A: 1.0e5\n{table}")
    return f


GOOD = """table:
  input: [0.0, 0.25, 0.5]
  Fc: [3.0, 10.0, 14.0]
  Fs: [2.0, 6.0, 8.0]
  sigma0: [9.0e4, 1.2e5, 1.6e5]
  sigma1: [-290.0, 0.0, 270.0]
  sigma2: [15.0, 40.0, 65.0]
  vs: [0.028, 0.024, 0.020]
"""


def test_a_table_file_loads_and_interpolates_piecewise_linearly(tmp_path):
    pf = read_params_file(_yaml(tmp_path, GOOD))
    p = pf.params
    assert p.laws == "table" and p.sigma0A == 1.0e5  # the 13 constants stay (the inverse laws' fallback)
    assert p.Fc(0.25) == 10.0 and p.Fc(0.125) == pytest.approx(6.5) and p.sigma1(0.375) == pytest.approx(135.0)
    assert p.Fs(-1.0) == 2.0 and p.vs(9.0) == 0.020  # the end values held outside the levels
    # monotone between levels: never beyond its neighbours
    grid = np.linspace(0.0, 0.5, 101)
    fc = [p.Fc(float(u)) for u in grid]
    assert np.all(np.diff(fc) >= 0.0)
    # at a level, exactly that level's value (the written set is the level's fit there)
    t = ThetaTable((0.0, 0.1, 0.3), ((0.1, 0.3, 0.7),) * 6)
    assert [t.value(0, u) for u in t.u] == [0.1, 0.3, 0.7]
    # the paper's set is untouched by default
    assert TABLE_I.laws == "paper" and TABLE_I.table is None


@pytest.mark.parametrize("table, expect", [
    (GOOD.replace("[0.0, 0.25, 0.5]", "[0.0, 0.5, 0.25]"), "table.input: must be strictly increasing"),
    (GOOD.replace("[0.0, 0.25, 0.5]", "[0.0, 0.25, 0.25]"), "table.input: must be strictly increasing"),
    (GOOD.replace("Fs: [2.0, 6.0, 8.0]", "Fs: [2.0, 6.0]"), "table.Fs: 2 values for 3 levels"),
    (GOOD.replace("vs: [0.028, 0.024, 0.020]", "vs: [0.028, -0.024, 0.020]"), "table.vs[1]: must be > 0"),
    (GOOD.replace("  sigma2: [15.0, 40.0, 65.0]\n", ""), "table.sigma2: must be a list of numbers"),
    (GOOD + "  F_offset: [1.0, 2.0, 3.0]\n", "table.F_offset: give both F_offset and k_x"),
    (GOOD + "  Fq: [1.0, 2.0, 3.0]\n", "table.Fq: unknown"),
])
def test_a_bad_table_is_refused_with_its_key_path(tmp_path, table, expect):
    with pytest.raises(ConfigError) as exc:
        read_params_file(_yaml(tmp_path, table))
    assert any(expect in e for e in exc.value.errors), exc.value.errors


def test_laws_must_name_a_kind_and_a_table_needs_laws_table(tmp_path):
    with pytest.raises(ConfigError, match="laws: 'spline' not allowed"):
        read_params_file(_yaml(tmp_path, GOOD, laws="spline"))
    with pytest.raises(ConfigError, match="table: given but laws is not 'table'"):
        read_params_file(_yaml(tmp_path, GOOD, laws="paper"))
    with pytest.raises(ConfigError, match="laws: table needs a mapping"):
        read_params_file(_yaml(tmp_path, ""))


def test_table_of_the_paper_laws_gives_the_paper_model_at_the_levels():
    levels = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    p = replace(TABLE_I, table=_table_of(TABLE_I, levels))
    for u in levels:
        for v, z in ((0.05, 1e-5), (-0.1, -2e-5), (0.002, 0.0)):
            assert force(p, z, v, u) == pytest.approx(force(TABLE_I, z, v, u), rel=1e-12, abs=1e-9)
    # the linear laws (7)-(11) are piecewise linear already: equal between the levels too
    assert p.sigma2(0.37) == pytest.approx(TABLE_I.sigma2(0.37), rel=1e-12)
    m_t, m_p = LuGreModel(p), LuGreModel(TABLE_I)
    for k in range(200):
        v = 0.1 * math.sin(0.05 * k)
        m_t.advance(v, 0.3, 1e-3)
        m_p.advance(v, 0.3, 1e-3)
    assert m_t.force(0.01, 0.3) == pytest.approx(m_p.force(0.01, 0.3), rel=1e-9)


def test_a_table_set_simulates_with_its_per_level_bench_terms():
    levels = [0.0, 0.25, 0.5]
    table = _table_of(TABLE_I, levels, bench=[(10.0, 100.0), (20.0, 100.0), (30.0, 300.0)])
    p = replace(TABLE_I, table=table)
    plant, ref = DamperPlant(p, 1e-3), DamperPlant(TABLE_I, 1e-3)
    for k in range(500):
        v = 0.05 * math.sin(2 * math.pi * k / 500)
        F, Fr = plant.tick(v, 0.25, 0.01), ref.tick(v, 0.25, 0.01)
        assert math.isfinite(F)
    assert F - Fr == pytest.approx(20.0 + 100.0 * 0.01, rel=1e-9)  # offset(0.25) + k_x(0.25)·x


def test_the_inverse_laws_accept_a_table_set_and_use_its_local_slope():
    from mrctl.laws.base import Measurement
    from mrctl.laws.inverse import PaperInverse, SmoothInverse

    levels = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    p = replace(TABLE_I, table=_table_of(TABLE_I, levels))
    # σ0, σ1, σ2 are linear in I: the table's segments give the paper's slopes exactly
    for j, (a, b) in ((2, ("sigma0A", "sigma0B")), (4, ("sigma2A", "sigma2B"))):
        A, B = p.table.local(j, 0.33)
        assert A == pytest.approx(getattr(TABLE_I, a), rel=1e-9) and B == pytest.approx(getattr(TABLE_I, b), rel=1e-9)
    for cls in (PaperInverse, SmoothInverse):  # eq (12) as published jumps: compare the smooth law only
        law_t, law_p = cls(p, 0.6, 1e-3), cls(TABLE_I, 0.6, 1e-3)
        got, ref = [], []
        for k in range(400):
            t = k * 1e-3
            m = Measurement(k, t, 0.01 * math.sin(6.0 * t), 0.06 * math.cos(6.0 * t))
            F_des = 300.0 * m.v
            got.append(law_t.current(m, F_des))
            ref.append(law_p.current(m, F_des))
        assert all(0.0 <= i <= 0.6 for i in got)
        if cls is SmoothInverse:
            diff = np.abs(np.array(got) - np.array(ref))
            assert np.mean(diff) < 0.005 and np.max(diff) < 0.15  # Fc between levels differs a little


def test_a_table_set_pickles_and_round_trips_through_an_inline_mapping(tmp_path):
    p = replace(TABLE_I, table=_table_of(TABLE_I, [0.0, 0.3, 0.6], bench=[(1.0, 0.0), (2.0, 0.0), (3.0, 0.0)]))
    assert pickle.loads(pickle.dumps(p)) == p
    d = p.as_dict()
    assert d["laws"] == "table" and d["table"]["input"] == [0.0, 0.3, 0.6]
    assert params_from_mapping(d) == p
    back, errors = params_check(tmp_path)(d, "parameters")  # what a sweep writes into its configs
    assert errors == [] and back == p
    _, errors = params_check(tmp_path)({**d, "table": {**d["table"], "input": [0.0, 0.6, 0.3]}}, "parameters")
    assert any("parameters.table.input: must be strictly increasing" in e for e in errors)


# -- identification: table laws where the paper's shapes cannot follow -----------------------------

#: a damper whose Fs has a hump and σ2 a curve over the levels: the paper's linear laws cannot follow them
CURVED = replace(TRUTH, table=ThetaTable(
    tuple(np.linspace(0.0, 2.5, 26).tolist()),
    tuple(tuple(float(x) for x in col) for col in (
        [TRUTH.Fc(u) for u in np.linspace(0.0, 2.5, 26)],
        25.0 + 110.0 * np.sin(np.pi * np.linspace(0.0, 2.5, 26) / 2.5),
        [TRUTH.sigma0(u) for u in np.linspace(0.0, 2.5, 26)],
        [TRUTH.sigma1(u) for u in np.linspace(0.0, 2.5, 26)],
        100.0 + 160.0 * np.linspace(0.0, 2.5, 26) ** 2,
        [TRUTH.vs(u) for u in np.linspace(0.0, 2.5, 26)],
    ))))


def _levels_dataset(d, params, seed: int):
    """A constant-input record through LEVELS of the damper ``params`` (no input lag), and its description
    ``d/ds.yaml``."""
    from identify_synth import write_csv

    rec, _ = sine_levels_record(LEVELS, params=replace(params, tau_input=0.0), seed=seed)
    write_csv(d / "r.csv", rec, {"t": "t", "x": "x", "F": "F", "u": "u"})
    (d / "ds.yaml").write_text("""version: 1
protocol: constant_input
input: current
columns: {time: t, displacement: x, force: F, input: u}
files: [{path: r.csv}]
""")
    return d / "ds.yaml"


@pytest.fixture(scope="module")
def curved(tmp_path_factory):
    from mrctl.offline.identify import identify_dataset

    d = tmp_path_factory.mktemp("curved")
    return d, identify_dataset(_levels_dataset(d, CURVED, seed=5))


def test_identification_writes_table_laws_that_beat_the_paper_laws(curved, tmp_path):
    from mrctl.offline.identify.result import write_result

    d, res = curved
    ch = res.details["laws_choice"]
    assert ch["laws"] == "table" and res.params.laws == "table"
    loo = ch["leave_level_out_mean"]
    assert loo["table"] < loo["paper"], loo  # the levels it was not fitted to, on the whole
    by_level: dict[float, list] = {}
    for s in res.holdout:
        by_level.setdefault(s.level, []).append(s)
    assert len(by_level) == len(LEVELS)
    for lv, scores in by_level.items():
        fit = np.mean([s.nrmse for s in scores])
        assert np.mean([s.nrmse_laws for s in scores]) <= 1.2 * fit, lv  # the written set ≈ the per-level fits
        assert np.mean([s.nrmse_table for s in scores]) <= np.mean([s.nrmse_paper for s in scores]) + 1e-12
    assert max(np.mean([s.nrmse_paper for s in sc]) for sc in by_level.values()) > 2.0 * max(
        np.mean([s.nrmse_table for s in sc]) for sc in by_level.values())
    # written and read back: the same set, the controller's loader accepts it
    out = tmp_path / "p.yaml"
    write_result(res, out)
    back = read_params_file(out).params
    assert back.laws == "table" and back.table.u == pytest.approx(res.params.table.u)
    assert back.Fs(1.25) == pytest.approx(res.params.Fs(1.25), rel=1e-6)


def test_fit_laws_paper_keeps_the_paper_laws_and_reports_both(curved):
    from mrctl.config.dataset import load_dataset
    from mrctl.offline.identify import identify_dataset

    d, _ = curved
    (d / "paper.yaml").write_text((d / "ds.yaml").read_text() + "fit: {laws: paper}\n")
    res = identify_dataset(load_dataset(d / "paper.yaml"), source="paper.yaml")
    assert res.params.laws == "paper" and res.details["laws_choice"]["asked"] == "paper"
    assert all(s.nrmse_laws == s.nrmse_paper and s.nrmse_table is not None for s in res.holdout)


def test_auto_keeps_the_paper_laws_where_the_damper_follows_them(tmp_path):
    """The synthetic damper of the paper's laws: leaving a level out, the laws predict it at least as well."""
    from mrctl.offline.identify import identify_dataset

    res = identify_dataset(_levels_dataset(tmp_path, TRUTH, seed=6))
    assert res.details["laws_choice"]["laws"] == "paper", res.details["laws_choice"]


# -- the chain: mrctl simulate and hil_sim run a table set from its file ------------------------

TABLE_FILE = """version: 1
input: current
laws: table
table:
  input: [0.0, 0.15, 0.35, 0.6]
  Fc: [3.0, 12.0, 20.0, 26.0]
  Fs: [2.5, 5.0, 9.0, 11.0]
  sigma0: [9.0e4, 1.1e5, 1.4e5, 1.8e5]
  sigma1: [-280.0, -100.0, 120.0, 400.0]
  sigma2: [15.0, 30.0, 50.0, 75.0]
  vs: [0.028, 0.026, 0.023, 0.018]
  F_offset: [1.0, 1.5, 2.5, 2.0]
  k_x: [0.0, 50.0, 100.0, 80.0]
"""


def test_mrctl_simulate_runs_a_table_set(tmp_path, capsys):
    from mrctl.cli import main
    from mrctl.config import load_yaml

    (tmp_path / "p.yaml").write_text(TABLE_FILE)
    exp = load_yaml(ROOT / "config" / "experiments" / "fig5.yaml")
    exp["parameters"] = "p.yaml"
    exp["duration_s"] = 1.0
    import yaml

    (tmp_path / "exp.yaml").write_text(yaml.safe_dump(exp))
    out = tmp_path / "sim.csv"
    assert main(["simulate", str(tmp_path / "exp.yaml"), "--out", str(out), "-q"]) == 0, capsys.readouterr().err
    lines = out.read_text().splitlines()
    head = next(ln for ln in lines if ln.startswith("t,")).split(",")
    rows = [ln.split(",") for ln in lines[lines.index(",".join(head)) + 1:]]
    I = np.array([float(r[head.index("I")]) for r in rows])
    assert len(rows) >= 999 and np.all((I >= 0.0) & (I <= 0.6)) and I.max() > 0.05
    # the log's sidecar carries the table: a replay runs the same laws
    rep = tmp_path / "rep.csv"
    assert main(["simulate", "--replay", str(out), "--law", "paper", "--out", str(rep), "-q"]) == 0
    import json

    side = json.loads(rep.with_suffix(".json").read_text())
    assert side["parameters"]["laws"] == "table" and side["parameters"]["table"]["k_x"] == [0.0, 50.0, 100.0, 80.0]


def test_hil_sim_bench_takes_a_table_set(tmp_path):
    from hil_sim.config import validate_bench

    (tmp_path / "p.yaml").write_text(TABLE_FILE)
    sine = {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0}
    cfg = validate_bench({"version": 1, "parameters": "p.yaml", "duration_s": 1, "excitation": sine}, tmp_path, "test")
    assert cfg.params.laws == "table" and cfg.params.Fc(0.25) == pytest.approx(16.0)
    assert cfg.describe()["parameters"]["table"]["input"] == [0.0, 0.15, 0.35, 0.6]
    bad = TABLE_FILE.replace("[0.0, 0.15, 0.35, 0.6]", "[0.0, 0.35, 0.15, 0.6]")
    (tmp_path / "bad.yaml").write_text(bad)
    with pytest.raises(ConfigError) as exc:
        validate_bench({"version": 1, "parameters": "bad.yaml", "excitation": sine}, tmp_path, "test")
    assert any("table.input: must be strictly increasing" in e for e in exc.value.errors), exc.value.errors
