"""Never an absurd parameter set: what the data support, bounded law fits, refusals.

The cases the issue reported — Fs = 6.9e10 N with vs = 0.1 mm/s from a
record with rest and ramps, laws that go negative inside the fitted range,
a 0.05 N Coulomb force from a short stroke — each end in an error that says
which law, where, and what to try, and no file a daemon would load.
"""

from __future__ import annotations

import numpy as np
import pytest

from identify_synth import sine_levels_record
from mrctl.cli import main
from mrctl.model.params import TABLE_I
from mrctl.offline.identify import IdentificationError, identify_dataset, identify_runs
from mrctl.offline.identify.guards import Support, check_laws, law_problems, theta_problems
from mrctl.offline.identify.laws import fit_laws

SUP = Support(F_amp=20.0, v_max=0.1, x_amp=0.008)
GOOD_THETA = {"sigma0": 1e5, "sigma1": 100.0, "sigma2": 50.0, "Fc": 10.0, "Fs": 12.0, "vs": 0.02}


def test_a_sane_theta_passes():
    assert theta_problems(GOOD_THETA, SUP, "0.3 A") == []


def test_stiction_spike_from_rest_and_ramps_is_refused():
    msgs = theta_problems({**GOOD_THETA, "Fs": 6.9e10, "vs": 5e-5}, SUP, "0.3 A")
    assert len(msgs) == 2
    assert msgs[0].startswith("0.3 A: Fs = 6.9e+10 N exceeds 60 N, 3 × the force amplitude 20 N")
    assert msgs[1].startswith("0.3 A: vs = 5e-05 m/s is below 0.0001 m/s, 0.1 % of the velocity scale 0.1 m/s")
    assert "exclude rest, pauses and ramps" in msgs[1]


def test_coulomb_force_a_short_stroke_cannot_show_is_refused():
    (msg,) = theta_problems({**GOOD_THETA, "Fc": 0.05, "Fs": 0.06}, SUP, "level 5 Hz")
    assert "Fc = 0.05 N is below 0.2 N, 1 % of the force amplitude 20 N" in msg
    assert "longer stroke or a lower frequency" in msg


def test_a_law_that_crosses_zero_inside_the_range_names_where():
    bad = TABLE_I.with_overrides(vsA=-0.04, vsB=0.0281)  # vs(I) = 0 at 0.70 A
    msgs = law_problems(bad, 0.0, 1.0, SUP)
    assert len(msgs) == 1 and msgs[0].startswith("vs(1 A) = -0.0119 m/s must stay > 0")
    assert "[0, 1] A" in msgs[0] and "try: " in msgs[0]
    assert law_problems(bad, 0.0, 0.5, SUP) == []
    with pytest.raises(IdentificationError, match="not physical, so no parameters file was written"):
        check_laws(bad, 0.0, 1.0, SUP)
    # voltage laws: the unit is the input's
    assert "[0, 1] V" in law_problems(bad, 0.0, 1.0, SUP, unit="V")[0]


def test_bounded_laws_stay_above_their_floors():
    """Per-level values whose straight line goes negative at an end: the bounded fit does not."""
    I = np.array([0.0, 0.2, 0.4, 0.6])
    thetas = {"sigma0": np.array([9e4, 1.2e5, 1.5e5, 1.8e5]), "sigma1": np.array([-200, 0.0, 200, 400]),
              "sigma2": np.array([15.0, 35, 55, 75]), "Fs": np.array([1.0, 3.6, 6.4, 9.0]),
              "vs": np.array([0.030, 0.012, 0.004, 0.003]), "Fc": np.array([3.0, 8.0, 20.0, 30.0])}
    free, _ = fit_laws(I, thetas)
    assert free.vs(0.6) < 0.0  # ordinary least squares: negative inside the identified range
    floors = SUP.floors()
    p, _ = fit_laws(I, thetas, floors=floors)
    for q in np.linspace(0.0, 0.6, 61):
        assert p.vs(q) >= floors["vs"] * (1 - 1e-9) and p.Fs(q) > 0 and p.sigma0(q) > 0 and p.Fc(q) > 0
    assert law_problems(p, 0.0, 0.6, SUP) == []
    # where least squares already stays positive, the bounded fit is the same fit
    assert p.FsA == pytest.approx(free.FsA) and p.sigma2B == pytest.approx(free.sigma2B)


@pytest.fixture(scope="module")
def rest_and_ramps():
    """mrctl's own run format, but a real bench's record: a 30 N offset, rest and ramps at every current."""
    P = TABLE_I.with_overrides(F_offset=30.0)
    rec, _ = sine_levels_record([0.0, 0.2, 0.4, 0.55], params=P, amp_m=0.008, steady_cycles=4, rate_hz=1000.0,
                                F_noise_N=0.05)
    return {"t": rec["t"], "I": rec["u"], "F_meas": rec["F"], "v_meas": rec["v"], "x": rec["x"]}


def test_run_with_rest_and_ramps(rest_and_ramps, tmp_path):
    from test_identify import write_run_csv

    path = write_run_csv(tmp_path / "run.csv", rest_and_ramps)
    # without the offset the fit is absurd (the Fs spike): refused
    with pytest.raises(IdentificationError, match=r"(?s)not physical.*level 0 A: Fs = .* exceeds") as ei:
        identify_runs([path], model={"offset": False, "stiffness": False})
    assert "vs = " in str(ei.value)
    # with the offset (the default for run CSVs), a physical set (Table I's Fs and vs), its offset found;
    # only the steady cycles are fitted, each level's period its own
    res = identify_runs([path])
    for lv in res.details["levels"]:
        assert lv["theta"]["Fs"] == pytest.approx(TABLE_I.Fs(lv["level"]), rel=0.1)
        assert lv["theta"]["vs"] == pytest.approx(TABLE_I.vs(lv["level"]), rel=0.1)
        assert lv["offset_N"] == pytest.approx(30.0, abs=0.5)
    assert res.params.F_offset == pytest.approx(30.0, abs=0.5)
    assert all(s.nrmse < 0.01 for s in res.holdout)


def test_the_cli_refuses_and_writes_nothing(rest_and_ramps, tmp_path, capsys):
    path = tmp_path / "run.csv"
    cols = list(rest_and_ramps)
    rows = np.column_stack([rest_and_ramps[c] for c in cols])
    path.write_text(",".join(cols) + "\n" + "\n".join(",".join(f"{q:.9g}" for q in r) for r in rows) + "\n")
    out = tmp_path / "p.yaml"
    assert main(["identify", str(path), "--out", str(out), "--no-offset"]) == 2
    err = capsys.readouterr().err
    assert "not physical" in err and "Traceback" not in err and not out.exists()
    # the same record described as a dataset: steady cycles only, per-segment periods
    ds = tmp_path / "ds.yaml"
    ds.write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, velocity: v_meas, "
                  "force: F_meas, input: I}\nfiles: [run.csv]\n")
    res = identify_dataset(ds)
    assert [lv["level"] for lv in res.details["levels"]] == [0.0, 0.2, 0.4, 0.55]
    assert all(s.nrmse < 0.01 for s in res.holdout)
