"""Recorder: lossless round trip, sidecar, overflow, writer errors, SIGKILL.

Deterministic: stalls and failures are injected through ``opener``; no test
asserts a wall-clock latency (the machine is shared and noisy).
"""

from __future__ import annotations

import errno
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mrctl.daemon.recorder import CORE_COLUMNS, Recorder, read_run, read_sidecar, sidecar_path

ROOT = Path(__file__).resolve().parents[1]
EXTRA = ("seq", "t_wall_s", "late_us", "compute_us", "I_applied", "fault")
COLS = CORE_COLUMNS + EXTRA


def row(k: int) -> tuple[float, ...]:
    """A tick's row with awkward values: long mantissas, negatives, big ints."""
    t = k * 1e-3
    return (t, 0.01 * math.sin(7.1 * t), -0.0713 * math.cos(7.1 * t) / 3.0, 1234.5678901234567 * math.sin(t),
            -987.654321 + k / 7.0, 0.1 * (k % 11), float(k), 1.7e9 + t + 1e-7, float(k % 13) - 0.25,
            12.5 / (k + 1), 2.0 ** -30 * k, float(k % 2))


def wait_until(pred, timeout=10.0) -> None:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise AssertionError("condition not reached within timeout")
        time.sleep(0.002)


class GatedFile:
    """Real file whose writes wait while ``gate`` is clear (a stalled disk)."""

    def __init__(self, path: Path) -> None:
        self.fh = open(path, "wb", buffering=0)
        self.gate = threading.Event()
        self.gate.set()
        self.entered = threading.Event()  # a write is waiting at the gate

    def write(self, data):
        if not self.gate.is_set():
            self.entered.set()
            self.gate.wait()
        return self.fh.write(data)

    def fileno(self):
        return self.fh.fileno()

    def close(self):
        self.fh.close()


