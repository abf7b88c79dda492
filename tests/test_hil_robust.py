"""Loopback HIL with the closed law on benches that are not its model.

hil_sim runs the mismatched damper (Table I off by 15-30 %) or the Bouc–Wen
damper; the daemon runs the closed law over the serial protocol and over
Modbus TCP. Here: the loop is closed and corrected over a real link (the
NRMSE beats what the smooth law reaches on that bench even in simulation),
0 A reaches the device on the way out, the log is complete. The "within
1.5x of simulate" figure is measured by bench/hil_robust.py (medians over
repeated runs; docs/inverse-laws.md).
"""

from pathlib import Path

import pytest

from hil_util import (ROOT, HilSim, expected_rows, experiment_at_test_rate, hil_tracking, protocol_errors,
                      run_hil as _run_hil)
from mrctl.daemon.recorder import read_run, read_sidecar

pytestmark = pytest.mark.hil
EXP = ROOT / "config" / "experiments"
#: smooth on these benches, in simulation at 1 kHz: 5.6 % (mismatch), 2.9 % (Bouc-Wen). The tests run
#: the daemon at 200 Hz (hil_util), host-paced against the bench's own 1 kHz clock: measured on
#: 2026-11-25 1.16-1.55 % (mismatch, Modbus TCP) and 2.2-2.6 % (Bouc-Wen, serial) on a quiet machine,
#: up to 4.5 % (Bouc-Wen) with a sixth of the deadlines skipped at load average 5-7 on 2 cores. The
#: mismatch bound still says "corrected beyond smooth"; the Bouc-Wen bound only "a closed, stable loop
#: over the link" (the 1.5x-of-simulate figures are bench/hil_robust.py's, on a quiet host)
BOUND = {"mismatch": 0.035, "bouc_wen": 0.05}
BENCH = {"mismatch": ROOT / "config" / "hil_mismatch_bench.yaml",
         "bouc_wen": ROOT / "config" / "hil_bouc_wen_bench.yaml"}
PARAMS = {"mismatch": "parameters: table1", "bouc_wen": "parameters: {tau_input: 0.005}"}


def _experiment(d: Path, name: str, bench: str, **replace: str) -> Path:
    return experiment_at_test_rate(EXP / name, d, **{"parameters: table1": PARAMS[bench], **replace})


def _check(tmp_path, bench, start, make_cfg):
    d, cfg, res, code = _run_hil(tmp_path, start, make_cfg)
    assert code == 0
    out = d / "run.csv"
    side = read_sidecar(out)
    assert side["complete"] is True and side["summary"]["exit_current_A"] == 0.0
    assert side["rows_written"] == side["summary"]["ticks"]
    bad, exchanges = protocol_errors(side)
    assert exchanges > 0.5 * expected_rows(side) and bad <= 0.01 * exchanges, side["summary"]["link"]
    truth = read_run(d / "truth.csv")
    tr = hil_tracking(read_run(out), truth)
    print(f"{bench}/{cfg.name}: HIL force NRMSE {100 * tr['nrmse']:.3f} % over {tr['rows']} ticks, "
          f"skipped deadlines {side['summary']['timing']['skipped_deadlines']}")
    assert tr["rows"] > 0.3 * expected_rows(side) and tr["nrmse"] < BOUND[bench], tr
    assert truth["I_cmd"][-1] == 0.0
    assert not any("no load-cell force" in m for m in side["summary"]["messages"])


def test_closed_law_over_serial_against_the_bouc_wen_bench(tmp_path):
    def start(d):
        return HilSim("--config", str(BENCH["bouc_wen"]), "--transport", "serial", "--link", str(d / "tty"),
                      "--truth", str(d / "truth.csv"), "--duration", "30")

    _check(tmp_path, "bouc_wen", start, lambda d, hil: _experiment(
        d, "hil_closed_serial.yaml", "bouc_wen", **{"/tmp/mrctl-sim-tty": str(d / "tty"),
                                                     "loop: {pacing: device}": "loop: {pacing: host}"}))


def test_closed_law_over_modbus_tcp_against_the_mismatched_bench(tmp_path):
    def start(d):
        return HilSim("--config", str(BENCH["mismatch"]), "--transport", "modbus-tcp", "--bind", "127.0.0.1:0",
                      "--truth", str(d / "truth.csv"), "--duration", "30")

    _check(tmp_path, "mismatch", start, lambda d, hil: _experiment(
        d, "hil_closed_modbus_tcp.yaml", "mismatch",
        **{"port: 5020": f"port: {hil.field('bind').rsplit(':', 1)[1]}"}))
