"""Several daemons of one user: each has a status socket, ``mrctl ls`` lists them."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from mrctl.cli import main
from mrctl.daemon import instances
from mrctl.daemon.status import query_status

ROOT = Path(__file__).resolve().parents[1]
FIG5 = str(ROOT / "config" / "experiments" / "fig5.yaml")
#: three 1 kHz loops beside a test suite on a shared machine skip deadlines: timing is not what is judged here
OPEN_TIMING = "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n"


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    """This user's runtime directory under tmp_path, for the test and its subprocesses."""
    tmp = tmp_path / "t"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    monkeypatch.setattr(instances, "SYSTEM_DIR", tmp_path / "no-system")
    return tmp / f"mrctl-{os.getuid()}"


@pytest.fixture
def fig5(tmp_path) -> str:
    """fig5.yaml with its timing bounds open (the verdict on a shared machine's clock is another test's)."""
    cfg = tmp_path / "fig5.yaml"
    cfg.write_text(Path(FIG5).read_text() + OPEN_TIMING)
    return str(cfg)


def _start(cfg: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mrctl", "run", cfg, "--duration", "120", "--no-progress", "--no-log",
                             *args],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ.copy())


def _wait_for(path: Path, p: subprocess.Popen) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if query_status(str(path), 0.5).get("ticks", 0) > 0:
                return
        except OSError:
            pass
        if p.poll() is not None:
            break
        time.sleep(0.05)
    p.kill()
    raise AssertionError(f"daemon did not serve {path}: {p.communicate()}")


def test_ls_lists_named_and_unnamed_daemons_and_a_second_run_is_not_blind(user_dir, fig5, capsys):
    first = _start(fig5)
    procs = [first]
    try:
        _wait_for(user_dir / "status.sock", first)
        second = _start(fig5)  # unnamed too: it must not run without a status socket
        procs.append(second)
        _wait_for(user_dir / f"run-{second.pid}.sock", second)
        named = _start(fig5, "--instance", "left")
        procs.append(named)
        _wait_for(user_dir / "left.sock", named)
        # a socket left behind by a daemon that died is not a daemon
        stale = socket.socket(socket.AF_UNIX)
        stale.bind(str(user_dir / "dead.sock"))
        stale.close()

        assert main(["ls", "--json"]) == 0
        found = json.loads(capsys.readouterr().out)
        by_pid = {d["pid"]: d for d in found}
        assert set(by_pid) == {p.pid for p in procs}, found
        assert by_pid[named.pid]["instance"] == "left"
        assert by_pid[second.pid]["instance"] == f"run-{second.pid}"
        assert by_pid[first.pid]["instance"] is None
        for d in found:
            assert d["config"] == fig5 and d["state"] == "OK" and d["uptime_s"] > 0 and d["answering"]
        assert main(["ls"]) == 0
        table = capsys.readouterr().out
        assert "left" in table and str(named.pid) in table and "dead" not in table and fig5 in table

        assert main(["status", "--instance", "left", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["pid"] == named.pid
        assert main(["status", "--instance", f"run-{second.pid}", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["pid"] == second.pid
    finally:
        for p in procs:
            p.terminate()
        outs = [p.communicate(timeout=60) for p in procs]
    assert f"mrctl status --instance run-{second.pid}" in outs[1][1]  # the second run said where it is
    assert "running without it" not in outs[1][1]
    assert all(p.returncode == 0 for p in procs), outs


def test_ls_with_nothing_running_and_bad_instance_names(user_dir, capsys):
    assert main(["ls"]) == 0
    assert "no mrctl running" in capsys.readouterr().out
    assert main(["ls", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == []
    for bad in ("../x", "a/b", "status", "", ".hidden"):
        assert main(["status", "--instance", bad]) == 2, bad
        assert "--instance" in capsys.readouterr().err
    assert main(["run", FIG5, "--instance", "a/b", "--duration", "0.1"]) == 2


def test_status_finds_the_one_daemon_of_this_user(user_dir, fig5, capsys):
    p = _start(fig5, "--instance", "only")
    try:
        _wait_for(user_dir / "only.sock", p)
        assert main(["status", "--json"]) == 0  # not at status.sock, but the only one
        assert json.loads(capsys.readouterr().out)["pid"] == p.pid
    finally:
        p.terminate()
        p.communicate(timeout=60)
