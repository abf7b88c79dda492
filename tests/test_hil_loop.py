"""Loopback HIL: the daemon against hil_sim over the real protocols.

Short, functional forms for CI: over each transport the daemon controls the
bench for 3.5 s, the device follows its setpoints, 0 A reaches the device on
the way out, and the run log is complete. Tracking accuracy over a real-time
link on a shared VM is a timing figure (it depends on skipped deadlines and
late replies), so the issue's "NRMSE within 2x of simulate" target is
measured by bench/hil_loop.py as a median over repeated runs and reported in
docs/performance.md; here the NRMSE bound only proves the loop is closed
(an uncontrolled damper is at ~40 %), and the measured ratio is printed.
"""

from pathlib import Path

import numpy as np
import pytest

from hil_util import ROOT, HilSim, hil_tracking, run_daemon
from mrctl.recorder import read_run, read_sidecar

pytestmark = pytest.mark.hil
BENCH = str(ROOT / "config" / "hil_fig5_bench.yaml")
EXP = ROOT / "config" / "experiments"
CLOSED_LOOP_NRMSE = 0.05


def _experiment(tmp_path: Path, name: str, **replace: str) -> Path:
    text = (EXP / name).read_text()
    for old, new in replace.items():
        text = text.replace(old, new)
    p = tmp_path / name
    p.write_text(text)
    return p


def _check(tmp_path, cfg, hil):
    out = tmp_path / "run.csv"
    try:
        res = run_daemon(cfg, out, duration_s=3.5)
    finally:
        code = hil.stop()
    assert res.returncode == 0, res.stderr
    assert code == 0
    run = read_run(out)
    truth = read_run(tmp_path / "truth.csv")
    side = read_sidecar(out)
    assert side["complete"] is True and side["summary"]["exit_current_A"] == 0.0
    assert side["rows_written"] == side["summary"]["ticks"]  # every tick run is logged
    # the device followed the daemon: each current sent after the sample of
    # tick s shows up as the device's I_cmd within its next few ticks
    ok = np.isfinite(run["seq"]) & (run["I"] > 0)
    seq, I = run["seq"][ok].astype(np.int64), run["I"][ok]
    k_truth, I_truth = truth["k"].astype(np.int64), truth["I_cmd"]
    applied = 0
    for s, i in zip(seq[::10], I[::10]):
        j = np.searchsorted(k_truth, s + 1)
        if np.any(np.abs(I_truth[j:j + 4] - i) < 1e-6):
            applied += 1
    assert applied >= 0.8 * len(seq[::10]), (applied, len(seq[::10]))
    tr = hil_tracking(run, truth)
    print(f"{cfg.name}: HIL force NRMSE {100 * tr['nrmse']:.3f} % over {tr['rows']} ticks, "
          f"skipped deadlines {side['summary']['timing']['skipped_deadlines']}, "
          f"link errors {side['summary']['link_errors']}")
    assert tr["rows"] > 1500 and tr["nrmse"] < CLOSED_LOOP_NRMSE, tr
    assert truth["I_cmd"][-1] == 0.0  # 0 A at the device after the daemon left


def test_fig5_over_serial_on_a_pty(tmp_path):
    link = tmp_path / "tty"
    hil = HilSim("--config", BENCH, "--transport", "serial", "--link", str(link),
                 "--truth", str(tmp_path / "truth.csv"), "--duration", "30")
    _check(tmp_path, _experiment(tmp_path, "hil_serial.yaml", **{"/tmp/mrctl-sim-tty": str(link)}), hil)


def test_fig5_over_modbus_tcp_on_loopback(tmp_path):
    hil = HilSim("--config", BENCH, "--transport", "modbus-tcp", "--bind", "127.0.0.1:0",
                 "--truth", str(tmp_path / "truth.csv"), "--duration", "30")
    port = hil.field("bind").rsplit(":", 1)[1]
    _check(tmp_path, _experiment(tmp_path, "hil_modbus_tcp.yaml", **{"port: 5020": f"port: {port}"}), hil)


def test_fig5_over_modbus_rtu_on_a_pty(tmp_path):
    link = tmp_path / "rtu"
    hil = HilSim("--config", BENCH, "--transport", "modbus-rtu", "--link", str(link), "--baud", "921600",
                 "--truth", str(tmp_path / "truth.csv"), "--duration", "30")
    _check(tmp_path, _experiment(tmp_path, "hil_modbus_rtu.yaml", **{"/tmp/mrctl-sim-rtu": str(link)}), hil)
