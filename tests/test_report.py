"""Tests of mrctl.offline.report: CSV loading, the summary metrics, and the PNG."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mrctl.offline.report import ReportError, load_run, make_report, summarize

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
OFFSET_N = 0.5  # constant force error built into the synthetic run


def synthetic(duration: float = 2.0, dt: float = 1e-3) -> dict[str, np.ndarray]:
    """1 Hz sine stroke, F_des = 500·v, F = F_des + constant offset, I ∝ |F_des|."""
    t = np.arange(0.0, duration, dt)
    x = 0.01 * np.sin(2 * np.pi * t)
    v = 0.01 * 2 * np.pi * np.cos(2 * np.pi * t)
    F_des = 500.0 * v
    F = F_des + OFFSET_N
    I = np.clip(np.abs(F_des) / 60.0, 0.0, 0.5)
    I[np.abs(F_des) < 3.0] = 0.0
    return {"t": t, "x": x, "v": v, "F_des": F_des, "F": F, "I": I}


def write_csv(path: Path, cols: dict[str, np.ndarray], order: list[str] | None = None,
              preamble: str = "") -> Path:
    order = order or list(cols)
    n = len(next(iter(cols.values())))
    lines = [",".join(order)]
    lines += [",".join(repr(float(cols[c][k])) for c in order) for k in range(n)]
    path.write_text(preamble + "\n".join(lines) + "\n")
    return path


def expected_nrmse(cols: dict[str, np.ndarray], settle: float = 1.0) -> float:
    w = cols["t"] >= cols["t"][0] + settle
    return OFFSET_N / float(np.ptp(cols["F_des"][w]))


# -- make_report --------------------------------------------------------------
def test_make_report_writes_png(tmp_path: Path) -> None:
    csv_path = write_csv(tmp_path / "run.csv", synthetic())
    out = tmp_path / "fig.png"
    make_report(csv_path, out)
    data = out.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    assert len(data) > 20_000


def test_make_report_short_run_and_custom_title(tmp_path: Path) -> None:
    # Shorter than the settle time: the whole run is used, nothing crashes.
    csv_path = write_csv(tmp_path / "short.csv", synthetic(duration=0.3))
    out = tmp_path / "short.png"
    make_report(csv_path, out, title="bench 7, 0.3 s")
    assert out.read_bytes().startswith(PNG_SIGNATURE)


def test_make_report_unwritable_output(tmp_path: Path) -> None:
    csv_path = write_csv(tmp_path / "run.csv", synthetic())
    with pytest.raises(ReportError, match="cannot write"):
        make_report(csv_path, tmp_path / "no_such_dir" / "fig.png")


def test_make_report_without_matplotlib(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    real_import = builtins.__import__

    def no_mpl(name, *args, **kwargs):
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mpl)
    csv_path = write_csv(tmp_path / "run.csv", synthetic())
    with pytest.raises(ReportError, match=r"pip install 'mrctl\[plot\]'"):
        make_report(csv_path, tmp_path / "fig.png")
    assert not (tmp_path / "fig.png").exists()


# -- summarize ----------------------------------------------------------------
def test_summarize_known_offset_nrmse() -> None:
    cols = synthetic()
    m = summarize(cols)
    assert m["nrmse"] == pytest.approx(expected_nrmse(cols), abs=1e-9)
    assert m["t_start"] == pytest.approx(1.0, abs=1e-9)


def test_summarize_window_excludes_transient() -> None:
    cols = synthetic()
    cols["F"] = cols["F"].copy()
    cols["F"][cols["t"] < 1.0] += 100.0  # huge start-up error, inside the settle window
    assert summarize(cols)["nrmse"] == pytest.approx(expected_nrmse(cols), abs=1e-9)
    assert summarize(cols, settle=0.0)["nrmse"] > 1.0


def test_summarize_short_run_uses_whole_run() -> None:
    cols = synthetic(duration=0.5)
    m = summarize(cols, settle=1.0)
    assert m["t_start"] == 0.0
    assert m["n"] == len(cols["t"])
    assert m["nrmse"] == pytest.approx(OFFSET_N / np.ptp(cols["F_des"]), abs=1e-9)


def test_summarize_current_metrics() -> None:
    t = np.arange(6) * 1e-3
    zeros = np.zeros(6)
    I = np.array([0.0, 0.2, 0.5, 0.5, 0.1, 0.0])
    cols = {"t": t, "x": zeros, "v": zeros, "F_des": np.arange(6.0), "F": np.arange(6.0), "I": I}
    m = summarize(cols, settle=0.0)
    assert m["nrmse"] == 0.0
    assert m["max_dI"] == pytest.approx(0.4)
    assert m["share_zero"] == pytest.approx(2 / 6)
    assert m["share_max"] == pytest.approx(2 / 6)


def test_summarize_flat_reference_is_nan() -> None:
    cols = synthetic()
    cols["F_des"] = np.zeros_like(cols["F_des"])
    assert math.isnan(summarize(cols)["nrmse"])


# -- load_run: tolerated input ------------------------------------------------
def test_load_run_extra_columns_any_order_and_comments(tmp_path: Path) -> None:
    cols = synthetic(duration=0.05)
    n = len(cols["t"])
    path = tmp_path / "run.csv"
    header = "seq,I,z,F,fault,t,F_des,v,x"
    def f(c: str, k: int) -> str:
        return repr(float(cols[c][k]))

    rows = [
        f"{k},{f('I', k)},0.001,{f('F', k)},none,{f('t', k)},{f('F_des', k)},{f('v', k)},{f('x', k)}"
        for k in range(n)
    ]
    rows.insert(10, "# operator note: bumped the rig")
    path.write_text("# mrctl run 0.1\n# params: table1.yaml\n" + header + "\n" + "\n".join(rows) + "\n")

    loaded = load_run(path)
    assert set(loaded) == {"t", "x", "v", "F_des", "F", "I"}
    for c, arr in cols.items():
        np.testing.assert_array_equal(loaded[c], arr)
    assert loaded["t"].dtype == np.float64

    out = tmp_path / "fig.png"
    make_report(path, out)
    assert out.read_bytes().startswith(PNG_SIGNATURE)


# -- load_run: bad input ------------------------------------------------------
def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ReportError, match="no such file"):
        load_run(tmp_path / "nope.csv")


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"])
def test_empty_file(tmp_path: Path, text: str) -> None:
    path = tmp_path / "empty.csv"
    path.write_text(text)
    with pytest.raises(ReportError, match="empty"):
        load_run(path)


def test_missing_column_named_and_found_listed(tmp_path: Path) -> None:
    cols = synthetic(duration=0.01)
    del cols["F_des"]
    path = write_csv(tmp_path / "run.csv", cols, order=["t", "x", "v", "F", "I"])
    with pytest.raises(ReportError) as info:
        load_run(path)
    msg = str(info.value)
    assert "F_des" in msg
    assert "found: t, x, v, F, I" in msg


def test_several_missing_columns_all_named(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("t,x,v\n0,0,0\n0.001,0,0\n")
    with pytest.raises(ReportError) as info:
        load_run(path)
    assert "F_des, F, I" in str(info.value)


def test_non_numeric_names_line_and_column(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    # line 1 comment, 2 header, 3-4 data, 5 the bad one
    path.write_text("# c\nt,x,v,F_des,F,I\n0,0,0,0,0,0\n0.001,0,0,0,0,0\n0.002,0,0,0,oops,0\n")
    with pytest.raises(ReportError, match=r"line 5\b.*column F\b.*'oops'"):
        load_run(path)


def test_infinite_rejected_nan_is_no_value(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("t,x,v,F_des,F,I\n0,0,0,0,0,0\n0.001,0,inf,0,0,0\n")
    with pytest.raises(ReportError, match=r"line 3\b.*column v\b"):
        load_run(path)
    path.write_text("t,x,v,F_des,F,I\n0,0,0,0,0,0\nnan,0,0,0,0,0\n")
    with pytest.raises(ReportError, match=r"line 3\b.*column t\b"):
        load_run(path)
    # a daemon log while the supervisor held the damper at 0 A, no load cell
    path.write_text("t,x,v,F_des,F,I\n0,0,0,0,nan,0\n0.001,nan,nan,nan,nan,0\n0.002,0,1,2,nan,0.1\n")
    cols = load_run(path)
    assert np.isnan(cols["x"][1]) and np.isnan(cols["F"]).all()
    assert math.isnan(summarize(cols)["nrmse"])  # no measured force: no tracking figure


def test_ragged_row_names_line(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("t,x,v,F_des,F,I\n0,0,0,0,0,0\n0.001,0,0\n")
    with pytest.raises(ReportError, match=r"line 3\b"):
        load_run(path)


def test_non_numeric_extra_column_is_ignored(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("t,fault,x,v,F_des,F,I\n0,none,0,0,0,0,0\n0.001,OVERCURRENT,0,0,1,1,0.1\n")
    loaded = load_run(path)
    np.testing.assert_array_equal(loaded["F"], [0.0, 1.0])


@pytest.mark.parametrize("n_rows", [0, 1])
def test_too_few_rows(tmp_path: Path, n_rows: int) -> None:
    path = tmp_path / "run.csv"
    path.write_text("t,x,v,F_des,F,I\n" + "0,0,0,0,0,0\n" * n_rows)
    with pytest.raises(ReportError, match="at least 2"):
        load_run(path)


def test_a_non_numeric_extra_column_leaves_the_others_read(tmp_path: Path) -> None:
    """The tick index still shades the skipped deadlines when the fault column is not numeric."""
    cols = synthetic(duration=2.0)
    n = len(cols["t"])
    cols["k"] = np.arange(n, dtype=float) + 5.0 * (np.arange(n) >= 1000)  # 5 ticks skipped at t = 1 s
    path = write_csv(tmp_path / "run.csv", cols)
    text = path.read_text().splitlines()
    text = [text[0] + ",fault"] + [line + ",none" for line in text[1:]]
    path.write_text("\n".join(text) + "\n")
    (m,) = make_report(path, tmp_path / "fig.png")
    assert len(m["skipped_spans"]) == 1 and m["skipped_spans"][0][0] == pytest.approx(0.999, abs=2e-3)
    assert m["fault_spans"] == []
