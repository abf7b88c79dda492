"""docs/observe.md and what ships with it: the PlotJuggler layout, the metric list, the units."""

from __future__ import annotations

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from mrctl.daemon.prometheus import families
from mrctl.runlog.format import RUN_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
DOC = (ROOT / "docs" / "observe.md").read_text()


def test_plotjuggler_layout_loads_and_plots_stream_series():
    root = ET.parse(ROOT / "docs" / "plotjuggler-mrctl.xml").getroot()
    assert root.tag == "root" and root.find("tabbed_widget") is not None
    curves = [c.get("name") for c in root.iter("curve")]
    # PlotJuggler names a UDP JSON key K as the series /K
    assert {"/F_des", "/F", "/I"} <= set(curves)
    assert all(c.startswith("/") and c[1:] in RUN_COLUMNS for c in curves), curves
    assert "plotjuggler-mrctl.xml" in DOC


def test_every_metric_is_in_the_docs_list():
    full = {
        "mrctl_version": "0.1.0", "experiment": "e", "law": "l", "uptime_s": 1, "rate_hz": 1000, "ticks": 1,
        "timing": {k: 1.0 for k in ("lateness_p50_us", "lateness_p99_us", "lateness_p999_us", "lateness_max_us",
                                    "compute_p50_us", "compute_p99_us", "compute_p999_us", "compute_max_us")}
        | {"overruns": 0, "skipped_deadlines": 0},
        "current_A": 0, "F_des_N": 0, "x_m": 0, "v_mps": 0, "link_errors": 0, "safety_state": "OK",
        "safety_counters": {"faults_entered": 0, "holds_used": 0, "ticks_in_fault": 0, "resumes": 0, "missing": 0},
        "recorder": {"rows_written": 0, "dropped_rows": 0}, "stream": {"datagrams": 0, "dropped": 0, "rows_behind": 0},
        "taps": {"active": 0}, "reloads": {"ok": 0, "rejected": 0},
    }
    names = {f.name for f in families(full)}
    assert len(names) >= 28
    missing = [n for n in sorted(names) if f"`{n}" not in DOC]
    assert not missing, f"docs/observe.md does not list {missing}"


def test_units_keep_syslog_level_prefixes():
    for unit in ("mrctl.service", "mrctl@.service"):
        text = (ROOT / "systemd" / unit).read_text()
        assert "SyslogLevelPrefix=yes" in text and "SyslogLevelPrefix=no" not in text


def test_exporter_unit_reads_the_socket_as_group_mrctl():
    text = (ROOT / "systemd" / "mrctl-exporter.service").read_text()
    assert "mrctl exporter --listen 127.0.0.1:9877" in text and "SupplementaryGroups=mrctl" in text  # loopback
    assert "mrctl run" not in text  # never the control process


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_exporter_unit_verifies(tmp_path):
    unit = "mrctl-exporter.service"
    (tmp_path / unit).write_text((ROOT / "systemd" / unit).read_text().replace("/usr/local/bin/mrctl", sys.executable))
    res = subprocess.run(["systemd-analyze", "verify", unit], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stderr.strip() == "", res.stderr
