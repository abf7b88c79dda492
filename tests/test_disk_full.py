"""A disk that fills up mid-run: the loop stays safe, the loss is warned about
while it happens (stderr, ``mrctl status``), the run ends with exit 4 and a
sidecar that records what was lost."""

from __future__ import annotations

import errno
import io
import re
import threading
import time
from pathlib import Path

import pytest

from mrctl.daemon.service import RunOptions, Service

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"


class FailingFile:
    """A log file that takes its first ``ok_lines`` lines (the header is the
    first), then fails with ENOSPC on every write. Counted in lines, not in
    writes: how many rows a block holds depends on the machine's timing
    (a loaded machine wrote fewer blocks in a 1 s run than a count of writes
    assumed), the number of rows a run reaches does not."""

    def __init__(self, path: Path, ok_lines: int) -> None:
        self.fh = open(path, "wb", buffering=0)
        self.left = ok_lines

    def write(self, data):
        n = bytes(data).count(b"\n")
        if 0 < self.left and n <= self.left:
            self.left -= n
            return self.fh.write(data)
        self.left = 0
        raise OSError(errno.ENOSPC, "No space left on device")

    def fileno(self):
        return self.fh.fileno()

    def close(self):
        self.fh.close()


def _failing_log(monkeypatch, ok_lines: int) -> None:
    import mrctl.runlog.files as files

    real = files.create_log

    def create(path, force=False, mkdir=False):
        fh = real(path, force, mkdir)
        fh.close()
        return FailingFile(Path(path), ok_lines)

    monkeypatch.setattr(files, "create_log", create)


def test_injected_write_failure_is_warned_in_status_and_on_stderr_and_exits_4(tmp_path, monkeypatch):
    _failing_log(monkeypatch, ok_lines=51)  # the header and 50 rows: any 1 s run has far more
    out = tmp_path / "run.csv"
    err = io.StringIO()
    svc = Service(RunOptions(str(FIG5), out=str(out), duration_s=2.0, live=False, err=err, stream=io.StringIO(),
                             status_socket=str(tmp_path / "s.sock")))
    seen: dict = {}

    def watch():  # what mrctl status shows while rows are being lost
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            rec = svc.rec
            if rec is not None and rec.stats()["dropped_rows"] > 0:
                time.sleep(0.2)  # the monitor polls every 50 ms
                seen.update(svc.snapshot())
                seen["stderr_then"] = err.getvalue()
                return
            time.sleep(0.01)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    code = svc.run()
    th.join(5)
    assert code == 4, err.getvalue()
    assert seen, "never saw the recorder lose rows"
    assert seen["recorder"]["dropped_rows"] > 0 and "No space left" in seen["recorder"]["error"]
    assert "LOSING ROWS" in seen["log"] and "No space left" in seen["log"]
    assert "run log: losing rows" in seen["stderr_then"]  # warned while running, not only at the end
    from mrctl.runlog.read import read_sidecar

    side = read_sidecar(out)
    assert side["exit_code"] == 4 and side["complete"] is True
    assert side["dropped_rows"] > 0 and side["rows_written"] + side["dropped_rows"] == side["ticks"]
    assert "No space left" in side["error"]
    assert side["summary"]["exit_current_A"] == 0.0


def test_sidecar_that_cannot_be_written_is_reported_with_the_counts(tmp_path, monkeypatch):
    _failing_log(monkeypatch, ok_lines=51)
    import mrctl.runlog.files as files

    real = files.write_json
    calls = {"n": 0}

    def write_json(path, data, reserve=0):
        calls["n"] += 1
        if data.get("closed_utc"):  # the final sidecar: the disk is full for it too
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, data, reserve)

    monkeypatch.setattr(files, "write_json", write_json)
    out = tmp_path / "run.csv"
    err = io.StringIO()
    code = Service(RunOptions(str(FIG5), out=str(out), duration_s=1.0, live=False, err=err, stream=io.StringIO(),
                              status_socket=str(tmp_path / "s.sock"))).run()
    text = err.getvalue()
    assert code == 4, text
    line = next(ln for ln in text.splitlines() if "could not write the sidecar" in ln)
    assert re.search(r"\d+ rows written and \d+ lost \(ticks \d+–\d+\) of \d+ ticks", line), line


@pytest.mark.parametrize("sigterm", [False, True], ids=["to-the-end", "sigterm"])
def test_full_tmpfs_ends_with_exit_4_and_a_sidecar_that_records_the_loss(tmp_path, sigterm):
    from hil_sim.testing.daemon_faults import disk_full

    r = disk_full(tmp_path, sigterm=sigterm)
    if r.get("skipped"):
        pytest.skip(r["skipped"])
    assert not r["traceback"], r["messages"]
    assert r["exit"] == 4, r
    assert any("run log: losing rows" in m for m in r["messages"]), r["messages"]
    s = r["sidecar"]
    assert s["exit_code"] == 4 and s["complete"] is True, s
    assert s["dropped_rows"] > 0 and "No space left" in (s["error"] or "")
    assert s["rows_written"] + s["dropped_rows"] == s["ticks"] == r["loop_ticks"]
    assert r["exit_current_A"] == 0.0
    if sigterm:
        assert r.get("signal_sent")
        st = r["status_while_losing"]
        assert "LOSING ROWS" in (st.get("log") or "")