class FailingFile:
    """Real file that writes ``ok_writes`` calls, then half of one, then ENOSPC."""

    def __init__(self, path: Path, ok_writes: int) -> None:
        self.fh = open(path, "wb", buffering=0)
        self.left = ok_writes
        self.torn = False

    def write(self, data):
        if self.left > 0:
            self.left -= 1
            return self.fh.write(data)
        if not self.torn:  # short write: only part of the block reaches the disk
            self.torn = True
            return self.fh.write(bytes(data)[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    def fileno(self):
        return self.fh.fileno()

    def close(self):
        self.fh.close()


# -- round trip ---------------------------------------------------------------
def test_rows_round_trip_exactly_in_order_over_blocks_and_partial_block(tmp_path):
    path = tmp_path / "run.csv"
    n = 10 * 64 + 37  # ten full blocks and a partial one
    rows = [row(k) for k in range(n)]
    # capacity for the whole run: a tight loop may outrun the writer (no overflow here)
    with Recorder(path, COLS, {"who": "test"}, capacity_ticks=704, block_ticks=64) as rec:
        assert rec.block_ticks == 64 and rec.capacity_ticks == 704
        for r in rows:
            rec.record(*r)
        st = rec.close(summary={"nrmse": 0.0123})
    assert st["error"] is None and st["dropped_rows"] == 0
    assert st["ticks"] == n and st["rows_written"] == n

    header = path.read_text().splitlines()[0].split(",")
    assert tuple(header[:6]) == ("t", "x", "v", "F_des", "F", "I")
    assert tuple(header) == COLS
    data = read_run(path)
    assert list(data) == list(COLS)
    got = np.column_stack([data[c] for c in COLS])
    want = np.array(rows)
    assert got.shape == want.shape
    assert np.array_equal(got, want)  # '%r' is exact, not just close
    # the report loader reads the same file (core columns by name)
    from mrctl.offline.report import load_run
    core = load_run(path)
    assert np.array_equal(core["F_des"], want[:, 3])


def test_core_columns_match_simulator_and_report():
    from mrctl.offline.report import REQUIRED_COLUMNS
    from mrctl.offline.simulate import CSV_COLUMNS
    assert CORE_COLUMNS == ("t", "x", "v", "F_des", "F", "I")
    assert CSV_COLUMNS[:6] == CORE_COLUMNS == REQUIRED_COLUMNS


def test_custom_format_rounds_to_its_precision(tmp_path):
    path = tmp_path / "r.csv"
    fmt = {c: "%.9g" for c in CORE_COLUMNS} | {"seq": "%d"}
    rows = [row(k) for k in range(300)]
    with Recorder(path, COLS, {}, fmt=fmt) as rec:
        for r in rows:
            rec.record(*r)
    data = read_run(path)
    want = np.array(rows)
    for j, c in enumerate(COLS):
        if c in CORE_COLUMNS:
            np.testing.assert_allclose(data[c], want[:, j], rtol=1e-8, atol=0)
        else:
            assert np.array_equal(data[c], want[:, j]), c
    assert path.read_text().splitlines()[2].split(",")[6] == "1"  # seq as an integer


def test_sidecar_incomplete_during_run_complete_after_close(tmp_path):
    path = tmp_path / "bench_run.csv"
    meta = {"config": {"rate_hz": 1000, "law": "smooth"}, "versions": {"mrctl": "0.1.0"},
            "rt": ["sched_fifo: refused"], "np": np.float64(1.5), "path": tmp_path}
    rec = Recorder(path, COLS, meta, capacity_ticks=128, block_ticks=16)
    assert sidecar_path(path) == tmp_path / "bench_run.json" == rec.sidecar
    side = read_sidecar(path)
    assert side["complete"] is False
    assert side["meta"]["config"] == {"rate_hz": 1000, "law": "smooth"}
    assert side["meta"]["np"] == 1.5 and side["meta"]["path"] == str(tmp_path)
    assert side["columns"] == list(COLS)
    for k in range(100):
        rec.record(*row(k))
    assert read_sidecar(path)["complete"] is False
    st = rec.close(summary={"nrmse": float("nan"), "max_dI": 0.25})
    side = json.loads((tmp_path / "bench_run.json").read_text())  # strict JSON
    assert side["complete"] is True
    assert side["rows_written"] == 100 and side["ticks"] == 100
    assert side["overflow_rows"] == 0 and side["dropped_rows"] == 0 and side["error"] is None
    assert side["summary"] == {"nrmse": "nan", "max_dI": 0.25}
    assert side["meta"]["versions"] == {"mrctl": "0.1.0"}
    assert st["complete"] is True and st["sidecar_error"] is None
    # idempotent
    assert rec.close() == st and rec.stats() == st
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_partial_block_reaches_disk_within_flush_interval(tmp_path):
    """Blocks never span more than rate × flush_interval ticks."""
    path = tmp_path / "r.csv"
    rec = Recorder(path, COLS, {}, rate_hz=100.0, flush_interval_s=0.2, block_ticks=1000)
    assert rec.block_ticks == 20  # 100 Hz × 0.2 s
    for k in range(45):
        rec.record(*row(k))
    wait_until(lambda: rec.stats()["rows_written"] == 40)  # two full 20-tick blocks
    assert len(read_run(path)["t"]) == 40
    rec.flush()  # the 5-row partial block, on demand
    wait_until(lambda: rec.stats()["rows_written"] == 45)
    wait_until(lambda: rec.stats()["fsyncs"] >= 1)
    rec.close()
    assert np.array_equal(read_run(path)["seq"], np.arange(45.0))


# -- overflow -----------------------------------------------------------------
def test_stalled_writer_never_blocks_record_and_counts_overflow_exactly(tmp_path):
    path = tmp_path / "r.csv"
    files: list[GatedFile] = []

    def opener(p):
        files.append(GatedFile(p))
        return files[-1]

    rec = Recorder(path, COLS, {}, capacity_ticks=100, block_ticks=10, opener=opener)
    gf = files[0]
    gf.gate.clear()  # the disk stalls after the header
    n = 5000
    done = threading.Event()

    def loop():
        for k in range(n):
            rec.record(*row(k))
        done.set()

    th = threading.Thread(target=loop)
    th.start()
    th.join(20.0)
    assert done.is_set(), "record() blocked on a stalled writer"
    wait_until(gf.entered.is_set)  # the writer really is stuck inside write()
    st = rec.stats()
    assert st["ticks"] == n
    assert st["overflow_rows"] == n - 100  # exactly what 10 blocks × 10 rows could not hold
    assert st["overflow_first_tick"] == 100 and st["overflow_last_tick"] == n - 1
    assert st["rows_written"] == 0 and st["blocks_free"] == 0

    gf.gate.set()  # disk recovers: recording resumes once blocks come back
    wait_until(lambda: rec.stats()["blocks_free"] >= 9)
    for k in range(n, n + 25):
        rec.record(*row(k))
    st = rec.close(summary={})
    assert st["overflow_rows"] == n - 100 and st["dropped_rows"] == n - 100
    assert st["rows_written"] == 125 and st["error"] is None
    seq = read_run(path)["seq"]
    assert np.array_equal(seq, np.r_[np.arange(100.0), np.arange(n, n + 25.0)])
    side = read_sidecar(path)
    assert side["complete"] is True and side["overflow_rows"] == n - 100
    assert (side["overflow_first_tick"], side["overflow_last_tick"]) == (100, n - 1)


# -- writer errors --------------------------------------------------------------
def test_writer_error_is_reported_and_record_keeps_returning(tmp_path):
    path = tmp_path / "r.csv"
    # header write + 3 block writes succeed, the 4th is torn, then ENOSPC
    rec = Recorder(path, COLS, {}, capacity_ticks=40, block_ticks=10,
                   opener=lambda p: FailingFile(p, ok_writes=4))
    n = 3000
    for k in range(n):
        rec.record(*row(k))
        if k % 50 == 0:
            time.sleep(0)  # let the writer run now and then
    wait_until(lambda: rec.error is not None)
    for k in range(n, n + 500):  # still returns after the error
        rec.record(*row(k))
    st = rec.close(summary={"x": 1})
    assert "OSError" in st["error"] and "No space left" in st["error"] and str(path) in st["error"]
    assert st["ticks"] == n + 500
    data = read_run(path)  # the torn half-line is dropped
    written = len(data["seq"])
    assert 30 <= written < 40  # 3 whole blocks + the complete lines of the torn one
    assert np.array_equal(data["seq"], np.arange(float(written)))
    assert st["rows_written"] == written
    assert st["lost_first_tick"] == written
    assert st["overflow_rows"] + st["lost_rows"] == st["dropped_rows"] == n + 500 - written
    assert not rec.ok
    side = read_sidecar(path)
    assert side["complete"] is True and side["error"] == st["error"]
    assert side["rows_written"] == written and side["dropped_rows"] == n + 500 - written


def test_unwritable_file_fails_at_construction(tmp_path):
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    with pytest.raises(OSError):
        Recorder(tmp_path / "r.csv", COLS, {}, opener=lambda p: open("/dev/full", "wb", buffering=0))
    with pytest.raises(ValueError, match="start with"):
        Recorder(tmp_path / "r.csv", ("x", "t"), {})
    with pytest.raises(ValueError, match="duplicate"):
        Recorder(tmp_path / "r.csv", COLS + ("t",), {})
    with pytest.raises(ValueError, match="sidecar"):
        Recorder(tmp_path / "r.json", COLS, {})


def test_wrong_row_length_is_a_caller_bug(tmp_path):
    with Recorder(tmp_path / "r.csv", COLS, {}) as rec:
        with pytest.raises(Exception):
            rec.record(1.0, 2.0)
        rec.record(*row(0))
    assert rec.stats()["rows_written"] == 1
    rec.record(*row(1))  # after close: ignored, counted
    assert rec.stats()["rows_written"] == 1


# -- read_run -----------------------------------------------------------------
def test_read_run_drops_only_a_torn_last_line(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text("# comment\nt,x\n0,1\n0.001,2\n0.002,3")
    d = read_run(p)
    assert list(d) == ["t", "x"] and np.array_equal(d["x"], [1.0, 2.0])
    p.write_text("t,x\n0,1\n0.0")
    assert np.array_equal(read_run(p)["t"], [0.0])
    p.write_text("t,x\n")
    assert read_run(p)["t"].shape == (0,)
    p.write_text("t,x\n0,1\n0.001\n0.002,3\n")
    with pytest.raises(ValueError, match="line 3"):
        read_run(p)


# -- SIGKILL ------------------------------------------------------------------
CHILD = textwrap.dedent(
    """
    import math, sys, time
    from mrctl.daemon.recorder import Recorder
    cols = ("t", "x", "v", "F_des", "F", "I", "seq", "t_wall_s", "late_us", "compute_us",
            "I_applied", "fault")
    rec = Recorder(sys.argv[1], cols, {"child": True}, rate_hz=1000.0, flush_interval_s=1.0)
    period = 1e-3
    t0 = time.monotonic()
    k = 0
    while True:
        deadline = t0 + k * period
        now = time.monotonic()
        if deadline > now:
            time.sleep(deadline - now)
        t = k * period
        rec.record(t, math.sin(t), math.cos(t), 2.0 * t, 2.0 * t + 0.1, 0.5, float(k),
                   time.time(), 1.0, 2.0, 0.5, 0.0)
        k += 1
        if k % 100 == 0:
            sys.stdout.write(f"{k}\\n")
            sys.stdout.flush()
    """
)


def test_sigkill_leaves_valid_csv_missing_at_most_about_one_second(tmp_path):
    path = tmp_path / "killed.csv"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE,
                            env=env, text=True)
    reported = 0
    try:
        deadline = time.monotonic() + 20.0
        for line in proc.stdout:  # ~2.5 s of ticks at 1 kHz
            reported = int(line)
            if reported >= 2500 or time.monotonic() > deadline:
                break
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        rest = proc.stdout.read()
        proc.wait(10)
        proc.stdout.close()
    for line in rest.split():
        reported = max(reported, int(line))
    assert proc.returncode == -signal.SIGKILL
    assert reported >= 2500

    raw = path.read_bytes()
    lines = raw.split(b"\n")
    assert lines[0] == b",".join(c.encode() for c in COLS)
    ncol = len(COLS)
    body = lines[1:-1]  # all newline-terminated data lines must be complete
    assert all(len(line.split(b",")) == ncol for line in body)
    data = read_run(path)
    seq = data["seq"]
    assert len(seq) == len(body)
    assert np.array_equal(seq, np.arange(float(len(seq))))  # from tick 0, no gap
    assert np.array_equal(data["t"], seq * 1e-3)
    lost = reported - len(seq)  # the child ran ≥ `reported` ticks
    print(f"SIGKILL: {reported} ticks reported, {len(seq)} rows on disk, lost {lost}")
    assert lost <= 1000 + 300, f"lost {lost} ticks of {reported}"
    side = read_sidecar(path)
    assert side["complete"] is False and side["meta"] == {"child": True}


# -- formatting in the loop's idle time (defer_format) --------------------------
def test_deferred_format_writes_the_same_file_as_the_writer_thread(tmp_path):
    """Blocks formatted by format_pending (chunks and a tail of < 8 rows) give
    byte-for-byte the CSV the writer thread gives."""
    n = 5 * 64 + 13
    rows = [row(k) for k in range(n)]
    fmt = {c: "%.9g" for c in COLS}
    with Recorder(tmp_path / "thread.csv", COLS, capacity_ticks=1024, block_ticks=64, fmt=fmt) as rec:
        for r in rows:
            rec.record(*r)
    with Recorder(tmp_path / "loop.csv", COLS, capacity_ticks=1024, block_ticks=64, fmt=fmt,
                  defer_format=True) as rec:
        for k, r in enumerate(rows):
            rec.record(*r)
            rec.format_pending(time.monotonic_ns() + 10**9)  # plenty of idle time
            if k == 64:  # block 0 was handed over and formatted here, not by the thread
                assert not rec._pending
        st = rec.close()
    assert st["rows_written"] == n and st["dropped_rows"] == 0
    assert (tmp_path / "loop.csv").read_bytes() == (tmp_path / "thread.csv").read_bytes()


def test_deferred_format_stops_at_the_deadline_and_resumes(tmp_path):
    """format_pending does one chunk per clock check: with a fake clock that
    runs out after 3 checks it formats 2 chunks and leaves the rest."""
    rec = Recorder(tmp_path / "run.csv", COLS, capacity_ticks=256, block_ticks=64, defer_format=True)
    for k in range(65):  # one full block handed over by the 65th row
        rec.record(*row(k))
    assert len(rec._pending) == 1
    ticks = iter([0, 0, 5])
    rec.format_pending(5, clock=lambda: next(ticks))
    assert rec._pending[0][3] == 16  # two chunks of 8 rows done, block still waiting
    rec.format_pending(time.monotonic_ns() + 10**9)
    assert not rec._pending
    st = rec.close()
    assert st["rows_written"] == 65
    assert np.array_equal(read_run(tmp_path / "run.csv")["t"], np.array([row(k)[0] for k in range(65)]))


def test_the_run_logs_formats_take_the_run_logs_formatter_in_the_loop_and_the_thread(tmp_path):
    """With the run log's formats (RUN_FORMATS) the recorder formats with the
    run log's one formatter (compiled: C, 32 rows a chunk; interpreted: '%',
    8): the loop's idle time and the writer thread write the bytes '%' writes."""
    from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS
    from mrctl.runlog.rowtext import RowFormatter

    rng = np.random.default_rng(3)
    n = 3 * 64 + 29
    rows = [tuple(float(v) for v in rng.normal(0.0, 10.0 ** rng.integers(-5, 4), len(RUN_COLUMNS))) for _ in range(n)]
    rows[5] = (math.nan, -0.0, math.inf, 1e-320, 1234567885.0, *rows[5][5:])
    want = (",".join(RUN_COLUMNS) + "\n" + "".join(
        ",".join(RUN_FORMATS[c] % v for c, v in zip(RUN_COLUMNS, r)) + "\n" for r in rows)).encode()
    for defer in (False, True):
        path = tmp_path / f"d{defer}.csv"
        with Recorder(path, RUN_COLUMNS, capacity_ticks=1024, block_ticks=64, fmt=RUN_FORMATS,
                      defer_format=defer) as rec:
            for r in rows:
                rec.record(*r)
                rec.format_pending(time.monotonic_ns() + 10**9)
        assert path.read_bytes() == want, defer
    rec = Recorder(tmp_path / "c.csv", RUN_COLUMNS, capacity_ticks=256, block_ticks=100, fmt=RUN_FORMATS,
                   defer_format=True)
    for r in rows[:101]:
        rec.record(*r)
    ticks = iter([0, 0, 5])
    rec.format_pending(5, clock=lambda: next(ticks))  # two chunks, then out of time
    assert rec._pending[0][3] == (64 if RowFormatter(RUN_COLUMNS, RUN_FORMATS).compiled else 16)
    rec.close()


def test_deferred_format_without_idle_time_falls_back_to_the_thread_in_order(tmp_path):
    """A loop that never calls format_pending loses nothing: the second full
    block sends every waiting block to the writer thread, oldest first."""
    n = 6 * 32 + 5
    rows = [row(k) for k in range(n)]
    with Recorder(tmp_path / "run.csv", COLS, capacity_ticks=4096, block_ticks=32, defer_format=True) as rec:
        for r in rows:
            rec.record(*r)
            assert len(rec._pending) <= 1
        st = rec.close()
    assert st["rows_written"] == n and st["dropped_rows"] == 0
    got = read_run(tmp_path / "run.csv")
    assert np.array_equal(np.column_stack([got[c] for c in COLS]), np.array(rows))
