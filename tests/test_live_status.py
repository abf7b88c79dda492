"""What a user reads while a run goes on: the live line and ``mrctl status``."""

from __future__ import annotations

import io
import json
import re
import socket
import threading
from pathlib import Path

from mrctl.cli import main
from mrctl.daemon.service import RunOptions, Service

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"


class FakeTTY(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_live_line_fits_the_terminal_and_shows_elapsed_and_remaining(tmp_path, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    err = FakeTTY()
    cfg = tmp_path / "fig5.yaml"  # timing not judged: a real clock on a shared machine
    cfg.write_text(Path(FIG5).read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    code = Service(RunOptions(str(cfg), out=None, duration_s=1.6, live=True, err=err, stream=io.StringIO(),
                              status_socket=str(tmp_path / "s.sock"))).run()
    assert code == 0
    lines = [seg for seg in err.getvalue().replace("\n", "\r").split("\r") if seg.strip()]
    live = [ln for ln in lines if "elapsed" in ln]
    assert live, err.getvalue()[:500]
    for ln in lines:
        assert len(ln) < 80, repr(ln)  # never wraps on an 80-column terminal
    assert all(re.search(r"elapsed \d+\.\d s", ln) and re.search(r"\d+\.\d s left", ln) for ln in live)


def test_live_line_ends_at_100_percent_and_is_cut_between_fields(tmp_path, monkeypatch):
    """The last line drawn is the run's end (not the last half-second tick of
    the refresh), and a narrow terminal cuts it between fields."""
    from mrctl.daemon.monitor import fit_line

    monkeypatch.setenv("COLUMNS", "60")
    err = FakeTTY()
    cfg = tmp_path / "fig5.yaml"  # the live line is judged here, not a shared machine's clock
    cfg.write_text(FIG5.read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    assert Service(RunOptions(str(cfg), out=None, duration_s=0.7, live=True, err=err, stream=io.StringIO(),
                              status_socket=str(tmp_path / "s.sock"))).run() == 0
    live = [seg for seg in err.getvalue().split("\r") if "elapsed" in seg]
    assert "100%" in live[-1] and "0.0 s left" in live[-1], live[-1]
    line = "[##########] 100% elapsed 0.7 s, 0.0 s left | I 0.123 A OK link_err 0 | late p99 12.3 us"
    assert fit_line(line, 56) == "[##########] 100% elapsed 0.7 s, 0.0 s left"
    assert fit_line(line, 70) == "[##########] 100% elapsed 0.7 s, 0.0 s left | I 0.123 A OK link_err 0"
    assert fit_line("abc def", 5) == "abc" and fit_line("short", 80) == "short"


def test_live_line_until_stopped_has_no_remaining_time(tmp_path, monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")
    svc = Service(RunOptions(str(FIG5), out=None, duration_s=None, live=False, err=io.StringIO(),
                             stream=io.StringIO(), status_socket=str(tmp_path / "s.sock")))
    svc._total_ticks = None
    line = svc._live_line()
    assert "elapsed" in line and "left" not in line


SNAPSHOT = {
    "mrctl_version": "0.1.0", "pid": 4242, "experiment": "fig5", "uptime_s": 12.345678912,
    "rate_hz": 1000.0, "ticks": 12345, "law": "smooth", "current_A": 0.123456789012,
    "x_m": 0.0012345678, "v_mps": -0.0456789123, "F_des_N": -22.839456123,
    "safety_state": "OK", "fault": "NONE", "link_errors": 3,
    "timing": {"lateness_p50_us": 12.3456789, "lateness_p99_us": 87.654321098, "lateness_max_us": 1234.56789,
               "compute_p99_us": 45.678901234, "overruns": 2},
    "recorder": {"rows_written": 12000, "dropped_rows": 0, "error": None},
}


def _serve(path: Path, payload: bytes) -> threading.Thread:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.listen(1)

    def one():
        c, _ = s.accept()
        with c:
            c.sendall(payload)
        s.close()

    th = threading.Thread(target=one, daemon=True)
    th.start()
    return th


def test_status_prints_rounded_values_with_their_units(tmp_path, capsys):
    p = tmp_path / "s.sock"
    th = _serve(p, (json.dumps(SNAPSHOT) + "\n").encode())
    assert main(["status", "--socket", str(p)]) == 0
    th.join(2)
    out = capsys.readouterr().out
    assert not re.search(r"\d\.\d{5,}", out), out  # no unrounded floats
    assert "0.1235 A" in out and "12.3 s" in out and "1000 Hz" in out
    assert re.search(r"p50/p99/max 12/88/1235 µs", out), out
    assert "F_des -22.8 N" in out and "x 1.23 mm" in out and "v -45.7 mm/s" in out
    assert "log: 12000 rows written" in out
