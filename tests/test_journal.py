"""journald priorities: warnings and faults reach the journal as <4>/<3> lines, the rest stays info."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
from pathlib import Path

from mrctl.daemon.service import RunOptions, Service
from mrctl.util.journal import ERR, WARNING, Journal, prefixed, stream_is_journal

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"
PRIO = re.compile(r"^<([0-7])>")


def _fault_config(tmp_path: Path, auto_resume: bool = True) -> Path:
    """fig5 with a ±5 mm displacement range: the 10 mm sine leaves it twice a period."""
    text = FIG5.read_text().replace(
        "safety: {I_max: 0.6}",
        f"safety: {{I_max: 0.6, x_range_m: [-0.005, 0.005], auto_resume: {str(auto_resume).lower()}}}")
    p = tmp_path / "fault.yaml"
    p.write_text(text)
    return p


def test_prefix_on_every_line_and_clamped():
    assert prefixed(WARNING, "mrctl: a\nb") == "<4>mrctl: a\n<4>b"
    assert prefixed(ERR, "x") == "<3>x" and prefixed(42, "x") == "<7>x" and prefixed(-1, "x") == "<0>x"


def test_formatter_writes_the_prefix_only_when_asked_or_on_the_journal():
    assert Journal(io.StringIO(), prefix=True).format(WARNING, "disk full") == "<4>mrctl: disk full"
    assert Journal(io.StringIO(), prefix=False).format(ERR, "x") == "mrctl: x"
    assert Journal(io.StringIO()).prefix is False  # no file descriptor: never the journal


def test_journal_stream_must_name_this_very_stream(tmp_path):
    with open(tmp_path / "err", "w") as f, open(tmp_path / "other", "w") as g:
        st = os.fstat(f.fileno())
        env = {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        assert stream_is_journal(f, env)
        assert not stream_is_journal(g, env)  # e.g. stderr redirected to a file by a wrapper script
        assert not stream_is_journal(f, {}) and not stream_is_journal(f, {"JOURNAL_STREAM": "garbage"})


def test_a_fault_runs_warnings_reach_the_journal_at_priority_4_or_less(tmp_path):
    err, out = io.StringIO(), io.StringIO()
    code = Service(RunOptions(str(_fault_config(tmp_path)), duration_s=1.5, live=False, err=err, stream=out,
                              status_socket=str(tmp_path / "s.sock"), log_priorities=True)).run()
    assert code == 5  # out of range twice a period: a degraded run
    assert any("<3>mrctl: verdict: degraded: ticks in fault" in ln for ln in err.getvalue().splitlines())
    lines = [ln for ln in err.getvalue().splitlines() if ln]
    assert lines, "a fault run must say so on stderr"
    assert all(PRIO.match(ln) for ln in lines), lines  # every stderr line carries its priority
    faults = [ln for ln in lines if "safety: FAULT" in ln]
    assert faults and all(ln.startswith("<3>mrctl: safety: FAULT OUT_OF_RANGE") for ln in faults), faults
    assert any(ln.startswith("<5>mrctl: safety: fault cleared") for ln in lines)  # auto_resume: a notice


def test_under_systemd_stderr_is_detected_and_prefixed(tmp_path):
    """The real path: JOURNAL_STREAM names the process's stderr, as systemd sets it."""
    errf = tmp_path / "stderr"
    with open(errf, "w") as f:
        st = os.fstat(f.fileno())
        env = dict(os.environ, JOURNAL_STREAM=f"{st.st_dev}:{st.st_ino}")
        res = subprocess.run([sys.executable, "-m", "mrctl", "run", str(_fault_config(tmp_path, False)),
                              "--duration", "1", "--quiet", "--no-log", "--status-socket", str(tmp_path / "s.sock")],
                             cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=f, text=True, timeout=120)
        bad = subprocess.run([sys.executable, "-m", "mrctl", "check", str(tmp_path / "missing.yaml")],
                             cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=f, text=True, timeout=60)
    assert res.returncode == 5 and bad.returncode == 2  # a latched fault: degraded
    lines = errf.read_text().splitlines()
    fault = [ln for ln in lines if "safety: FAULT" in ln]
    assert len(fault) == 1 and fault[0].startswith("<3>mrctl: ")  # latched: reported once
    assert any(ln.startswith("<3>mrctl: ") and "missing.yaml" in ln for ln in lines)  # the CLI's errors too
    assert not [ln for ln in lines if ln and not PRIO.match(ln)], lines
    assert not PRIO.search(res.stdout)  # stdout lines stay at the unit's SyslogLevel (info)


def test_a_terminal_sees_no_prefixes(tmp_path):
    err = io.StringIO()
    Service(RunOptions(str(_fault_config(tmp_path, False)), duration_s=0.5, live=False, err=err,
                       stream=io.StringIO(), status_socket=str(tmp_path / "s.sock"))).run()
    assert "mrctl: safety: FAULT" in err.getvalue() and not PRIO.search(err.getvalue())
