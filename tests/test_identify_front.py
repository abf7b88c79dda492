"""What a lab user meets at identification's front end (issue 26, item 6).

Repeated warnings fold into one line with a count; the figure shows a
record fitted at every level under its whole name; ``model.inertia`` on
constant-input data is refused, never silently dropped; a CSV with an
instrument's preamble is read with ``format.skip_rows``.
"""

from __future__ import annotations

import pytest

from identify_synth import TRUTH, sine_levels_record, write_csv
from mrctl.config.dataset import load_dataset
from mrctl.offline.identify import IdentificationError, identify_dataset
from mrctl.offline.identify.errors import merge_warnings
from mrctl.util.schema import ConfigError

LONG = "a-record-name-longer-than-fourteen-characters"
DS = """version: 1
protocol: constant_input
input: current
columns: {time: t, displacement: x, force: F, input: u}
"""


def test_merge_warnings_folds_the_same_text_of_several_records():
    names = ["r1", "r10", "r2"]
    ws = [f"{n}: decimated by 2 to 500 Hz (anti-aliased)" for n in names] + [
        "r10: 1 whole cycle(s), fewer than 2; skipped", "no held-out data", "no held-out data"]
    assert merge_warnings(ws, names) == [
        "decimated by 2 to 500 Hz (anti-aliased) (3 records: r1, r10, r2)",
        "r10: 1 whole cycle(s), fewer than 2; skipped", "no held-out data"]
    many = [f"run{k}.csv: decimated by 2 to 500 Hz" for k in range(15)]
    (line,) = merge_warnings(many, [f"run{k}.csv" for k in range(15)])
    assert line == "decimated by 2 to 500 Hz (15 records: run0.csv, run1.csv, run2.csv, …)"


@pytest.fixture(scope="module")
def fast(tmp_path_factory):
    """Three records at 2 kHz (decimated alike), one with a long name, three levels each."""
    d = tmp_path_factory.mktemp("fast")
    files = []
    for k, name in enumerate(["r1", "r2", LONG]):
        rec, _ = sine_levels_record([0.0, 1.0, 2.0], rate_hz=2000.0, seed=10 + k)
        write_csv(d / f"{name}.csv", rec, {"t": "t", "x": "x", "F": "F", "u": "u"})
        files.append(f"  - {{path: {name}.csv}}")
    (d / "ds.yaml").write_text(DS + "files:\n" + "\n".join(files) + "\n")
    return d, identify_dataset(d / "ds.yaml")


def test_warnings_of_every_record_become_one_line_with_a_count(fast):
    _, res = fast
    dec = [w for w in res.warnings if "decimated by" in w]
    assert len(dec) == 1 and "(3 records: " in dec[0], res.warnings


def test_the_figure_shows_every_level_and_whole_names(fast):
    from mrctl.offline.identify_figure import _pick, score_table

    _, res = fast
    picked = _pick(res.traces)
    assert sorted(tr.level for tr in picked) == [0.0, 1.0, 2.0]
    table = score_table(res)
    assert LONG in table and table.count(LONG) == 3  # one row per level, never cut to 14 characters


def test_every_level_is_drawn_past_four(tmp_path):
    from mrctl.offline.identify_figure import _pick, make_identification_figure

    rec, _ = sine_levels_record([0.0, 0.5, 1.0, 1.5, 2.0], seed=21)
    write_csv(tmp_path / "r.csv", rec, {"t": "t", "x": "x", "F": "F", "u": "u"})
    (tmp_path / "ds.yaml").write_text(DS + "files: [{path: r.csv}]\nholdout: {fraction: 0}\n")
    res = identify_dataset(tmp_path / "ds.yaml")
    picked = _pick(res.traces)  # no held-out data: the fitted cycles, still every level
    assert [tr.level for tr in picked] == [0.0, 0.5, 1.0, 1.5, 2.0] and {tr.part for tr in picked} == {"fit"}
    png = make_identification_figure(res, tmp_path / "f.png", dpi=40)
    assert png[:4] == b"\x89PNG"


def test_inertia_on_constant_input_is_refused(tmp_path):
    rec, _ = sine_levels_record([0.0, 1.0, 2.0], seed=3)
    write_csv(tmp_path / "r.csv", rec, {"t": "t", "x": "x", "F": "F", "u": "u"})
    (tmp_path / "ds.yaml").write_text(DS + "files: [{path: r.csv}]\nmodel: {inertia: true}\n")
    with pytest.raises(ConfigError) as exc:
        load_dataset(tmp_path / "ds.yaml")
    assert any(e.startswith("model.inertia: not identifiable from constant_input") for e in exc.value.errors)
    (tmp_path / "ok.yaml").write_text(DS + "files: [{path: r.csv}]\n")
    with pytest.raises(IdentificationError, match="model.inertia: not identifiable"):
        identify_dataset(tmp_path / "ok.yaml", model={"inertia": True})


