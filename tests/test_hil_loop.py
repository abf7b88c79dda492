"""Loopback HIL: the daemon against hil_sim over the real protocols.

Short, functional forms for CI: over each transport the daemon controls the
bench for 4 s at 200 Hz (daemon and bench: a rate CI holds; hil_util), the
device follows its setpoints, 0 A reaches the device on the way out, and the
run log is complete. A refused start, a lost link or a protocol error fails
the test; nothing is skipped for load. Tracking accuracy and 1 kHz timing
over a real-time link are figures, measured by bench/hil_loop.py as a median
over repeated runs and reported in docs/performance.md; here the NRMSE bound
only proves the loop is closed (the best constant current is at 7.5 %).
"""

from pathlib import Path

import numpy as np
import pytest

from hil_util import (ROOT, HilSim, bench_at_test_rate, expected_rows, experiment_at_test_rate, hil_tracking,
                      protocol_errors, run_hil as _run_hil)
from mrctl.daemon.recorder import read_run, read_sidecar

pytestmark = pytest.mark.hil
BENCH = str(ROOT / "config" / "hil_fig5_bench.yaml")
EXP = ROOT / "config" / "experiments"
# The best open-loop constant current scores 7.5 % on this scenario (0.35 A;
# 0 A: 31 %), so staying under 6.5 % proves the loop is closed. At 200 Hz
# with one tick of actuation latency the runs score 3.1-3.3 % on a quiet
# machine, up to 5.1 % with a fifth of the deadlines skipped under load
# (2026-11-25, load average 7 on 2 cores).
CLOSED_LOOP_NRMSE = 0.065


def _experiment(tmp_path: Path, name: str, **replace: str) -> Path:
    return experiment_at_test_rate(EXP / name, tmp_path, **replace)


def _check(tmp_path, start, make_cfg):
    d, cfg, res, code = _run_hil(tmp_path, start, make_cfg)
    out = d / "run.csv"
    assert code == 0
    run = read_run(out)
    truth = read_run(d / "truth.csv")
    side = read_sidecar(out)
    assert side["complete"] is True and side["summary"]["exit_current_A"] == 0.0
    assert side["rows_written"] == side["summary"]["ticks"]  # every tick run is logged
    # the device followed the daemon. On an exchange link the current of row i
    # travels in exchange i+1, whose reply carries the device tick s[i+1] that
    # was current when it arrived; the device applies it at its next tick,
    # unless the next setpoint overtook it (the daemon catching up after a
    # stall), so any current sent around then counts
    rows = np.flatnonzero(np.isfinite(run["seq"][:-2]) & np.isfinite(run["seq"][1:-1]) & (run["I"][:-2] > 0))
    rows = rows[rows >= 1]
    k_truth, I_truth = truth["k"].astype(np.int64), truth["I_cmd"]
    checked = applied = 0
    for i in rows:
        j = np.searchsorted(k_truth, int(run["seq"][i + 1]) + 1)
        sent = run["I"][i - 1:i + 3]
        checked += 1
        applied += bool(np.any(np.abs(I_truth[j:j + 3, None] - sent[None, :]) < 1e-6))
    assert checked > 100 and applied >= 0.8 * checked, (applied, checked)
    tr = hil_tracking(run, truth)
    print(f"{cfg.name}: HIL force NRMSE {100 * tr['nrmse']:.3f} % over {tr['rows']} ticks, "
          f"skipped deadlines {side['summary']['timing']['skipped_deadlines']}, "
          f"link errors {side['summary']['link_errors']}")
    # rows matched to the truth after the settle window: a third is "the loop ran" even with 40 % of
    # the deadlines skipped on a loaded machine (timing is bench/hil_loop.py's figure)
    assert tr["rows"] > 0.3 * expected_rows(side) and tr["nrmse"] < CLOSED_LOOP_NRMSE, tr
    bad, exchanges = protocol_errors(side)
    assert exchanges > 0.5 * expected_rows(side) and bad <= 0.01 * exchanges, side["summary"]["link"]
    assert truth["I_cmd"][-1] == 0.0  # 0 A at the device after the daemon left


def test_fig5_over_serial_on_a_pty(tmp_path):
    def start(d):
        return HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "serial", "--link", str(d / "tty"),
                      "--truth", str(d / "truth.csv"), "--duration", "30")

    _check(tmp_path, start, lambda d, hil: _experiment(d, "hil_serial.yaml", **{"/tmp/mrctl-sim-tty": str(d / "tty")}))


def test_fig5_over_modbus_tcp_on_loopback(tmp_path):
    def start(d):
        return HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "modbus-tcp", "--bind", "127.0.0.1:0",
                      "--truth", str(d / "truth.csv"), "--duration", "30")

    _check(tmp_path, start, lambda d, hil: _experiment(
        d, "hil_modbus_tcp.yaml", **{"port: 5020": f"port: {hil.field('bind').rsplit(':', 1)[1]}"}))


def test_fig5_over_modbus_rtu_on_a_pty(tmp_path):
    def start(d):
        return HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "modbus-rtu", "--link", str(d / "rtu"), "--baud", "921600",
                      "--truth", str(d / "truth.csv"), "--duration", "30")

    _check(tmp_path, start, lambda d, hil: _experiment(d, "hil_modbus_rtu.yaml", **{"/tmp/mrctl-sim-rtu": str(d / "rtu")}))


# -- device pacing (loop.pacing: device, the SYNC flag): the shipped serial and
# RTU experiments use it; these run the same files with host pacing, so both
# modes stay covered over the pty transports
def test_fig5_over_serial_host_paced(tmp_path):
    def start(d):
        return HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "serial", "--link", str(d / "tty"),
                      "--truth", str(d / "truth.csv"), "--duration", "30")

    _check(tmp_path, start, lambda d, hil: _experiment(d, "hil_serial.yaml", **{
        "/tmp/mrctl-sim-tty": str(d / "tty"), "loop: {pacing: device}": "loop: {pacing: host}"}))


def test_fig5_over_modbus_tcp_device_paced(tmp_path):
    def start(d):
        return HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "modbus-tcp", "--bind", "127.0.0.1:0",
                      "--truth", str(d / "truth.csv"), "--duration", "30")

    _check(tmp_path, start, lambda d, hil: _experiment(d, "hil_modbus_tcp.yaml", **{
        "port: 5020": f"port: {hil.field('bind').rsplit(':', 1)[1]}", "loop: {pacing: host}": "loop: {pacing: device}"}))
