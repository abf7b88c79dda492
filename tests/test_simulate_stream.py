"""mrctl simulate in blocks: the same run whatever the block size, the same CSV
as the whole-run writer it replaced, memory that does not grow with the
duration, a disk that cannot hold the log refused before the run, a disk
that fails during it reported (exit 4), and --no-log."""

from __future__ import annotations

import io
import json
import math
import os
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from mrctl.cli import main
from mrctl.config import load_experiment
from mrctl.experiment import build
from mrctl.offline import logstream
from mrctl.offline.simulate import CSV_COLUMNS, SIM_COLUMNS, log_columns, simulate, simulate_blocks
from mrctl.offline.simulate_log import simulate_logged
from mrctl.runlog.format import RUN_FORMATS

ROOT = Path(__file__).resolve().parents[1]
EXP = ROOT / "config" / "experiments"
#: summary figures that are sums of squares: equal within rounding across block sizes
SUMS = ("force_rmse_N", "force_nrmse", "rms_a_sprung_mps2", "rms_tyre_defl_m", "rms_stroke_m")


@pytest.fixture(autouse=True)
def _plugins_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent / "plugins"))


def _exp(name: str):
    return build(load_experiment(EXP / name))


def _savetxt_csv(res) -> bytes:
    """The run log as the whole-run writer wrote it before simulate streamed
    (np.savetxt of every column at once): the bytes it must still write."""
    cols = log_columns(res)
    extra = tuple(c for c in res.columns if c not in SIM_COLUMNS)
    names = CSV_COLUMNS + extra
    data = np.column_stack([np.asarray(cols[c] if c in cols else res.columns[c], float) for c in names])
    text = io.StringIO()
    text.write(",".join(names) + "\n")
    np.savetxt(text, data, delimiter=",", fmt=[RUN_FORMATS.get(c, "%.9g") for c in names])
    return text.getvalue().encode("ascii")


def _law_fault_config(tmp_path: Path) -> Path:
    """fig5_robust with a law that returns NaN at tick 2500 (tests/plugins/bad_laws.py)."""
    lines = (EXP / "fig5_robust.yaml").read_text().splitlines()
    start = lines.index("inverse:")
    end = start + 1
    while lines[end].startswith("  "):
        end += 1
    lines[start:end] = ["inverse: {law: 'bad_laws:ReturnsNaN', after_ticks: 2500}"]
    p = tmp_path / "fault.yaml"
    p.write_text("\n".join(lines) + "\n")
    return p


@pytest.mark.parametrize("name, duration", [("fig5_robust.yaml", 3.0), ("quarter_car.yaml", 2.0),
                                            ("robust/mismatch_lag_noise_observer_c500.yaml", 2.0)])
def test_any_block_size_is_the_same_run(name, duration):
    whole = simulate(_exp(name), duration)
    for size in (1, 7, 1000):
        cut = simulate(_exp(name), duration, block_ticks=size)
        assert cut.columns.keys() == whole.columns.keys()
        for c, v in whole.columns.items():
            assert np.array_equal(v, cut.columns[c], equal_nan=True), (size, c)
        for key, value in whole.summary.items():
            if key in SUMS:
                assert cut.summary[key] == pytest.approx(value, rel=1e-13), (size, key)
            elif key not in ("wall_s", "realtime_factor"):
                assert cut.summary[key] == value or (math.isnan(value) and math.isnan(cut.summary[key])), key
        assert cut.row_figures == whole.row_figures


def test_a_law_fault_ends_the_run_at_its_tick_in_any_block(tmp_path):
    cfg = _law_fault_config(tmp_path)
    whole = simulate(build(load_experiment(cfg)), 4.0)
    cut = simulate(build(load_experiment(cfg)), 4.0, block_ticks=999)
    assert whole.fault is not None and cut.fault is not None and str(whole.fault) == str(cut.fault)
    assert whole.ticks == cut.ticks == 2501 and cut.columns["I"][-1] == 0.0
    for c, v in whole.columns.items():
        assert np.array_equal(v, cut.columns[c], equal_nan=True), c


@pytest.mark.parametrize("name, duration", [("fig5_robust.yaml", 4.0), ("quarter_car.yaml", 3.0),
                                            ("fig5_paper.yaml", 4.0),
                                            ("robust/bouc_wen_displacement_only_c500.yaml", 3.0)])
def test_the_streamed_csv_is_the_whole_run_writers_byte_for_byte(tmp_path, name, duration):
    want = _savetxt_csv(simulate(_exp(name), duration))
    for size in (1500, 16384):
        out = tmp_path / f"b{size}.csv"
        res, _, code = simulate_logged(_exp(name), duration, str(out), None, block_ticks=size)
        assert code == 0 and out.read_bytes() == want, size
        side = json.loads(out.with_suffix(".json").read_text())
        assert side["complete"] is True and side["rows_written"] == res.ticks == want.count(b"\n") - 1


