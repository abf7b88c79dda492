"""The live UDP stream (docs/observe.md): every row, in order, as PlotJuggler reads it; never waited for."""

from __future__ import annotations

import json
import math
import socket
import struct
import subprocess
import sys
import threading
import time
from array import array
from pathlib import Path

import pytest

from mrctl.config import ConfigError, load_experiment
from mrctl.daemon.recorder import Recorder
from mrctl.daemon.rowbus import RowBus
from mrctl.daemon.stream import UdpStream, json_row_format
from mrctl.errors import BadInput
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS
from mrctl.runlog.read import read_run, read_sidecar

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"


def _timing_open(d: Path) -> Path:
    """fig5 with the timing bounds opened: these runs are about rows, on a
    shared machine whose timing is a bench/ figure (docs/runlog.md: the verdict)."""
    p = d / "fig5.yaml"
    p.write_text(FIG5.read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    return p
COLS = ("t", "F_des", "F", "I", "k")
NEVER = 1 << 62


class Receiver:
    """A UDP socket on loopback collecting datagrams in a thread (or never reading)."""

    def __init__(self, read: bool = True, rcvbuf: int = 1 << 22) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.url = f"udp://127.0.0.1:{self.port}"
        self.got: list[bytes] = []
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True) if read else None
        if self._th:
            self._th.start()

    def _run(self) -> None:
        self.sock.settimeout(0.1)
        while not self._stop.is_set():
            try:
                self.got.append(self.sock.recv(65536))
            except socket.timeout:
                continue

    def close(self, linger_s: float = 0.5) -> list[dict]:
        time.sleep(linger_s)
        self._stop.set()
        if self._th:
            self._th.join(2)
        self.sock.close()
        return [json.loads(g) for g in self.got]


def _rows(n: int, row0: int = 0) -> array:
    """n rows of COLS: t = k·1 ms, F_des, F (NaN every 7th), I, k."""
    a = array("d")
    for i in range(row0, row0 + n):
        a.extend((i * 1e-3, 10.0 + i, math.nan if i % 7 == 3 else -float(i), 0.5, float(i)))
    return a


def _drain(bus: RowBus) -> None:
    for s in bus.sinks:
        while s.work(NEVER, time.monotonic_ns, None):
            pass


def test_rows_arrive_as_json_objects_with_timestamp_nan_as_null():
    rx = Receiver()
    bus = RowBus(COLS, block_ticks=64)
    st = UdpStream(rx.url, COLS, None, 1, epoch0=lambda: 1_700_000_000.0)
    bus.add(st)
    for j in range(4):  # the recorder's hand-over: blocks of 64 rows
        bus.publish(_rows(64, 64 * j), 64, 64 * j)
        _drain(bus)
    rows = rx.close()
    assert [r["k"] for r in rows] == list(range(256))  # every row, in order
    for r in rows:
        assert set(r) == {"timestamp", *COLS}
        assert r["timestamp"] == pytest.approx(1_700_000_000.0 + r["t"], abs=1e-6)
        assert (r["F"] is None) == (r["k"] % 7 == 3)  # NaN is null (PlotJuggler skips it), never invalid JSON
    assert st.stats()["datagrams"] == 256 and st.stats()["dropped"] == 0


def test_decimation_and_columns_keep_the_row_index_across_blocks():
    rx = Receiver()
    bus = RowBus(COLS, block_ticks=50)
    bus.add(UdpStream(rx.url, COLS, ("I", "F_des"), every=10, epoch0=lambda: 0.0))
    for j in range(5):
        bus.publish(_rows(50, 50 * j), 50, 50 * j)  # 50 is not a multiple of 10's phase in every block
        _drain(bus)
    rows = rx.close()
    assert [round(r["timestamp"] * 1e3) for r in rows] == list(range(0, 250, 10))
    assert all(set(r) == {"timestamp", "F_des", "I"} for r in rows)  # the row's order, t only as timestamp
    assert rows[3]["F_des"] == 40.0


