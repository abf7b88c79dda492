"""mrctl sweep against what a careless user, a hostile one and a faulty environment do.

One table, one sweep (locked); one row per point whatever ran twice; an
output that is not a regular file, a table that is not this sweep's or not
mrctl's, refused before any point runs; a scheduler that is mute or not
Dask at all, a link failure within a bound; a sweep at its cap that starts
at once and is checked without being built; workers that die with it.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import pytest
import yaml

from hil_sim.testing.peers import ReplyingServer
from mrctl.cli import main
from mrctl.config import load_yaml
from mrctl.errors import LinkFailure
from mrctl.sweep import runner
from mrctl.sweep.runner import SweepInterrupted, probe_scheduler, run_sweep
from mrctl.sweep.spec import MAX_POINTS, load_sweep
from mrctl.sweep.table import ResultsTable, columns

ROOT = Path(__file__).resolve().parents[1]
EXP = ROOT / "config" / "experiments"


@pytest.fixture
def sweep_file(tmp_path: Path) -> Path:
    data = load_yaml(EXP / "fig5_robust.yaml")
    data["duration_s"] = 0.2
    (tmp_path / "base.yaml").write_text(yaml.safe_dump(data))
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump({"base": "base.yaml", "grid": {"demand.c_des": [250, 500, 750]}}))
    return p


def _table(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _no_point(monkeypatch) -> None:
    def boom(task):
        raise AssertionError("a point ran")

    monkeypatch.setattr(runner, "run_point", boom)
    monkeypatch.setattr(runner, "run_points", lambda tasks: [boom(t) for t in tasks])


# -- item 2: one sweep per table; one row per point ------------------------------------------
def test_a_second_sweep_on_a_table_in_use_is_refused_naming_the_first(sweep_file, capsys):
    out = sweep_file.parent / "r.csv"
    s = load_sweep(sweep_file)
    held = ResultsTable(out, columns(s.axes, s.metrics))
    held.open()  # another sweep, mid-run
    try:
        assert main(["sweep", str(sweep_file), "--out", str(out), "--no-progress"]) == 3
        err = capsys.readouterr().err
        assert f"in use by another mrctl sweep (pid {os.getpid()})" in err and "refusing" in err
    finally:
        held.close(False)
    assert main(["sweep", str(sweep_file), "--out", str(out), "--no-progress", "--workers", "1"]) == 0
    assert [r["point"] for r in _table(out)] == ["0", "1", "2"]


def test_a_resume_keeps_one_row_per_point(sweep_file):
    out = sweep_file.parent / "r.csv"
    assert run_sweep(load_sweep(sweep_file), out, workers=1, progress=False)["ok"] == 3
    lines = out.read_text().splitlines()
    with open(out, "a") as fh:  # what two sweeps on one table left: every point twice, one three times
        fh.write("\n".join(lines[1:] + lines[2:3]) + "\n")
    assert len(_table(out)) == 7
    sweep_file.write_text(yaml.safe_dump({"base": "base.yaml", "grid": {"demand.c_des": [250, 500, 750, 1000]}}))
    counts = run_sweep(load_sweep(sweep_file), out, workers=1, progress=False)
    assert counts["skipped"] == 3 and counts["ok"] == 1
    rows = _table(out)
    assert [r["point"] for r in rows] == ["0", "1", "2", "3"] and len({r["config_hash"] for r in rows}) == 4


# -- items 3 and 8: outputs that are not regular files, refused before anything is read --------
@pytest.mark.parametrize("kind", ["fifo", "dev-null", "directory", "symlink"])
def test_an_out_that_is_not_a_regular_file_is_refused_before_any_point(sweep_file, kind):
    d = sweep_file.parent
    out = {"fifo": d / "r.csv", "dev-null": Path("/dev/null"), "directory": d / "r.csv", "symlink": d / "r.csv"}[kind]
    if kind == "fifo":
        os.mkfifo(out)
    elif kind == "directory":
        out.mkdir()
    elif kind == "symlink":
        (d / "elsewhere.csv").write_text("keep\n")
        out.symlink_to(d / "elsewhere.csv")
    # a child: a FIFO once blocked the journal's read for ever
    r = subprocess.run([sys.executable, "-m", "mrctl", "sweep", str(sweep_file), "--out", str(out), "--no-progress"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert ("not a regular file" in r.stderr or "symlink" in r.stderr) and "Traceback" not in r.stderr
    assert not (d / "r.csv.partial.csv").exists()
    if kind == "symlink":
        assert (d / "elsewhere.csv").read_text() == "keep\n"


def test_a_base_that_is_a_fifo_or_a_device_is_not_a_regular_file(tmp_path, capsys):
    os.mkfifo(tmp_path / "fifo.yaml")
    for base, extra in (("fifo.yaml", []), ("/dev/zero", ["--allow-outside-paths"])):
        (tmp_path / "s.yaml").write_text(f"base: {base}\n")
        assert main(["check", str(tmp_path / "s.yaml"), *extra]) == 2
        err = capsys.readouterr().err
        assert "not a regular file" in err and "no such file" not in err


# -- item 7: tables that are not this sweep's, or not mrctl's ---------------------------------
def test_a_hand_edited_csv_table_is_refused_naming_the_line(sweep_file, monkeypatch, capsys):
    out = sweep_file.parent / "r.csv"
    assert run_sweep(load_sweep(sweep_file), out, workers=1, progress=False)["ok"] == 3
    good = out.read_bytes()
    _no_point(monkeypatch)
    lines = good.decode().splitlines(keepends=True)
    for edited, needle in (("".join(lines[:2] + ["x" + lines[2]] + lines[3:]), "line 3: point is not a whole number"),
                           ("".join(lines[:3]) + "7,abc\n" + lines[3], "line 4: 2 cells"),
                           (good.decode() + "\udcff", None)):
        data = edited.encode("utf-8", "surrogateescape") if needle else good + b"3,\xff\xfe,bad\n"
        out.write_bytes(data)
        assert main(["sweep", str(sweep_file), "--out", str(out), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert (needle or "line 5: not UTF-8 text") in err and "Traceback" not in err
        assert out.read_bytes() == data  # untouched


def test_a_corrupt_or_foreign_parquet_is_refused_before_any_journal(sweep_file, monkeypatch, capsys):
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = sweep_file.parent / "r.parquet"
    _no_point(monkeypatch)
    out.write_bytes(b"PAR1" + os.urandom(2000))
    assert main(["sweep", str(sweep_file), "--out", str(out), "--no-progress"]) == 2
    assert "not a readable Parquet file" in capsys.readouterr().err
    assert main(["report", str(out), "--out", str(sweep_file.parent / "f.png")]) == 2
    assert "not a readable Parquet file" in capsys.readouterr().err
    pq.write_table(pa.table({"a": [1, 2], "b": ["x", "y"]}), out)  # someone else's table
    assert main(["sweep", str(sweep_file), "--out", str(out), "--no-progress"]) == 2
    assert "another sweep's table" in capsys.readouterr().err
    assert sorted(p.name for p in sweep_file.parent.iterdir()) == ["base.yaml", "r.parquet", "s.yaml"]


# -- item 3, 7: a scheduler that is mute, or not a Dask scheduler ------------------------------
@pytest.mark.parametrize("reply, needle", [
    (None, "no answer within"),
    (bytes(range(256)) * 16, "not a Dask scheduler"),
    (b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n", "not a Dask scheduler"),
    ((3).to_bytes(8, "little") + (1 << 62).to_bytes(8, "little") + bytes(64), "not a Dask scheduler"),
], ids=["mute", "random-bytes", "http", "bad-frame"])
def test_a_scheduler_that_is_mute_or_not_dask_is_a_link_failure(reply, needle):
    import distributed  # noqa: F401 - a test dependency: missing, the test fails
    got: list[BaseException] = []
    with ReplyingServer(reply) as srv:
        t = threading.Thread(target=lambda: got.append(_raises(lambda: probe_scheduler(srv.address, timeout=1.0))),
                             daemon=True)
        t.start()
        t.join(60)
    assert not t.is_alive(), "the probe did not return"
    assert isinstance(got[0], LinkFailure) and needle in str(got[0]), got


def _raises(fn) -> BaseException | None:
    try:
        fn()
    except BaseException as exc:  # noqa: BLE001 - what it raised is the result
        return exc
    return None


def test_the_command_says_not_a_dask_scheduler_and_exits_3(sweep_file, monkeypatch, capsys):
    import distributed  # noqa: F401 - a test dependency: missing, the test fails
    _no_point(monkeypatch)
    out = sweep_file.parent / "r.csv"
    with ReplyingServer(os.urandom(4096)) as srv:
        assert main(["sweep", str(sweep_file), "--out", str(out), "--scheduler", srv.address]) == 3
    err = capsys.readouterr().err
    assert "not a Dask scheduler" in err and "internal error" not in err
    assert not out.exists()  # refused before the table was opened


# -- item 4: a sweep at its own cap ----------------------------------------------------------
def test_a_sweep_at_its_cap_starts_at_once_in_flat_memory_and_checks_without_building(sweep_file, monkeypatch, capsys):
    sweep_file.write_text(yaml.safe_dump({"base": "base.yaml", "grid": {"inverse.law": ["smooth", "closed"]},
                                          "random": {"n": MAX_POINTS // 2,
                                                     "plant.parameters.F0": {"factor_uniform": [0.8, 1.2]}}}))
    assert main(["check", str(sweep_file)]) == 0
    out = capsys.readouterr().out
    assert f"{MAX_POINTS} points" in out and out.rstrip().endswith("OK")
    s = load_sweep(sweep_file)
    assert s.size() == MAX_POINTS
    last = s.point(MAX_POINTS - 1)  # any point, from its index alone
    assert last.values["inverse.law"] == "closed" and last.seed == MAX_POINTS // 2 - 1
    calls = []

    def three(task):
        calls.append(task["index"])
        if len(calls) > 3:
            raise KeyboardInterrupt
        return {"point": task["index"], "config_hash": task["hash"], "status": "ok", "error": ""}

    monkeypatch.setattr(runner, "run_point", three)
    tracemalloc.start()
    try:
        with pytest.raises(SweepInterrupted):
            run_sweep(s, sweep_file.parent / "r.csv", workers=1, progress=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert calls == [0, 1, 2, 3] and len(_table(sweep_file.parent / "r.csv")) == 3
    assert peak < 20 * 2**20, f"{peak / 2**20:.1f} MiB for a sweep of {MAX_POINTS} points"


# -- item 8: workers die with the sweep -------------------------------------------------------
def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, ValueError, IndexError):
                pass
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_killed_sweep_leaves_no_worker_and_no_lock(sweep_file):
    data = load_yaml(sweep_file.parent / "base.yaml")
    data["duration_s"] = 1.0
    (sweep_file.parent / "base.yaml").write_text(yaml.safe_dump(data))
    sweep_file.write_text(yaml.safe_dump({"base": "base.yaml", "random": {"n": 400, "plant.parameters.F0":
                                                                          {"factor_uniform": [0.8, 1.2]}}}))
    out = sweep_file.parent / "r.csv"
    proc = subprocess.Popen([sys.executable, "-m", "mrctl", "sweep", str(sweep_file), "--out", str(out),
                             "--workers", "2", "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (not out.exists() or out.read_text().count("\n") < 3):
            time.sleep(0.05)
        workers = _children(proc.pid)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert len(workers) == 2
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and any(Path(f"/proc/{w}").exists() for w in workers):
        time.sleep(0.05)
    alive = [w for w in workers if Path(f"/proc/{w}").exists()
             and (Path(f"/proc/{w}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z")]
    assert not alive, f"workers {alive} outlived their sweep"
    # the table is free: the next sweep resumes it
    assert main(["sweep", str(sweep_file), "--out", str(out), "--no-progress", "--workers", "2"]) == 0
    assert [int(r["point"]) for r in _table(out)] == list(range(400))


@pytest.mark.parametrize("suffix", ["csv", "parquet"])
def test_a_table_larger_than_a_sort_chunk_is_merged_from_disk_in_point_order(tmp_path, monkeypatch, suffix):
    """The rewrite in point order never holds the table: chunks sorted, spilled, merged; duplicates dropped."""
    import random

    from mrctl.sweep import rows
    from mrctl.sweep.table import read_results

    monkeypatch.setattr(rows, "SORT_CHUNK", 700)
    cols = columns(["demand.c_des"], ["force_nrmse"])
    table = ResultsTable(tmp_path / f"r.{suffix}", cols)
    table.open()
    order = list(range(5000))
    random.Random(1).shuffle(order)
    for i in order + order[:300]:  # 300 points twice
        table.add({"point": i, "config_hash": f"h{i}", "demand.c_des": 100 + i, "force_nrmse": i / 1e4,
                   "status": "ok"})
    table.close(True)
    got_cols, got = read_results(tmp_path / f"r.{suffix}")
    assert got_cols == cols and [int(r["point"]) for r in got] == list(range(5000))
    assert got[4999]["demand.c_des"] == "5099" and float(got[7]["force_nrmse"]) == 7e-4
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"r.{suffix}"]  # no spill file left


def test_a_parquet_table_is_typed_by_the_first_row_per_point_and_written_in_point_order(tmp_path, monkeypatch):
    """Each column's type comes from the rows kept (a dropped duplicate does not widen it); rows in point order."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from mrctl.sweep import rows

    monkeypatch.setattr(rows, "SORT_CHUNK", 2)  # spilled and merged
    cols = columns(["demand.c_des", "observer.on"], ["force_nrmse"])
    table = ResultsTable(tmp_path / "r.parquet", cols)
    table.open()
    for i, c_des, on, nrmse in [(4, 140, True, 0.5), (2, 120, False, None), (0, 100, True, 1.5),
                                (3, 130, None, 2), (1, 110, False, 0.25)]:
        table.add({"point": i, "config_hash": f"h{i}", "demand.c_des": c_des, "observer.on": on, "seed": 7,
                   "force_nrmse": nrmse, "status": "ok"})
    table.add({"point": 2, "config_hash": "h2", "demand.c_des": "text", "observer.on": 3.5, "status": "ok"})
    table.close(True)
    got = pq.read_table(tmp_path / "r.parquet")
    assert got.schema == pa.schema([
        ("point", pa.int64()), ("config_hash", pa.string()), ("demand.c_des", pa.int64()),
        ("observer.on", pa.bool_()), ("seed", pa.int64()), ("force_nrmse", pa.float64()),
        ("status", pa.string()), ("error", pa.string()), ("wall_s", pa.float64()),
        ("mrctl_version", pa.string()), ("build", pa.string())])
    assert got.to_pydict() == {
        "point": [0, 1, 2, 3, 4], "config_hash": ["h0", "h1", "h2", "h3", "h4"],
        "demand.c_des": [100, 110, 120, 130, 140], "observer.on": [True, False, False, None, True],
        "seed": [7] * 5, "force_nrmse": [1.5, 0.25, None, 2.0, 0.5], "status": ["ok"] * 5, "error": [""] * 5,
        "wall_s": [None] * 5, "mrctl_version": [""] * 5, "build": [""] * 5}