def test_a_law_fault_is_logged_up_to_its_tick(tmp_path):
    cfg = _law_fault_config(tmp_path)
    want = _savetxt_csv(simulate(build(load_experiment(cfg)), 4.0))
    out = tmp_path / "f.csv"
    res, _, code = simulate_logged(build(load_experiment(cfg)), 4.0, str(out), None, block_ticks=1000)
    assert code == 1 and out.read_bytes() == want


def test_memory_does_not_grow_with_the_duration():
    """The blocks are dropped: ten times the duration takes no more memory
    (before streaming every column of the run was kept, ~150 B a tick)."""
    def peak(duration: float) -> int:
        exp = _exp("fig5_robust.yaml")
        tracemalloc.start()
        simulate_blocks(exp, duration, lambda k0, block: None, block_ticks=500)
        _, top = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        return top

    short, long = peak(2.0), peak(20.0)
    assert long < 1.2 * short + 200_000, (short, long)


def test_a_disk_too_small_for_the_log_is_refused_before_the_run(tmp_path, monkeypatch, capsys):
    real = logstream.shutil.disk_usage
    free = {"bytes": 10_000_000}
    monkeypatch.setattr(logstream.shutil, "disk_usage", lambda p: real(p)._replace(free=free["bytes"]))
    out = tmp_path / "big.csv"
    blocks: list[int] = []

    def spied(exp, duration, on_block, **kw):  # the blocks the log is given
        return simulate_blocks(exp, duration, lambda k0, b: (blocks.append(k0), on_block(k0, b)), **kw)

    monkeypatch.setattr("mrctl.offline.simulate_log.simulate_blocks", spied)
    assert main(["simulate", str(EXP / "fig5_robust.yaml"), "--duration", "200", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "does not fit" in err and "not started" in err and "MiB" in err and "Traceback" not in err
    assert not out.exists() and not out.with_suffix(".json").exists()
    assert blocks == [0]  # refused at the first block, before the loop went on


def test_the_estimate_is_close_to_the_log_written(tmp_path):
    seen = []
    out = tmp_path / "e.csv"
    simulate_logged(_exp("fig5_robust.yaml"), 30.0, str(out), None, on_estimate=seen.append, block_ticks=2000)
    (est,) = seen
    size = out.stat().st_size
    assert est.rows == 30001 and abs(est.total_bytes - size) < 0.02 * size, (est, size)
    assert est.free_bytes > 0 and "rows of" in est.text()


def test_a_disk_that_fails_during_the_run_ends_it_with_exit_4_and_says_what_was_written(tmp_path):
    """The file size limit stands in for a full disk (EFBIG where ENOSPC would
    be): the first block fits, a later one does not, in the writer thread."""
    out = tmp_path / "full.csv"
    code = ("import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            "resource.setrlimit(resource.RLIMIT_FSIZE, (3_000_000, 3_000_000)); "
            "from mrctl.cli import main; sys.exit(main(sys.argv[1:]))")
    res = subprocess.run([sys.executable, "-c", code, "simulate", str(EXP / "fig5_robust.yaml"), "--duration", "100",
                          "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 4, res.stderr
    assert "cannot write the run log" in res.stderr and "Traceback" not in res.stderr
    side = json.loads(out.with_suffix(".json").read_text())
    lines = out.read_bytes().count(b"\n")
    assert side["complete"] is False and side["exit_code"] == 4 and "File too large" in side["error"]
    assert 0 < side["rows_written"] == lines - 1 < 100001


def test_no_log_keeps_only_the_figures(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", str(EXP / "fig5.yaml"), "--no-log", "--duration", "2"]) == 0
    out = capsys.readouterr().out
    assert "force NRMSE" in out and "wrote" not in out and not list(tmp_path.iterdir())
    assert main(["simulate", str(EXP / "fig5.yaml"), "--no-log", "--out", "x.csv"]) == 2
    assert "--no-log" in capsys.readouterr().err and not list(tmp_path.iterdir())


def test_the_figures_printed_are_simulates_whatever_the_log(tmp_path, capsys):
    assert main(["simulate", str(EXP / "fig5_robust.yaml"), "--duration", "20", "--no-log"]) == 0
    a = capsys.readouterr().out.splitlines()[1:4]
    assert main(["simulate", str(EXP / "fig5_robust.yaml"), "--duration", "20", "--out",
                 str(tmp_path / "r.csv")]) == 0
    b = capsys.readouterr().out.splitlines()[1:4]
    res = simulate(_exp("fig5_robust.yaml"), 20.0)
    assert a == b and f"{100 * res.summary['force_nrmse']:.3f} %" in a[0]
    assert os.path.getsize(tmp_path / "r.csv") > 20000 * 100
