"""A run's verdict: bounds from the experiment, exit 5 when degraded, the
sidecar, stderr, status and check say which bound and by how much."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from mrctl.cli import main
from mrctl.config import ConfigError, load_experiment
from mrctl.config.acceptance import AUTO_FORCE_NRMSE
from mrctl.daemon.recorder import read_sidecar
from mrctl.daemon.service import RunOptions, Service
from mrctl.runlog.acceptance import format_verdict, judge, row_figures

ROOT = Path(__file__).resolve().parents[1]
FIG5 = (ROOT / "config" / "experiments" / "fig5.yaml").read_text()
OPEN_TIMING = "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n"  # real-clock runs on a shared machine


class VirtualClock:
    """1 µs per reading, exactly what is slept; ``stall_at_ns`` adds one stall."""

    def __init__(self, stall_at_ns: int | None = None, stall_ns: int = 0) -> None:
        self.t = 0
        self.stall_at, self.stall_ns = stall_at_ns, stall_ns

    def now(self) -> int:
        self.t += 1000
        if self.stall_at is not None and self.t >= self.stall_at:
            self.t += self.stall_ns
            self.stall_at = None
        return self.t

    def sleep(self, s: float) -> None:
        self.t += int(s * 1e9)


def _cfg(tmp_path: Path, text: str = FIG5, extra: str = "") -> Path:
    p = tmp_path / "exp.yaml"
    p.write_text(text + extra)
    return p


def _run(cfg: Path, tmp_path: Path, duration: float = 1.0, clock: VirtualClock | None = None):
    clock = clock or VirtualClock()
    out, err, say = tmp_path / "run.csv", io.StringIO(), io.StringIO()
    svc = Service(RunOptions(str(cfg), out=str(out), duration_s=duration, live=False, clock_ns=clock.now,
                             sleep=clock.sleep, status_socket=str(tmp_path / "s.sock"), err=err, stream=say))
    code = svc.run()
    return svc, code, out, err.getvalue(), say.getvalue()


# -- the judgement ---------------------------------------------------------------
def test_row_figures_count_skipped_ticks_inside_a_forced_zero_stretch():
    k = np.array([0, 1, 2, 3, 10, 11, 12, 13], float)  # ticks 4-9 skipped while at 0 A
    x = np.array([0, 0, 0, math.nan, math.nan, 0, 0, 0])
    fault = np.array([0, 0, 0, 1, 1, 1, 0, 0], float)  # the fault clears one tick after x returns
    f = row_figures({"t": k * 1e-3, "x": x, "k": k, "fault": fault}, 1e-3)
    assert f["fault_share"] == pytest.approx(3 / 8)
    assert f["longest_zero_stretch_s"] == pytest.approx(9e-3)  # from tick 3 to tick 12
    assert f["longest_gap_s"] == pytest.approx(7e-3)


def test_judge_names_the_bound_and_the_excess_and_skips_what_is_not_measured():
    b = {"max_fault_share": 0.02, "max_skipped_share": 0.05, "max_gap_s": 0.1, "max_zero_stretch_s": 0.1,
         "max_force_nrmse": None}
    v = judge({"fault_share": 0.094, "longest_gap_s": 0.05, "force_nrmse": 0.106, "skipped_share": math.nan}, b, 1e-3)
    assert v["verdict"] == "degraded"
    assert v["reasons"] == ["ticks in fault 9.4 % > 2.0 % (acceptance.max_fault_share: by 7.4 %)"]
    assert v["figures"]["skipped_share"] is None
    assert judge({"fault_share": 0.0}, b, 1e-3)["verdict"] == "ok"
    # the gap bound is never tighter than two periods (a rate reduced to 10 Hz)
    assert judge({"longest_gap_s": 0.15}, b, 0.1)["verdict"] == "ok"
    assert format_verdict(judge({"fault_share": 0.0}, b, 1e-3)) == "verdict: ok (ticks in fault 0.0 %)"


def test_bounds_are_validated_with_their_key_paths(tmp_path):
    with pytest.raises(ConfigError, match=r"acceptance\.max_fault_share"):
        load_experiment(_cfg(tmp_path, extra="acceptance: {max_fault_share: 2}\n"))
    with pytest.raises(ConfigError, match=r"acceptance\.max_gap"):
        load_experiment(_cfg(tmp_path, extra="acceptance: {max_gap: 0.1}\n"))


# -- mrctl run ---------------------------------------------------------------------
def test_a_clean_run_exits_0_with_verdict_ok(tmp_path):
    svc, code, out, err, said = _run(_cfg(tmp_path), tmp_path, duration=2.0)
    assert code == 0, err
    side = read_sidecar(out)
    assert side["verdict"] == "ok" and side["verdict_reasons"] == [] and side["exit_code"] == 0
    acc = side["summary"]["acceptance"]
    assert acc["figures"]["fault_share"] == 0.0 and acc["figures"]["skipped_share"] == 0.0
    assert acc["figures"]["force_nrmse"] < 0.01 and acc["bounds"]["max_fault_share"] == 0.02
    assert "verdict: ok" in said


def test_a_run_in_fault_a_fifth_of_the_time_exits_5_and_says_by_how_much(tmp_path):
    cfg = _cfg(tmp_path, FIG5.replace("safety: {I_max: 0.6}",
                                      "safety: {I_max: 0.6, x_range_m: [-0.008, 0.008], auto_resume: true}"))
    svc, code, out, err, _ = _run(cfg, tmp_path, duration=2.0)
    assert code == 5
    side = read_sidecar(out)
    assert side["verdict"] == "degraded" and side["exit_code"] == 5 and side["summary"]["exit_code"] == 5
    reasons = side["verdict_reasons"]
    assert reasons[0].startswith("ticks in fault ") and "(acceptance.max_fault_share: by " in reasons[0]
    share = side["summary"]["acceptance"]["figures"]["fault_share"]
    assert share == pytest.approx(side["summary"]["safety"]["ticks_in_fault"] / side["summary"]["ticks"])
    assert "verdict: degraded: ticks in fault" in err
    # mrctl status (the end state of the run) says it too
    from mrctl.daemon.status import format_status

    assert "acceptance so far: verdict: degraded: ticks in fault" in format_status(svc.snapshot())


def test_a_stalled_loop_exits_5_naming_the_gap_and_the_skipped_deadlines(tmp_path):
    clock = VirtualClock(stall_at_ns=500_000_000, stall_ns=150_000_000)  # 150 ms stall at 0.5 s
    svc, code, out, err, _ = _run(_cfg(tmp_path), tmp_path, duration=1.5, clock=clock)
    assert code == 5
    reasons = read_sidecar(out)["verdict_reasons"]
    assert any(r.startswith("longest gap between tick starts 15") and "max_gap_s" in r for r in reasons), reasons
    assert any(r.startswith("deadlines skipped") for r in reasons), reasons
    assert not any(r.startswith("ticks in fault") for r in reasons)  # the sim bench has no link to lose


def test_tracking_bound_is_judged_when_set(tmp_path):
    # 2 s: past fig5's 1 s settling window (a run all start-up transient is not judged on tracking)
    svc, code, out, err, _ = _run(_cfg(tmp_path, extra="acceptance: {max_force_nrmse: 0.0001}\n"), tmp_path, 2.0)
    assert code == 5
    assert read_sidecar(out)["verdict_reasons"][0].startswith("force NRMSE ")
    short = tmp_path / "short"
    short.mkdir()
    svc, code, out, err, _ = _run(_cfg(short, extra="acceptance: {max_force_nrmse: 0.0001}\n"), short, 0.5)
    assert code == 0, err  # shorter than its settling window: tracking not judged


# -- simulate, check, the default log ---------------------------------------------------
def test_simulate_is_judged_on_what_it_has(tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["simulate", str(_cfg(tmp_path)), "--out", str(out), "--duration", "2"]) == 0
    assert read_sidecar(out)["verdict"] == "ok"
    assert "verdict: ok" in capsys.readouterr().out
    cfg = _cfg(tmp_path, extra="acceptance: {max_force_nrmse: 0.0001}\n")
    assert main(["simulate", str(cfg), "--out", str(out), "--force", "--duration", "2"]) == 5
    side = read_sidecar(out)
    assert side["verdict"] == "degraded" and side["exit_code"] == 5
    assert "longest_gap_s" not in side["summary"]["acceptance"]["figures"]  # no clock offline
    assert "verdict: degraded: force NRMSE" in capsys.readouterr().err


def test_check_prints_the_bounds(tmp_path, capsys):
    assert main(["check", str(_cfg(tmp_path, extra="acceptance: {max_fault_share: 0.1}\n"))]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("acceptance:"))
    assert "max_fault_share 10.0 %" in line and "max_gap_s 100 ms" in line
    assert f"max_force_nrmse {100 * AUTO_FORCE_NRMSE:.1f} %" in line  # fig5's law tracks force: the auto bound


def test_run_without_out_logs_under_runs_and_says_so_first(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    cfg = _cfg(tmp_path, extra=OPEN_TIMING)
    assert main(["run", str(cfg), "--duration", "0.2", "--quiet", "--status-socket", str(tmp_path / "s")]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("run log: runs/fig5-") and first.endswith(".csv")
    logs = list((tmp_path / "runs").glob("fig5-*.csv"))
    assert len(logs) == 1 and logs[0].with_suffix(".json").exists()
    assert json.loads(logs[0].with_suffix(".json").read_text())["verdict"] == "ok"
    assert main(["run", str(cfg), "--duration", "0.2", "--quiet", "--no-log",
                 "--status-socket", str(tmp_path / "s")]) == 0
    assert capsys.readouterr().out.splitlines()[0].startswith("no run log (--no-log)")
    assert len(list((tmp_path / "runs").glob("*.csv"))) == 1
    assert main(["run", str(cfg), "--no-log", "--out", "x.csv"]) == 2


def test_help_lists_exit_code_5(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    assert "  5  run completed but degraded" in capsys.readouterr().out
