"""``mrctl tap``: a running daemon's next rows as CSV, through the status socket (docs/observe.md)."""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
from array import array
from pathlib import Path

import pytest

from mrctl.cli import main
from mrctl.daemon.rowbus import RowBus
from mrctl.daemon.status import StatusServer, query_status
from mrctl.daemon.tap import TapRequest, TapServer, TapSink, parse_request, parse_trigger, tap
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS
from mrctl.runlog.read import read_sidecar

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"


def _timing_open(d: Path) -> Path:
    """fig5 with the timing bounds opened: these runs are about rows, on a
    shared machine whose timing is a bench/ figure (docs/runlog.md: the verdict)."""
    p = d / "fig5.yaml"
    p.write_text(FIG5.read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    return p
COLS = ("t", "F", "fault", "k")
NEVER = 1 << 62


def _block(row0: int, n: int, fault_at: int | None = None, F: float = 0.0) -> array:
    a = array("d")
    for i in range(row0, row0 + n):
        a.extend((i * 1e-3, F + i, 1.0 if fault_at is not None and i >= fault_at else 0.0, float(i)))
    return a


def _collect(sink: TapSink) -> list[str]:
    while sink.work(NEVER, time.monotonic_ns, None):
        pass
    text = b""
    while not sink.out.empty():
        b = sink.out.get()
        if b is None:
            break
        text += b
    return text.decode().splitlines()


def test_the_next_n_rows_in_the_logs_formats():
    sink = TapSink(COLS, TapRequest(20, ("t", "k")), {"t": "%.10g", "k": "%.10g"})
    sink.feed(_block(100, 16), 16, 100)
    sink.feed(_block(116, 16), 16, 116)
    lines = _collect(sink)
    assert lines == [f"{k * 1e-3:.10g},{k}" for k in range(100, 120)]
    assert sink.done and sink.end_reason == "complete"


def test_a_fault_trigger_captures_around_the_next_rising_edge_with_pre_rows():
    req = parse_request({"tap": 10, "columns": ["k", "fault"], "trigger": "fault", "pre": 4}, COLS)
    sink = TapSink(COLS, req, {"k": "%.10g", "fault": "%.9g"})
    for j in range(5):  # the fault comes at row 83, in the fourth block
        sink.feed(_block(20 * j, 20, fault_at=83), 20, 20 * j)
    lines = _collect(sink)
    assert sink.trigger_row == 83
    assert [int(ln.split(",")[1]) for ln in lines] == list(range(79, 89))  # 4 rows before, the edge, 5 after
    assert [ln.split(",")[0] for ln in lines] == ["0"] * 4 + ["1"] * 6


def test_a_threshold_trigger_waits_for_a_fresh_crossing():
    req = parse_request({"tap": 3, "columns": ["k"], "trigger": "F>50"}, COLS)
    sink = TapSink(COLS, req, {})
    sink.feed(_block(60, 10, F=0.0), 10, 60)  # F = 60..69: above already when armed, no edge
    sink.feed(_block(70, 10, F=-100.0), 10, 70)  # F = -30..-21: below
    sink.feed(_block(80, 100, F=-100.0), 100, 80)  # crosses 50 at row 151
    lines = _collect(sink)
    assert [float(x) for x in lines] == [151.0, 152.0, 153.0]


@pytest.mark.parametrize("req, msg", [
    ({"tap": 0}, "positive"), ({"tap": "10"}, "positive"), ({"tap": 5, "columns": ["F", "nope"]}, "nope"),
    ({"tap": 5, "trigger": "F=1"}, "COLUMN>VALUE"), ({"tap": 5, "trigger": "F>>1"}, "not a number"), ({"tap": 5, "trigger": "Q>1"}, "no column"),
    ({"tap": 5, "pre": 10}, "only with a trigger"),
])
def test_bad_requests_are_refused_with_the_reason(req, msg):
    with pytest.raises(ValueError, match=msg):
        parse_request(req, COLS)


def test_trigger_syntax():
    assert str(parse_trigger("I < 0.2", RUN_COLUMNS)) == "I<0.2"
    assert parse_trigger("fault", RUN_COLUMNS).op == ">"


def _server(tmp_path: Path, bus: RowBus, snapshot=lambda: {"pid": 1}) -> tuple[StatusServer, TapServer, str]:
    taps = TapServer(bus, RUN_FORMATS, lambda: {"rate_hz": 1000.0})
    path = str(tmp_path / "s.sock")
    srv = StatusServer(path, snapshot, taps.handle)
    srv.start()
    return srv, taps, path


def test_status_still_answers_at_once_while_taps_run(tmp_path, monkeypatch):
    from mrctl.daemon import status

    monkeypatch.setattr(status, "REQUEST_WAIT_S", 5.0)  # a status that waited for a request line would take 5 s
    bus = RowBus(COLS, block_ticks=10)
    srv, taps, path = _server(tmp_path, bus)
    try:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(path)
        s.sendall(b'{"tap": null}\n')
        head = json.loads(s.makefile("rb").readline())
        assert head["ok"] and head["columns"] == list(COLS)
        t0 = time.monotonic()
        assert query_status(path) == {"pid": 1}
        assert time.monotonic() - t0 < 2.5  # status does not wait for a request line
        assert taps.active == 1
        s.close()
        deadline = time.monotonic() + 3
        while taps.active and time.monotonic() < deadline:
            time.sleep(0.05)
        assert taps.active == 0  # the client left: its sink is gone from the bus
        assert bus.sinks == ()
    finally:
        srv.close()


def test_a_client_that_sends_nothing_still_gets_the_status(tmp_path):
    srv, _, path = _server(tmp_path, RowBus(COLS))
    try:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(path)  # like `nc -U`: no request, no shutdown
        s.settimeout(2)
        assert json.loads(s.makefile("rb").readline()) == {"pid": 1}
        s.close()
    finally:
        srv.close()


def test_tap_client_gets_rows_and_the_end(tmp_path):
    bus = RowBus(COLS, block_ticks=10)
    srv, _, path = _server(tmp_path, bus)
    out = io.BytesIO()
    try:
        import threading

        def feed():
            for j in range(50):
                bus.record(j * 1e-3, 1.0, 0.0, float(j))
                bus.work(NEVER)
                time.sleep(0.002)
            bus.flush()
            bus.close()

        deadline = time.monotonic() + 2
        th = threading.Thread(target=feed)
        # the tap subscribes before the rows come
        res_box = {}
        tt = threading.Thread(target=lambda: res_box.update(r=tap(path, out, rows=None, columns=["k"])))
        tt.start()
        while not bus.sinks and time.monotonic() < deadline:
            time.sleep(0.01)
        th.start()
        th.join(5)
        tt.join(5)
        res = res_box["r"]
    finally:
        srv.close()
    lines = out.getvalue().decode().splitlines()
    assert lines[0] == "k" and [int(x) for x in lines[1:]] == list(range(50)) and res.rows == 50
    assert res.end == "the run ended"


def test_tap_refused_request_is_a_clean_error(tmp_path, capsys):
    srv, _, path = _server(tmp_path, RowBus(RUN_COLUMNS))
    try:
        assert main(["tap", "--socket", path, "-n", "5", "--columns", "t,nope"]) == 2  # checked before asking
        assert main(["tap", "--socket", path, "-n", "5", "--pre", "3"]) == 2
        assert main(["tap", "--socket", str(tmp_path / "none.sock"), "-n", "5"]) == 3  # nothing running: the link-failure code
    finally:
        srv.close()
    err = capsys.readouterr().err
    assert "nope" in err and "--pre" in err and "no mrctl running" in err and "Traceback" not in err


# -- against a running daemon --------------------------------------------------
def _daemon(tmp_path: Path, seconds: float, out: bool = True) -> tuple[subprocess.Popen, str]:
    sock = str(tmp_path / "d.sock")
    cmd = [sys.executable, "-m", "mrctl", "run", str(_timing_open(tmp_path)), "--duration", str(seconds), "--quiet",
           "--status-socket", sock] + (["--out", str(tmp_path / "run.csv")] if out else ["--no-log"])
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if query_status(sock, 0.5).get("ticks", 0) > 200:
                return p, sock
        except OSError:
            pass
        if p.poll() is not None:
            break
        time.sleep(0.05)
    p.kill()
    raise AssertionError(f"daemon did not start: {p.communicate()}")


def _tap(sock: str, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mrctl", "tap", "--socket", sock, *args], cwd=ROOT,
                          capture_output=True, timeout=timeout)


def test_tap_500_rows_are_consecutive_rows_of_the_run(tmp_path):
    """Done-when: 500 consecutive rows; k has no gap the run log does not have (skipped deadlines)."""
    p, sock = _daemon(tmp_path, 4.0)
    try:
        res = _tap(sock, "-n", "500")
    finally:
        p.communicate(timeout=60)
    assert res.returncode == 0, res.stderr
    assert p.returncode == 0
    lines = res.stdout.decode().splitlines()
    assert lines[0] == ",".join(RUN_COLUMNS) and len(lines) == 501
    log = (tmp_path / "run.csv").read_text().splitlines()
    i = log.index(lines[1])
    assert log[i : i + 500] == lines[1:]  # the same 500 rows, byte for byte, with no row left out
    ks = [float(ln.split(",")[RUN_COLUMNS.index("k")]) for ln in lines[1:]]
    assert all(b > a for a, b in zip(ks, ks[1:]))


def test_tap_without_a_run_log_and_ctrl_c_ends_it_cleanly(tmp_path):
    p, sock = _daemon(tmp_path, 8.0, out=False)  # room for a slow tap start on a loaded machine
    try:
        t = subprocess.Popen([sys.executable, "-m", "mrctl", "tap", "--socket", sock, "-c", "t,k,I"], cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        time.sleep(1.5)
        t.send_signal(signal.SIGINT)
        out, err = t.communicate(timeout=30)
        deadline = time.monotonic() + 5.0  # the daemon sees the client leave within its poll (0.25 s)
        st = query_status(sock)
        while st["taps"]["active"] and time.monotonic() < deadline:
            time.sleep(0.1)
            st = query_status(sock)
    finally:
        p.communicate(timeout=60)
    assert t.returncode == 0, err
    lines = out.decode().splitlines()
    assert lines[0] == "t,I,k" and len(lines) > 200  # the run log's order
    ks = [float(ln.split(",")[2]) for ln in lines[1:] if ln.count(",") == 2]
    assert all(b > a for a, b in zip(ks, ks[1:]))
    assert st["taps"]["served"] >= 1 and st["taps"]["active"] == 0
    assert p.returncode == 0


def test_a_tap_client_that_never_reads_is_dropped_and_the_run_is_whole(tmp_path):
    p, sock = _daemon(tmp_path, 6.0)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        s.connect(sock)
        s.sendall(b'{"tap": null}\n')  # then never read
        p.communicate(timeout=60)
    finally:
        s.close()
    assert p.returncode == 0
    side = read_sidecar(tmp_path / "run.csv")
    assert side["complete"] and side["dropped_rows"] == 0 and side["rows_written"] == side["ticks"]
    assert side["summary"]["taps"]["dropped"] == 1


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX")
def test_tap_goes_through_the_status_sockets_permissions(tmp_path):
    bus = RowBus(COLS)
    srv, _, path = _server(tmp_path, bus)
    try:
        assert oct(os.stat(path).st_mode & 0o777) == oct(0o660)
    finally:
        srv.close()


def test_tap_against_a_daemon_that_never_answers_times_out(tmp_path):
    """D19: a socket that accepts and never answers hung ``mrctl tap`` forever."""
    path = str(tmp_path / "mute.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(4)
    try:
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "mrctl", "tap", "--socket", path, "-n", "5"],
                    capture_output=True, text=True, timeout=30)
        assert time.monotonic() - t0 < 15
        assert r.returncode == 3, (r.returncode, r.stderr)
        assert "no answer within 2 s" in r.stderr and "Traceback" not in r.stderr
    finally:
        srv.close()
