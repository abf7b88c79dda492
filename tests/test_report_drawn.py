"""What the report draws, checked on the figure itself: the lines' data, the
shaded fault and skipped-deadline spans, the error panel's values, the
caption's verdict, and the options (--panels, --time, --size, --title)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import matplotlib  # noqa: F401 - a test dependency: missing, the test fails

from mrctl.cli import main  # noqa: E402
from mrctl.offline.report import QUARTER_CAR_PANELS, ReportError, build_figure  # noqa: E402

DT = 1e-3


def _known_run(tmp_path: Path, name: str = "run.csv", verdict: str = "degraded") -> tuple[Path, dict]:
    """2 s at 1 kHz: ticks 800-849 skipped (a 50 ms gap), rows with k in
    [1200, 1300) in fault at 0 A (x, v, F_des NaN), F = F_des + 0.5 N + a
    ramp, so the error panel has known values."""
    k = np.concatenate((np.arange(0, 800), np.arange(850, 2000))).astype(float)
    t = k * DT
    x = 0.01 * np.sin(2 * np.pi * t)
    v = 0.01 * 2 * np.pi * np.cos(2 * np.pi * t)
    F_des = 500.0 * v
    F = F_des + 0.5 + 0.1 * t
    I = np.clip(np.abs(F_des) / 60.0, 0.0, 0.5)
    fault = np.zeros_like(t)
    bad = (k >= 1200) & (k < 1300)
    fault[bad] = 1.0
    for c in (x, v, F_des):
        c[bad] = np.nan
    I[bad] = 0.0
    cols = {"t": t, "x": x, "v": v, "F_des": F_des, "F": F, "I": I, "k": k, "fault": fault}
    path = tmp_path / name
    lines = [",".join(cols)] + [",".join(repr(float(cols[c][i])) for c in cols) for i in range(len(t))]
    path.write_text("\n".join(lines) + "\n")
    side = {"law": "smooth", "I_max_A": 0.6, "settle_s": 0.5, "verdict": verdict,
            "verdict_reasons": ["ticks in fault 5.1 % > 2.0 % (acceptance.max_fault_share: by 3.1 %)"]
            if verdict == "degraded" else []}
    path.with_suffix(".json").write_text(json.dumps(side))
    return path, cols


def _axes(fig) -> dict:
    return {ax.get_label(): ax for ax in fig.axes}


def _spans(ax, label: str) -> list[tuple[float, float]]:
    return sorted((round(p.get_x(), 9), round(p.get_x() + p.get_width(), 9))
                  for p in ax.patches if p.get_label() == label)


def test_the_figure_draws_the_runs_data_errors_faults_and_skips(tmp_path):
    path, cols = _known_run(tmp_path)
    fig, (m,) = build_figure(path)
    ax = _axes(fig)
    assert list(ax) == ["force", "error", "current", "fv", "fx"]
    actual, desired = ax["force"].lines[:2]
    np.testing.assert_array_equal(actual.get_xdata(), cols["t"])
    np.testing.assert_array_equal(actual.get_ydata(), cols["F"])
    np.testing.assert_array_equal(desired.get_ydata(), cols["F_des"])
    err = ax["error"].lines[0]
    np.testing.assert_allclose(err.get_ydata(), cols["F"] - cols["F_des"])  # NaN where no demand
    ok = np.isfinite(cols["F_des"])
    np.testing.assert_allclose(err.get_ydata()[ok], 0.5 + 0.1 * cols["t"][ok], atol=1e-9)
    np.testing.assert_array_equal(ax["current"].lines[0].get_ydata(), cols["I"])
    for name in ("force", "error", "current"):  # shaded in every time panel
        assert _spans(ax[name], "fault") == [(1.2, 1.3)]  # k 1200..1299, to one tick after
        assert _spans(ax[name], "skipped deadlines") == [(0.8, 0.85)]  # after k 799, up to k 850
        assert _spans(ax[name], "settling") == [(0.0, 0.5)]
    assert m["fault_spans"] == [pytest.approx((1.2, 1.3))]
    caption = fig.get_suptitle()
    assert "verdict: DEGRADED: ticks in fault 5.1 %" in caption and "force NRMSE" in caption
    legend = [t.get_text().replace("\n", " ") for t in fig.legends[0].get_texts()]
    assert "fault: 100 ticks (5.1 % of rows)" in legend  # what the shading counts, said
    assert "skipped deadlines: 50 (2.5 % of deadlines)" in legend
    assert "settling (not in metrics)" in legend


def test_overlays_differ_in_style_and_colour_and_each_shows_its_settling(tmp_path):
    a, _ = _known_run(tmp_path, "a.csv", verdict="ok")
    b, _ = _known_run(tmp_path, "b.csv")
    fig, runs = build_figure([a, b])
    force = _axes(fig)["force"]
    ra, rb = (ln for ln in force.lines if ln.get_label() in (runs[0]["label"], runs[1]["label"]))
    assert ra.get_color() != rb.get_color() and ra.get_linestyle() != rb.get_linestyle()
    assert _spans(force, "settling") == [(0.0, 0.5)]
    assert "a.csv (smooth): " in fig.get_suptitle() and "verdict: ok" in fig.get_suptitle()


def test_panels_time_size_and_title_options(tmp_path):
    path, cols = _known_run(tmp_path)
    fig, _ = build_figure(path, panels=["error", "current"], time=(1.0, 1.5), size=(7.0, 4.0), title="bench 3")
    ax = _axes(fig)
    assert list(ax) == ["error", "current"]
    assert ax["error"].get_xlim() == (1.0, 1.5)
    t = ax["error"].lines[0].get_xdata()
    assert t.min() >= 1.0 and t.max() <= 1.5
    assert tuple(fig.get_size_inches()) == (7.0, 4.0)
    assert fig.get_suptitle().startswith("bench 3\n")
    with pytest.raises(ReportError, match="unknown panel"):
        build_figure(path, panels=["force", "bogus"])
    with pytest.raises(ReportError, match="quarter-car run"):
        build_figure(path, panels=["body_acc"])


def test_quarter_car_run_gets_ride_panels_and_rms_figures(tmp_path):
    out = tmp_path / "qc.csv"
    cfg = Path(__file__).resolve().parents[1] / "config" / "experiments" / "quarter_car.yaml"
    assert main(["simulate", str(cfg), "--out", str(out), "--duration", "2"]) in (0, 5)
    fig, (m,) = build_figure(out)
    ax = _axes(fig)
    assert tuple(ax) == QUARTER_CAR_PANELS
    from mrctl.runlog.read import read_run

    run = read_run(out)
    np.testing.assert_array_equal(ax["body_acc"].lines[0].get_ydata(), run["a_sprung"])
    np.testing.assert_allclose(ax["tyre"].lines[0].get_ydata(), 1e3 * run["tyre_defl"])
    caption = fig.get_suptitle()
    assert "RMS body acceleration" in caption and "RMS tyre deflection" in caption
    assert "force NRMSE" not in caption
    assert m["rms_a_sprung_mps2"] > 0


def test_cli_options_are_checked(tmp_path, capsys):
    path, _ = _known_run(tmp_path)
    png = tmp_path / "f.png"
    assert main(["report", str(path), "--out", str(png), "--size", "8,5", "--time", "0.5,1.8",
                 "--panels", "force,error", "--title", "t"]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert main(["report", str(path), "--out", str(png), "--size", "8"]) == 2
    assert main(["report", str(path), "--out", str(png), "--time", "2,1"]) == 2
    assert main(["report", str(path), "--out", str(png), "--panels", "nope"]) == 2
    err = capsys.readouterr().err
    assert "--size" in err and "--time" in err and "--panels" in err and "Traceback" not in err


def test_the_error_panel_is_scaled_to_the_metrics_window(tmp_path):
    """A start-up transient inside the settling window does not flatten the
    error the metrics judge: the panel's limits come from t >= settle."""
    path, cols = _known_run(tmp_path)
    text = path.read_text().splitlines()
    head, rows = text[0], text[1:]
    first = rows[0].split(",")
    first[head.split(",").index("F")] = repr(float(first[head.split(",").index("F_des")]) - 400.0)  # a 400 N kick at t = 0
    path.write_text("\n".join([head, ",".join(first), *rows[1:]]) + "\n")
    fig, _ = build_figure(path)
    lo, hi = _axes(fig)["error"].get_ylim()
    err = 0.5 + 0.1 * cols["t"][cols["t"] >= 0.5]  # F - F_des in the metrics window (settle_s 0.5)
    assert lo > -5.0 and err.min() >= lo and err.max() <= hi, (lo, hi)