def test_own_blocks_without_a_recorder_are_published_and_flushed():
    rx = Receiver()
    bus = RowBus(COLS, block_ticks=32)
    bus.add(UdpStream(rx.url, COLS, None, 1, epoch0=lambda: 0.0))
    for i in range(100):
        bus.record(i * 1e-3, 1.0, 2.0, 3.0, float(i))
    bus.flush()  # the last 4 rows, at the end of the run
    _drain(bus)
    assert [r["k"] for r in rx.close()] == list(range(100))


def test_json_template_is_valid_json():
    fmt = json_row_format(RUN_COLUMNS, RUN_FORMATS)
    row = json.loads(fmt % ((1.5e9,) + tuple(0.25 * i for i in range(len(RUN_COLUMNS)))))
    assert list(row) == ["timestamp", *RUN_COLUMNS]


def test_a_receiver_that_never_reads_costs_nothing_but_drops():
    rx = Receiver(read=False, rcvbuf=4096)
    bus = RowBus(COLS, block_ticks=256)
    st = UdpStream(rx.url, COLS, None, 1, epoch0=lambda: 0.0)
    bus.add(st)
    t0 = time.perf_counter()
    for j in range(20):
        bus.publish(_rows(256, 256 * j), 256, 256 * j)
        _drain(bus)
    took = time.perf_counter() - t0
    rx.close(0)
    assert st.stats()["datagrams"] + st.stats()["dropped"] == 20 * 256
    assert took < 5.0  # ~5120 sends, each non-blocking (it would hang forever if one waited)


def test_nobody_listening_is_counted_not_raised():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # a port where nobody listens: ICMP port unreachable, ECONNREFUSED on a later send
    bus = RowBus(COLS, block_ticks=64)
    st = UdpStream(f"udp://127.0.0.1:{port}", COLS, None, 1, epoch0=lambda: 0.0)
    bus.add(st)
    for j in range(4):
        bus.publish(_rows(64, 64 * j), 64, 64 * j)
        _drain(bus)
        time.sleep(0.01)
    assert st.stats()["refused"] > 0 and bus.errors == 0


def test_a_stream_that_falls_behind_drops_whole_blocks_and_counts_them():
    rx = Receiver()
    bus = RowBus(COLS, block_ticks=100)
    st = UdpStream(rx.url, COLS, None, 1, epoch0=lambda: 0.0, max_backlog_rows=250)
    bus.add(st)
    for j in range(5):  # no idle time: nothing sent between hand-overs
        bus.publish(_rows(100, 100 * j), 100, 100 * j)
    _drain(bus)
    rows = rx.close()
    assert st.stats()["rows_behind"] == 300 and len(rows) == 200
    assert [r["k"] for r in rows] == list(range(200))


def test_idle_time_work_stops_at_its_deadline():
    rx = Receiver()
    bus = RowBus(COLS, block_ticks=256)
    st = UdpStream(rx.url, COLS, None, 1, epoch0=lambda: 0.0)
    bus.add(st)
    bus.publish(_rows(256), 256, 0)
    bus.work(time.monotonic_ns())  # the deadline has passed: one chunk at most
    assert st.datagrams <= 8
    rx.close(0)


def test_recorder_hands_each_block_to_on_block_with_its_first_tick(tmp_path):
    seen: list[tuple[list[float], int, int]] = []
    rec = Recorder(tmp_path / "r.csv", RUN_COLUMNS, block_ticks=16, capacity_ticks=64, defer_format=True,
                   fmt=RUN_FORMATS)
    rec.on_block = lambda b, n, t0: seen.append((b[: n * len(RUN_COLUMNS)].tolist(), n, t0))
    for k in range(40):
        rec.record(k * 1e-3, 0, 0, 0, 0, 0, k, k, 0, 0, 0, 0, 0, 0, 0)
        rec.format_pending(time.monotonic_ns() + 10**6)
    rec.flush()
    rec.close()
    assert [(n, t0) for _, n, t0 in seen] == [(16, 0), (16, 16), (8, 32)]
    assert [row[6] for b, _, _ in seen for row in struct.iter_unpack("=15d", array("d", b).tobytes())] == \
        [float(k) for k in range(40)]


