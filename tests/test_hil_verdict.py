"""Done-when of the verdict over a real link: a HIL run whose device stops
answering for 0.3 s (hil_sim SIGSTOPped mid-run) ends with exit 5 and a
sidecar ``verdict: degraded`` naming the share of ticks in fault and the time
latched (the stop is longer than the shipped ``latch_after_s`` 0.25 s, so the
run stays at 0 A until ``mrctl arm``, which nobody sends here); the same run
left alone exits 0 with ``verdict: ok``. Modbus TCP at 200 Hz (hil_util),
the shipped experiment's safety settings (link_loss_s 0.5 s rides through
the stop), the acceptance defaults for faults and forced 0 A loosened only
as far as a loaded CI machine needs for the clean run."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from hil_sim.testing.harness import Run
from hil_util import HIL_TEST_RATE_HZ, ROOT, HilSim, experiment_at_test_rate
from mrctl.core.safety import Fault
from mrctl.daemon.recorder import read_run, read_sidecar

pytestmark = pytest.mark.hil
EXP = ROOT / "config" / "experiments" / "hil_modbus_tcp.yaml"
BENCH = str(ROOT / "config" / "hil_fig5_bench.yaml")
#: the clean run must meet these on a loaded machine; a 0.3 s stop of the
#: device breaks both (about 10 % of a 3 s run in fault, one 0.3 s stretch)
ACCEPTANCE = {"max_fault_share": 0.05, "max_zero_stretch_s": 0.25, "max_skipped_share": 1.0, "max_gap_s": 3600.0,
              # the tracking at the test's 200 Hz on a shared machine is bench/'s figure, not this test's subject
              "max_force_nrmse": None}
RUN_S = 3.0


def _run(tmp_path, stop_s: float | None):
    hil = HilSim("--config", BENCH, "--transport", "modbus-tcp", "--bind", "127.0.0.1:0", "--duration", "60")
    try:
        port = hil.field("bind").rsplit(":", 1)[1]
        cfg = experiment_at_test_rate(EXP, tmp_path, acceptance=ACCEPTANCE, **{"port: 5020": f"port: {port}"})
        run = Run(cfg, tmp_path / "run.csv", RUN_S)
        st = None
        if stop_s is not None:
            st = run.wait_for(lambda s: s.get("ticks", 0) >= 200, timeout_s=60.0)  # 1 s into the loop
            assert st is not None, run.stderr()
            os.kill(hil.proc.pid, signal.SIGSTOP)
            try:
                time.sleep(stop_s)
            finally:
                os.kill(hil.proc.pid, signal.SIGCONT)
        code = run.wait(timeout_s=120.0)
    finally:
        hil.stop()
    return code, run.stderr(), read_sidecar(tmp_path / "run.csv"), st


def test_device_stopped_for_0_3_s_mid_run_is_degraded_naming_the_fault_share(tmp_path):
    code, err, side, at_stop = _run(tmp_path, stop_s=0.3)
    assert code == 5, err
    assert side["verdict"] == "degraded" and side["exit_code"] == 5
    reasons = side["verdict_reasons"]
    print("verdict:", side["verdict"], reasons)
    assert reasons and reasons[0].startswith("ticks in fault "), reasons
    assert "acceptance.max_fault_share" in reasons[0]
    assert "verdict: degraded: ticks in fault" in err
    assert any(r.startswith("time latched") and "acceptance.max_latched_s" in r for r in reasons), reasons
    figs = side["summary"]["acceptance"]["figures"]
    # latched 0.25 s into the stop and never re-armed: the rest of the run at 0 A, as its own rows show
    cols = read_run(tmp_path / "run.csv")
    k, I, fault = cols["k"], np.nan_to_num(cols["I"]), np.nan_to_num(cols["fault"]).astype(int)
    latched = (fault & int(Fault.LATCHED)) != 0
    first = int(np.argmax(latched))
    assert latched[first] and latched[first:].all() and (I[first:] == 0.0).all()
    assert k[first] >= at_stop["ticks"]  # latched by the stop, not before it
    # the time latched: the ticks from the first latched row to the end of the run (a skipped
    # deadline is no tick), and the share in fault the rows' own; neither depends on when the stop landed
    n, dt = len(k), 1.0 / HIL_TEST_RATE_HZ
    assert figs["latched_s"] == pytest.approx((n - first) * dt, abs=2 * dt), (figs, n - first)
    assert figs["fault_share"] == pytest.approx(np.count_nonzero(fault) / n, abs=2 / n), (figs, n)
    assert figs["fault_share"] >= (n - first - 2) / n, figs  # the latched ticks are in fault
    assert side["summary"]["safety"]["latches"] == 1 and side["summary"]["safety"]["arms"] == 0


def test_the_same_run_left_alone_exits_0_with_verdict_ok(tmp_path):
    code, err, side, _ = _run(tmp_path, stop_s=None)
    assert code == 0, err
    assert side["verdict"] == "ok" and side["verdict_reasons"] == [] and side["exit_code"] == 0
    link = side["summary"]["link"]
    assert link["frame_errors"] + link["device_errors"] == 0, link
