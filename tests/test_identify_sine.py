"""Constant-input sine tests as a lab records them, made by our own plant.

Two MATLAB files (written with ``scipy.io.savemat``, the lab's variable
names, displacement in mm and not centred, no velocity) each pass through
three input levels; every level starts at rest, ramps the stroke in over two
cycles, holds six steady cycles, ramps out over one and pauses; the two
files run at different frequencies; the force has an offset, a stiffness,
noise and quantisation. The protocol must find the steady cycles, estimate
each segment's period, fit each level with the offset and recover the set.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from identify_synth import TRUTH, sine_levels_record
from mrctl.cli import main
from mrctl.offline.identify import identify_dataset
from mrctl.offline.identify.prep import savgol_window


def _levels(segs):
    return "[" + ", ".join(f"{{from_s: {a:.6f}, to_s: {b:.6f}, value: {v}}}" for a, b, v in segs) + "]"


@pytest.fixture(scope="module")
def sine_dir(tmp_path_factory):
    from scipy.io import savemat

    d = tmp_path_factory.mktemp("sine")
    rec_a, seg_a = sine_levels_record([0.0, 1.0, 2.0], seed=3)
    rec_b, seg_b = sine_levels_record([0.5, 1.5, 2.5], seed=4, freq_hz=1.5, amp_m=0.01)
    for name, rec in (("a", rec_a), ("b", rec_b)):
        savemat(d / f"{name}.mat", {"Tout": rec["t"][:, None], "dist": 1e3 * rec["x"][:, None],
                                    "forc": rec["F"][:, None]})
    (d / "ds.yaml").write_text(f"""version: 1
protocol: constant_input
input: current
columns: {{time: Tout, displacement: {{name: dist, scale: 0.001}}, force: forc}}
files:
  - {{path: a.mat, levels: {_levels(seg_a)}}}
  - {{path: b.mat, levels: {_levels(seg_b)}}}