def test_stream_config_is_checked_with_key_paths(tmp_path):
    cfg = tmp_path / "e.yaml"
    text = FIG5.read_text()
    cfg.write_text(text + "stream: {url: 'tcp://x:1', every: 0, columns: [F, Force]}\n")
    with pytest.raises(ConfigError) as ei:
        load_experiment(cfg)
    msg = str(ei.value)
    assert "stream.url" in msg and "stream.every" in msg and "stream.columns" in msg and "Force" in msg
    cfg.write_text(text + "stream: {url: 'udp://127.0.0.1:9870', every: 10, columns: [F, I]}\n")
    node = load_experiment(cfg)
    assert node.stream.url == "udp://127.0.0.1:9870" and node.stream.columns == ("F", "I")


def test_an_unresolvable_stream_host_is_refused_before_the_device(tmp_path):
    from mrctl.daemon.observe import stream_settings

    with pytest.raises(BadInput, match="cannot resolve"):
        stream_settings({}, "udp://no-such-host.invalid:9870", None, None)
    assert stream_settings({}, None, None, None) is None


def _run_daemon(tmp_path: Path, url: str, seconds: float = 2.0, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mrctl", "run", str(_timing_open(tmp_path)), "--duration", str(seconds), "--quiet",
                           "--out", str(tmp_path / "run.csv"), "--status-socket", str(tmp_path / "s.sock"),
                           "--stream", url, *extra], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_a_2s_run_streams_every_tick_in_order_with_its_timestamp(tmp_path):
    """Done-when: every row of the run log (decimation 1), in order, each with its timestamp."""
    rx = Receiver()
    res = _run_daemon(tmp_path, rx.url)
    rows = rx.close()
    assert res.returncode == 0, res.stderr
    log = read_run(tmp_path / "run.csv")
    assert len(log["k"]) >= 1900
    assert [r["k"] for r in rows] == [int(k) for k in log["k"]]  # every tick the log has, in order
    offsets = [r["timestamp"] - r["t"] for r in rows]
    assert max(offsets) - min(offsets) < 2e-6  # timestamp = the run's start (Unix time) + t
    assert abs(offsets[0] - time.time()) < 120
    assert [r["F_des"] for r in rows[:50]] == pytest.approx([float(v) for v in log["F_des"][:50]], rel=1e-8)
    side = read_sidecar(tmp_path / "run.csv")
    assert side["summary"]["stream"]["datagrams"] == len(rows) and side["summary"]["stream"]["dropped"] == 0


def test_a_receiver_that_never_reads_leaves_the_run_and_its_log_whole(tmp_path):
    rx = Receiver(read=False, rcvbuf=4096)
    res = _run_daemon(tmp_path, rx.url)
    rx.close(0)
    assert res.returncode == 0, res.stderr
    side = read_sidecar(tmp_path / "run.csv")
    assert side["complete"] and side["dropped_rows"] == 0 and side["rows_written"] == side["ticks"]
    s = side["summary"]["stream"]
    assert s["datagrams"] + s["dropped"] == side["ticks"] and s["rows_behind"] == 0


def test_status_text_shows_the_stream_and_taps():
    from mrctl.daemon.status import format_status

    text = format_status({"stream": {"url": "udp://127.0.0.1:9870", "datagrams": 11000, "dropped": 3,
                                     "rows_behind": 0}, "taps": {"active": 1}})
    assert "stream udp://127.0.0.1:9870: 11000 datagrams sent, 3 dropped" in text and "taps: 1 connected" in text


def test_device_pacing_sends_from_the_worker_thread():
    rx = Receiver()
    bus = RowBus(COLS, block_ticks=64, defer=False)
    assert bus._worker is None  # no thread until something consumes rows
    bus.add(UdpStream(rx.url, COLS, None, 1, epoch0=lambda: 0.0))
    assert bus._worker is not None
    for j in range(4):
        bus.publish(_rows(64, 64 * j), 64, 64 * j)  # the loop thread only copies; the worker sends
        time.sleep(0.05)
    bus.close()
    assert [r["k"] for r in rx.close()] == list(range(256))
