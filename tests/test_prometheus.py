"""Prometheus metrics: ``mrctl status --format prometheus`` and ``mrctl exporter`` (docs/observe.md)."""

from __future__ import annotations

import math
import urllib.request

import pytest

import prometheus_client  # noqa: F401 - a test dependency: missing, the test fails
from prometheus_client.parser import text_string_to_metric_families  # noqa: E402

from mrctl.cli import main  # noqa: E402
from mrctl.daemon.exporter import parse_listen, start  # noqa: E402
from mrctl.daemon.prometheus import prometheus_text  # noqa: E402
from mrctl.daemon.status import StatusServer  # noqa: E402
from mrctl.errors import BadInput  # noqa: E402

SNAPSHOT = {
    "mrctl_version": "0.1.0", "pid": 4242, "experiment": 'fig5 "quoted"\\x', "uptime_s": 12.5,
    "rate_hz": 1000.0, "ticks": 12345, "law": "smooth", "current_A": 0.25, "x_m": 0.0012, "v_mps": None,
    "F_des_N": -22.8, "safety_state": "FAULT", "fault": "OUT_OF_RANGE", "link_errors": 3,
    "safety_counters": {"faults_entered": 2, "out_of_range": 7, "missing": 1, "late": 0, "stale": 0,
                        "non_finite": 0, "device_status": 0, "holds_used": 5, "ticks_in_fault": 40, "resumes": 1},
    "timing": {"lateness_p50_us": 12.0, "lateness_p99_us": 88.0, "lateness_p999_us": 300.0,
               "lateness_max_us": 1234.0, "compute_p50_us": 30.0, "compute_p99_us": 45.0, "compute_p999_us": 90.0,
               "compute_max_us": 200.0, "overruns": 2, "skipped_deadlines": 4},
    "recorder": {"rows_written": 12000, "dropped_rows": 17, "error": None},
    "stream": {"datagrams": 11000, "dropped": 3, "rows_behind": 0},
    "taps": {"active": 1, "served": 2, "dropped": 0},
    "reloads": {"ok": 1, "rejected": 0, "last_error": None},
}


def _parse(text: str) -> dict[str, dict]:
    """{family name: {(sample name, labels...): value}} via prometheus_client's own parser."""
    fams = {}
    for fam in text_string_to_metric_families(text):
        fams[fam.name] = {"type": fam.type, "samples": {(s.name, tuple(sorted(s.labels.items()))): s.value
                                                        for s in fam.samples}}
    return fams


def _value(fams, family, name=None, **labels):
    return fams[family]["samples"][(name or family, tuple(sorted(labels.items())))]


def test_status_as_prometheus_text_parses_with_base_units_and_conventions():
    fams = _parse(prometheus_text(SNAPSHOT))
    assert fams["mrctl_ticks"]["type"] == "counter" and _value(fams, "mrctl_ticks", "mrctl_ticks_total") == 12345
    assert _value(fams, "mrctl_overruns", "mrctl_overruns_total") == 2
    assert _value(fams, "mrctl_safety_faults", "mrctl_safety_faults_total") == 2
    assert _value(fams, "mrctl_recorder_lost_rows", "mrctl_recorder_lost_rows_total") == 17
    assert fams["mrctl_tick_lateness_seconds"]["type"] == "summary"
    assert _value(fams, "mrctl_tick_lateness_seconds", quantile="0.99") == pytest.approx(88e-6)
    assert _value(fams, "mrctl_tick_compute_seconds", quantile="0.5") == pytest.approx(30e-6)
    assert _value(fams, "mrctl_tick_lateness_max_seconds") == pytest.approx(1234e-6)
    assert _value(fams, "mrctl_current_amperes") == 0.25 and fams["mrctl_current_amperes"]["type"] == "gauge"
    assert _value(fams, "mrctl_desired_force_newtons") == -22.8
    assert _value(fams, "mrctl_displacement_meters") == 0.0012
    assert math.isnan(_value(fams, "mrctl_velocity_meters_per_second"))  # no value: NaN, not a missing metric
    assert _value(fams, "mrctl_safety_state", state="FAULT") == 1 and _value(fams, "mrctl_safety_state", state="OK") == 0
    assert _value(fams, "mrctl_safety_bad_samples", "mrctl_safety_bad_samples_total", kind="out_of_range") == 7
    assert _value(fams, "mrctl_stream_dropped", "mrctl_stream_dropped_total") == 3
    assert _value(fams, "mrctl_reloads", "mrctl_reloads_total", result="ok") == 1
    info = [k for k in fams["mrctl_info"]["samples"]][0][1]
    assert dict(info)["experiment"] == 'fig5 "quoted"\\x'  # label values escaped and read back
    assert _value(fams, "mrctl_up") == 1
    for name in fams:
        assert name.startswith("mrctl_")


def test_every_sample_carries_the_damper_label_and_no_daemon_is_up_0():
    fams = _parse(prometheus_text(SNAPSHOT, damper="left"))
    assert all(dict(labels).get("damper") == "left" for f in fams.values() for _, labels in f["samples"])
    down = _parse(prometheus_text(None, damper="left"))
    assert list(down) == ["mrctl_up"] and _value(down, "mrctl_up", damper="left") == 0


def test_status_format_prometheus_on_the_command_line(tmp_path, capsys):
    path = str(tmp_path / "s.sock")
    srv = StatusServer(path, lambda: SNAPSHOT)
    srv.start()
    try:
        assert main(["status", "--socket", path, "--format", "prometheus"]) == 0
    finally:
        srv.close()
    fams = _parse(capsys.readouterr().out)
    assert _value(fams, "mrctl_ticks", "mrctl_ticks_total") == 12345
    assert main(["status", "--socket", path, "--format", "prometheus"]) == 3  # nobody there: exit 3 (the link), and up 0
    cap = capsys.readouterr()
    assert _value(_parse(cap.out), "mrctl_up") == 0 and "no mrctl running" in cap.err


def test_exporter_endpoint_is_scraped_over_http(tmp_path):
    path = str(tmp_path / "s.sock")
    calls = []
    srv = StatusServer(path, lambda: calls.append(1) or SNAPSHOT)
    srv.start()
    server, thread = start("127.0.0.1:0", path, damper="left")
    try:
        url = f"http://127.0.0.1:{server.server_port}/metrics"
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200
            fams = _parse(r.read().decode())
        assert len(calls) == 1  # one status query per scrape
        assert _value(fams, "mrctl_up", damper="left") == 1
        assert _value(fams, "mrctl_ticks", "mrctl_ticks_total", damper="left") == 12345
        assert _value(fams, "mrctl_tick_lateness_seconds", quantile="0.99", damper="left") == pytest.approx(88e-6)
        srv.close()  # the daemon goes away: the exporter still answers, with mrctl_up 0
        with urllib.request.urlopen(url, timeout=10) as r:
            fams = _parse(r.read().decode())
        assert list(fams) == ["mrctl_up"] and _value(fams, "mrctl_up", damper="left") == 0
    finally:
        server.shutdown()
        srv.close()


def test_listen_addresses():
    assert parse_listen(":9877") == ("0.0.0.0", 9877)
    assert parse_listen("[::1]:9000") == ("::1", 9000)
    with pytest.raises(BadInput):
        parse_listen("9877x")