""")
    return d


@pytest.fixture(scope="module")
def result(sine_dir):
    return identify_dataset(sine_dir / "ds.yaml")


def test_segments_steady_cycles_and_periods(result):
    levels = result.details["levels"]
    assert [lv["level"] for lv in levels] == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
    for lv in levels:
        (seg,) = lv["segments"]
        # six steady cycles: ramps in and out and the pauses are left out; half held out
        assert seg["cycles_fit"] + seg["cycles_holdout"] in (5, 6)
        assert seg["cycles_holdout"] == 3
        freq = 2.0 if lv["level"] in (0.0, 1.0, 2.0) else 1.5
        assert seg["period_s"] == pytest.approx(1.0 / freq, rel=0.01)
        assert seg["stroke_m"] == pytest.approx(0.016 if freq == 2.0 else 0.020, rel=0.02)


def test_recovers_each_level_with_its_offset(result):
    for lv in result.details["levels"]:
        u, th = lv["level"], lv["theta"]
        assert th["Fc"] == pytest.approx(TRUTH.Fc(u), rel=0.03), u
        assert th["sigma2"] == pytest.approx(TRUTH.sigma2(u), rel=0.05), u
        assert th["Fs"] == pytest.approx(TRUTH.Fs(u), rel=0.05), u
        assert th["vs"] == pytest.approx(TRUTH.vs(u), rel=0.10), u
        assert lv["offset_N"] == pytest.approx(TRUTH.F_offset, abs=1.0)  # displacement not centred: 12 mm
        assert lv["k_x"] == pytest.approx(TRUTH.k_x, rel=0.10)
    p = result.params
    for u in np.linspace(0.0, 2.5, 11):
        assert p.Fc(u) == pytest.approx(TRUTH.Fc(u), rel=0.03)
    assert p.F_offset == pytest.approx(TRUTH.F_offset, abs=1.0) and p.tau_input == 0.0


def test_held_out_scores_per_record_and_level(result):
    assert {(s.record, s.level) for s in result.holdout} == {
        ("a", 0.0), ("a", 1.0), ("a", 2.0), ("b", 0.5), ("b", 1.5), ("b", 2.5)}
    for s in result.holdout:
        # 0.3 N noise on 60-400 N peak-to-peak: at the noise floor, with the per-level Θ and with the laws
        assert s.nrmse < 0.006 and s.nrmse_laws < 0.01, s
        # the condition each score holds for: file a at 2 Hz / 16 mm, file b at 1.5 Hz / 20 mm peak to peak
        freq, stroke = (2.0, 0.016) if s.record == "a" else (1.5, 0.020)
        assert s.frequency_hz == pytest.approx(freq, rel=0.01) and s.stroke_m == pytest.approx(stroke, rel=0.02), s


def test_conditions_figure(result, tmp_path):
    from mrctl.errors import BadInput
    from mrctl.offline.identify_figure import FigureError, make_conditions_figure

    png = tmp_path / "c.png"
    make_conditions_figure(result, png)
    assert png.read_bytes().startswith(b"\x89PNG")
    with pytest.raises(BadInput, match="refusing"):  # never written over
        make_conditions_figure(result, png)
    with pytest.raises(FigureError, match="unknown figure format"):
        make_conditions_figure(result, tmp_path / "c.txt")


def test_without_the_offset_the_fit_is_refused_not_written(sine_dir, tmp_path, capsys):
    """A 40 N offset the model may not fit drives σ2 negative and Fc past what the data support."""
    out = tmp_path / "p.yaml"
    assert main(["identify", "--dataset", str(sine_dir / "ds.yaml"), "--out", str(out), "--no-offset"]) == 2
    err = capsys.readouterr().err
    assert "not physical, so no parameters file was written" in err
    assert "level 0 A: sigma2 = " in err and "must stay >= 0" in err and "offset" in err
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_input_column_instead_of_levels_and_named_holdout(tmp_path):
    """A CSV with the commanded input as a column (levels found from it), one record held out whole."""
    for name, seed, freq in (("r1", 5, 2.0), ("r2", 6, 2.0)):
        rec, _ = sine_levels_record([0.2, 1.2, 2.2], seed=seed, freq_hz=freq)
        rows = "\n".join(f"{a:.6f},{1e3 * x:.4f},{f:.4f},{u:.3f}" for a, x, f, u in
                         zip(rec["t"], rec["x"], rec["F"], rec["u"]))
        (tmp_path / f"{name}.csv").write_text("t,x_mm,F,I\n" + rows + "\n")
    (tmp_path / "ds.yaml").write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: "
                                      "{name: x_mm, scale: 0.001}, force: F, input: I}\nfiles: [r1.csv, r2.csv]\n")
    res = identify_dataset(tmp_path / "ds.yaml", holdout="r2")
    assert {s.record for s in res.holdout} == {"r2"} and len(res.holdout) == 3
    assert res.settings["holdout_records"] == ["r2"] and res.settings["holdout_fraction"] == 0.0
    assert all(s.nrmse < 0.01 for s in res.holdout)
    for lv in res.details["levels"]:
        assert all(seg["record"] == "r1" for seg in lv["segments"])
        assert lv["theta"]["Fc"] == pytest.approx(TRUTH.Fc(lv["level"]), rel=0.05)


def test_cli_dataset_json_and_figure(sine_dir, tmp_path, capsys):
    out = tmp_path / "p.yaml"
    png = tmp_path / "p.png"
    assert main(["identify", str(sine_dir / "ds.yaml"), "--out", str(out), "--report", str(png)]) == 0
    text = capsys.readouterr().out
    assert "level (A)" in text and "with laws" in text and f"wrote {png}" in text
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["protocol"] == "constant_input" and summary["input"] == "current"
    assert len(summary["holdout"]) == 6
    assert {"record", "level", "nrmse", "stroke_m", "frequency_hz"} <= set(summary["holdout"][0])
    assert png.read_bytes().startswith(b"\x89PNG")


def test_savgol_window_follows_rate_and_band():
    assert savgol_window(100.0, 1.0) % 2 == 1
    # the window shrinks as the band widens and grows with the rate, and never drops below 5
    assert savgol_window(1000.0, 2.0) > savgol_window(1000.0, 20.0) > savgol_window(1000.0, 200.0) >= 5
    assert savgol_window(2000.0, 20.0) > savgol_window(1000.0, 20.0)


def test_the_summary_page_has_the_conditions_and_the_per_level_table(result):
    """Two files at two strokes and frequencies: the summary adds the NRMSE
    against each and the per-level table, one colour and marker per level
    in both; nothing empty, no unit twice, every legend told apart."""
    from figure_checks import axes_without_data, doubled_units, legends_with_lookalikes

    from mrctl.offline.identify_figure import build_identification_figure

    fig = build_identification_figure(result)
    labels = [ax.get_label() for ax in fig.axes]
    assert {"scores", "worst-time", "worst-fv", "stroke", "frequency", "levels-table"} <= set(labels)
    assert len(labels) == 12
    assert not axes_without_data(fig) and not doubled_units(fig) and not legends_with_lookalikes(fig)
    stroke = fig.axes[labels.index("stroke")]
    pts = sorted((round(float(x), 3), round(float(y), 4)) for ln in stroke.lines if ln.get_label()[:1].isdigit()
                 for x, y in zip(ln.get_xdata(), ln.get_ydata()))
    want = sorted((round(1e3 * s.stroke_m, 3), round(100 * (s.nrmse_laws if s.nrmse_laws is not None else s.nrmse), 4))
                  for s in result.holdout)
    assert pts == want
    table = fig.axes[labels.index("levels-table")].texts[0].get_text()
    assert all(f"{lv['level']:.4g}" in table for lv in result.details["levels"])