def test_a_csv_with_a_preamble_needs_skip_rows(tmp_path):
    rec, _ = sine_levels_record([0.0, 1.0, 2.0], seed=4)
    write_csv(tmp_path / "plain.csv", rec, {"t": "t", "x": "x", "F": "F", "u": "u"})
    body = (tmp_path / "plain.csv").read_text()
    (tmp_path / "r.csv").write_text("Instrument: LoadFrame 3000, s/n 1234\nDate,2026-11-26\nt,x,F,u\n" + body)
    (tmp_path / "bad.yaml").write_text(DS + "files: [{path: r.csv}]\n")
    with pytest.raises(IdentificationError, match="no column 't'"):
        identify_dataset(tmp_path / "bad.yaml")
    (tmp_path / "ds.yaml").write_text(DS + "files: [{path: r.csv}]\nformat: {skip_rows: 3}\n")
    res = identify_dataset(tmp_path / "ds.yaml")
    assert len(res.details["levels"]) == 3
    assert res.details["levels"][1]["theta"]["Fc"] == pytest.approx(TRUTH.Fc(1.0), rel=0.05)
    (tmp_path / "all.yaml").write_text(DS + "files: [{path: r.csv}]\nformat: {skip_rows: 100000}\n")
    with pytest.raises(IdentificationError, match="skip_rows 100000 skips the whole file"):
        identify_dataset(tmp_path / "all.yaml")


def test_run_csv_identification_folds_its_warnings_too(tmp_path):
    from test_identify import identify_csvs, staircase

    runs = [staircase([0.0, 0.25, 0.5], dt=5e-4, step_s=2.0, seed=s) for s in (1, 2, 3)]
    res = identify_csvs(tmp_path, runs, names=["a", "b", "c"])
    dec = [w for w in res.warnings if "decimated by 2" in w]
    assert dec == ["decimated by 2 to 1000 Hz (anti-aliased) (3 records: a, b, c)"], res.warnings


def test_table_laws_for_broadband_are_refused(tmp_path):
    (tmp_path / "r.csv").write_text("t,x,F,u\n0,0,0,0\n")
    (tmp_path / "ds.yaml").write_text("version: 1\nprotocol: broadband\ninput: current\n"
                                      "columns: {time: t, displacement: x, force: F, input: u}\n"
                                      "files: [{path: r.csv}]\nfit: {laws: table}\n")
    with pytest.raises(ConfigError) as exc:
        load_dataset(tmp_path / "ds.yaml")
    assert any(e.startswith("fit.laws: table is for constant_input") for e in exc.value.errors)


# -- mrctl's own constant-current runs: the same choice of laws as a dataset -------------------

def _curved_table_i(levels):
    """Table I with a hump in Fs and a curve in σ2 over the currents: not the paper's straight lines."""
    import numpy as np

    from mrctl.model.params import TABLE_I, ThetaTable

    u = np.asarray(levels, float)
    cols = [[TABLE_I.Fc(x) for x in u], 0.6 + 30.0 * np.sin(np.pi * u / 0.55),
            [TABLE_I.sigma0(x) for x in u], [TABLE_I.sigma1(x) for x in u], 15.0 + 500.0 * u ** 2,
            [TABLE_I.vs(x) for x in u]]
    from dataclasses import replace

    return replace(TABLE_I, table=ThetaTable(tuple(u.tolist()), tuple(tuple(float(x) for x in c) for c in cols)))


def test_run_csvs_write_table_laws_where_the_paper_laws_cannot_follow(tmp_path):
    import numpy as np
    from test_identify import identify_csvs, staircase

    from mrctl.config import load_params_file, load_yaml
    from mrctl.offline.identify import write_result

    currents = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    truth = _curved_table_i(np.linspace(0.0, 0.55, 23))
    res = identify_csvs(tmp_path, [staircase(currents, step_s=2.0, params=truth)], names=["curved"])
    ch = res.details["laws_choice"]
    assert ch["laws"] == "table" and res.params.laws == "table", ch
    assert ch["leave_level_out_mean"]["table"] < ch["leave_level_out_mean"]["paper"]
    for s in res.holdout:
        assert s.nrmse_laws == s.nrmse_table and s.nrmse_table <= 1.2 * s.nrmse + 1e-4
    assert max(s.nrmse_paper for s in res.holdout) > 2.0 * max(s.nrmse_table for s in res.holdout)
    out = tmp_path / "p.yaml"
    write_result(res, out)
    assert load_params_file(out).laws == "table" and load_yaml(out)["fit"]["laws"]["laws"] == "table"
    # and the paper's laws where the damper follows them (Table I), or when asked
    plain = identify_csvs(tmp_path, [staircase(currents, step_s=2.0)], names=["plain"])
    assert plain.details["laws_choice"]["laws"] == "paper" and plain.params.table is None
    forced = identify_csvs(tmp_path, [staircase(currents, step_s=2.0, params=truth)], names=["forced"], laws="paper")
    assert forced.params.laws == "paper" and all(s.nrmse_laws == s.nrmse_paper for s in forced.holdout)
    from mrctl.cli import main

    assert main(["identify", str(tmp_path / "forced.csv"), "--fit-laws", "table", "--out", str(tmp_path / "t.yaml"),
                 "-q", "--no-progress"]) == 0
    assert load_params_file(tmp_path / "t.yaml").laws == "table"
