"""systemd units: they verify, and they carry the RT limits and hardening."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNITS = Path(__file__).resolve().parents[1] / "systemd"
REQUIRED = [
    "Type=notify", "WatchdogSec=", "ExecReload=/bin/kill -HUP $MAINPID", "LimitRTPRIO=", "LimitMEMLOCK=",
    "NoNewPrivileges=yes", "ProtectSystem=strict", "ProtectHome=yes", "PrivateTmp=yes", "User=mrctl",
    "DevicePolicy=closed", "DeviceAllow=char-ttyUSB rw", "KillSignal=SIGTERM",
]


@pytest.mark.parametrize("unit", ["mrctl.service", "mrctl@.service"])
def test_unit_has_rt_limits_and_hardening(unit):
    text = (UNITS / unit).read_text()
    for line in REQUIRED:
        assert line in text, f"{unit}: missing {line}"
    assert "mrctl run" in text and "--out" in text


def test_template_is_per_damper():
    text = (UNITS / "mrctl@.service").read_text()
    assert "/etc/mrctl/%i.yaml" in text and "RuntimeDirectory=mrctl/%i" in text


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify_passes(tmp_path):
    # verify needs ExecStart's binary to exist: point it at this Python
    for unit in ("mrctl.service", "mrctl@.service"):
        text = (UNITS / unit).read_text().replace("/usr/local/bin/mrctl", sys.executable)
        (tmp_path / unit).write_text(text)
    (tmp_path / "mrctl@bench1.service").write_text((tmp_path / "mrctl@.service").read_text())
    res = subprocess.run(["systemd-analyze", "verify", "mrctl.service", "mrctl@bench1.service"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stderr.strip() == "", res.stderr
