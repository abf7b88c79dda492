"""A law that raises, returns NaN or is slow: 0 A and an orderly fault, never a crash.

The misbehaving laws are plugins named as module:Class (tests/plugins/bad_laws.py).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mrctl.errors import ExitCode

from mrctl.cli import main
from mrctl.daemon.recorder import read_run, read_sidecar
from mrctl.core.safety import Fault
from mrctl.daemon.service import RunOptions, Service

ROOT = Path(__file__).resolve().parents[1]
FIG5 = (ROOT / "config" / "experiments" / "fig5.yaml").read_text()
LAW = int(Fault.LAW)


@pytest.fixture(autouse=True)
def _plugins_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent / "plugins"))


def _cfg(tmp_path: Path, inverse: str, demand: str | None = None) -> Path:
    text = FIG5.replace("inverse:\n  law: smooth\n  eps_N_per_A: 3.0        # hold the current where dF/dI is below ~3 N/A\n"
                        "  max_slew_A_per_s: 50.0  # current-driver slew bound: 0.05 A per 1 ms tick\n",
                        f"inverse: {inverse}\n")
    assert text != FIG5
    if demand is not None:
        text = text.replace("demand: {type: viscous, c_des: 500.0}", f"demand: {demand}")
    p = tmp_path / "exp.yaml"
    p.write_text(text)
    return p


def _run(tmp_path: Path, cfg: Path) -> tuple[Service, int, dict]:
    out = tmp_path / "run.csv"
    svc = Service(RunOptions(str(cfg), out=str(out), duration_s=3.0, live=False,
                             status_socket=str(tmp_path / "st.sock")))
    code = svc.run()
    return svc, code, read_run(out)


@pytest.mark.parametrize("cls,kind", [("Raises", "raised"), ("ReturnsNaN", "non-finite")])
def test_run_a_law_that_fails_ends_at_zero_amps_with_exit_1(tmp_path, cls, kind):
    svc, code, cols = _run(tmp_path, _cfg(tmp_path, f"{{law: 'bad_laws:{cls}', after_ticks: 200}}"))
    assert code == 1
    fault = svc.ctl.law_fault
    assert fault is not None and fault.kind == kind and fault.k == int(cols["k"][-1])
    assert "bad_laws" in fault.law or cls in fault.law
    # the run ended at the fault: that tick is the last row, commanded 0 A, LAW bit set
    assert len(cols["t"]) == 201
    assert cols["I"][-1] == 0.0 and int(cols["fault"][-1]) & LAW
    assert np.all(cols["I"][150:200] > 0.0)  # the law commanded 0.2 A before
    assert svc.exit_current_A == 0.0
    assert svc.sup.fault & Fault.LAW and svc.sup.in_fault
    side = read_sidecar(tmp_path / "run.csv")
    assert side["summary"]["law_fault"].startswith("law fault:")
    assert any("law fault" in m for m in svc.messages)


def test_run_a_demand_law_that_raises_is_named(tmp_path):
    svc, code, cols = _run(tmp_path, _cfg(tmp_path, "{law: smooth}", "{type: 'bad_laws:DemandRaises', after_ticks: 100}"))
    assert code == 1
    assert svc.ctl.law_fault.kind == "raised" and "ZeroDivisionError" in svc.ctl.law_fault.detail
    assert svc.ctl.law_fault.law == "DemandRaises"
    assert cols["I"][-1] == 0.0 and len(cols["t"]) == 101


def test_run_a_slow_law_faults_after_three_overruns(tmp_path):
    svc, code, cols = _run(tmp_path, _cfg(tmp_path, "{law: 'bad_laws:Spins', after_ticks: 100}"))
    assert code == 1
    fault = svc.ctl.law_fault
    assert fault.kind == "slow" and "3 ticks in a row" in fault.detail and "CPU time" in fault.detail
    # three slow ticks (5 ms each) after 100 good ones: the third one commands 0 A and ends the run
    assert len(cols["t"]) == 103
    assert cols["I"][-1] == 0.0 and int(cols["fault"][-1]) & LAW
    assert svc.loop.stats.summary()["overruns"] >= 3
    assert svc.exit_current_A == 0.0


def _virtual_cpu_controller(tmp_path, cpu_ms_at):
    """A controller on the sim bench whose law takes ``cpu_ms_at[k]`` ms of
    (virtual) CPU time at tick k; the wall clock is virtual too."""
    from mrctl.config import load_experiment
    from mrctl.core.controller import Controller
    from mrctl.core.safety import SafetyConfig, SafetySupervisor
    from mrctl.experiment import build
    from mrctl.laws.inverse import SmoothInverse

    exp = build(load_experiment(_cfg(tmp_path, "{law: smooth}")))
    link = exp.make_link()
    link.open()
    now = [0]

    class CostsCpu(SmoothInverse):  # an interpreted subclass of a built-in (compiled) law
        def current(self, m, F_des):
            now[0] += cpu_ms_at.get(m.k, 0) * 1_000_000
            return super().current(m, F_des)

    law = CostsCpu(exp.params, 0.6, exp.dt)
    ctl = Controller(link, law, exp.demand, SafetySupervisor(SafetyConfig(I_max=0.6)), exp.dt,
                     clock_ns=lambda: now[0], cpu_clock_ns=lambda: now[0])
    return ctl, now


def test_one_slow_tick_is_not_a_fault(tmp_path):
    """A single overrun (a preempted tick) does not stop the run."""
    ctl, now = _virtual_cpu_controller(tmp_path, {10: 2, 20: 2, 21: 2})
    for k in range(40):
        assert ctl.tick(k, now[0]) is True
    assert ctl.law_fault is None


def test_three_ticks_over_the_cpu_budget_are_a_fault_at_the_third(tmp_path):
    ctl, now = _virtual_cpu_controller(tmp_path, {30: 2, 31: 2, 32: 2})
    ends = [ctl.tick(k, now[0]) for k in range(40)]
    assert ends.index(False) == 32
    assert ctl.law_fault.kind == "slow" and ctl.law_fault.k == 32
    assert ctl.sup.last_fault_tick == 32  # one tick number for the one event


def test_a_law_that_waits_is_not_faulted_slow(tmp_path):
    """5 ms of wall time per tick spent waiting (as under preemption by another
    process) is an overrun for the loop, not a law fault: the budget is CPU time."""
    svc, code, cols = _run(tmp_path, _cfg(tmp_path, "{law: 'bad_laws:Sleeps', after_ticks: 100}"))
    assert svc.ctl.law_fault is None, svc.ctl.law_fault
    assert code == ExitCode.DEGRADED  # the skipped deadlines break the run's acceptance bound, not the law
    assert svc.loop.stats.summary()["overruns"] >= 3


@pytest.mark.parametrize("law, what", [
    ("ExitsProcess", "SystemExit"), ("GeneratorExits", "GeneratorExit"), ("Interrupts", "KeyboardInterrupt"),
    ("ReturnsComplex", "complex"), ("ReturnsArray", "ndarray"),
])
def test_run_a_law_raising_a_base_exception_or_returning_a_non_float_is_a_law_fault(tmp_path, law, what):
    svc, code, cols = _run(tmp_path, _cfg(tmp_path, f"{{law: 'bad_laws:{law}', after_ticks: 100}}"))
    assert code == 1
    fault = svc.ctl.law_fault
    assert fault is not None and fault.kind == "raised" and fault.k == int(cols["k"][-1])
    assert what in fault.detail
    assert len(cols["t"]) == 101 and cols["I"][-1] == 0.0 and int(cols["fault"][-1]) & LAW
    assert svc.exit_current_A == 0.0
    assert read_sidecar(tmp_path / "run.csv")["complete"] is True


def test_simulate_a_law_that_raises_exits_1_at_zero_amps(tmp_path, capsys):
    cfg = _cfg(tmp_path, "{law: 'bad_laws:Raises', after_ticks: 300}")
    out = tmp_path / "sim.csv"
    assert main(["simulate", str(cfg), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "law fault" in err and "RuntimeError: boom from a plugin" in err and "tick 300" in err
    data = np.genfromtxt(out, delimiter=",", names=True)  # a plain CSV: the header first
    assert len(data) == 301 and data["I"][-1] == 0.0 and data["I"][-2] > 0.0


def test_simulate_nan_is_a_fault_on_the_quarter_car_too(tmp_path, capsys):
    text = _cfg(tmp_path, "{law: 'bad_laws:ReturnsNaN', after_ticks: 50}").read_text()
    (tmp_path / "exp.yaml").write_text(text.replace("plant: {driver_tau_s: 0.0}", "plant: {bench: quarter_car}"))
    assert main(["simulate", str(tmp_path / "exp.yaml")]) == 1
    assert "returned a non-finite value at tick 50" in capsys.readouterr().err



def test_offline_fault_kinds_name_the_law_and_tick():
    """mrctl/laws/guard.py: what both offline loops turn a caught exception into."""
    from mrctl.laws.base import NonFiniteOutput
    from mrctl.laws.guard import law_fault

    f = law_fault(NonFiniteOutput("I = nan"), "lawname", 7, 0.007)
    assert (f.kind, f.law, f.k, f.t, f.detail) == ("non-finite", "lawname", 7, 0.007, "I = nan")
    f = law_fault(KeyError("x"), "demandname", 3, 0.003)
    assert (f.kind, f.law, f.detail) == ("raised", "demandname", "KeyError: 'x'")


@pytest.mark.parametrize("bench", ["shaker", "quarter_car"])
def test_simulate_a_law_whose_applied_raises_is_a_fault_not_a_crash(tmp_path, capsys, bench):
    """The clamp tells the law what was commanded (applied); if that raises,
    the run ends at 0 A with a law fault in both offline loops."""
    text = _cfg(tmp_path, "{law: 'bad_laws:AppliedRaises', after_ticks: 40}").read_text()
    if bench == "quarter_car":
        text = text.replace("plant: {driver_tau_s: 0.0}", "plant: {bench: quarter_car}")
    (tmp_path / "exp.yaml").write_text(text)
    out = tmp_path / "sim.csv"
    assert main(["simulate", str(tmp_path / "exp.yaml"), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "raised at tick 40" in err and "RuntimeError: applied() lost its state" in err
    data = np.genfromtxt(out, delimiter=",", names=True)
    assert len(data) == 41 and data["I"][-1] == 0.0


def _mrctl(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent / "plugins"), str(ROOT)])}
    return subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=300)


def test_simulate_a_ctrl_c_inside_a_law_is_the_users_stop_not_a_law_fault(tmp_path):
    """The signal lands while a (Python) law computes: mrctl simulate stops as
    interrupted (exit 130, nothing left behind), not 'law raised KeyboardInterrupt'."""
    cfg = _cfg(tmp_path, "{law: 'bad_laws:CtrlC', after_ticks: 300}")
    p = _mrctl(tmp_path, "simulate", str(cfg), "--out", str(tmp_path / "sim.csv"))
    assert p.returncode == ExitCode.INTERRUPTED, p.stderr
    assert "interrupted" in p.stderr and "law" not in p.stderr, p.stderr
    assert not (tmp_path / "sim.csv").exists() and not (tmp_path / "sim.json").exists()


def test_sweep_a_ctrl_c_inside_a_law_stops_the_sweep_and_records_no_fault(tmp_path):
    """In-process points (--workers 1): the point under way is not written as a
    law fault and the sweep does not go on; the table holds the points before."""
    cfg = _cfg(tmp_path, "{law: 'bad_laws:CtrlC', after_ticks: 300}")
    cfg.write_text(cfg.read_text().replace("duration_s: 4.0", "duration_s: 0.5"))
    sweep = tmp_path / "s.yaml"
    sweep.write_text("version: 1\nname: s\nbase: exp.yaml\ngrid:\n  demand.c_des: [100, 200, 300]\n"
                     "metrics: [force_nrmse]\n")
    out = tmp_path / "t.csv"
    p = _mrctl(tmp_path, "sweep", str(sweep), "--out", str(out), "--workers", "1", "--no-progress")
    assert p.returncode == 0 and "interrupted" in p.stderr and "resume" in p.stderr, p.stderr
    table = out if out.exists() else out.with_name(out.name + ".partial.csv")
    rows = table.read_text().splitlines()[1:] if table.exists() else []
    assert all("KeyboardInterrupt" not in r and ",fault," not in r for r in rows), rows
    assert len(rows) < 3


def test_run_a_stop_noted_by_an_earlier_command_never_frees_a_laws_keyboard_interrupt(tmp_path, monkeypatch):
    """The note of a user's stop is for the offline loop only: in the daemon a
    law's own KeyboardInterrupt is its fault (exit 1, latched, 0 A), even if an
    earlier command in this process (a test, a script calling cli.main) was
    stopped by Ctrl-C and left the note set."""
    from mrctl.util import interrupt

    monkeypatch.setitem(interrupt._state, "signum", 2)
    svc, code, cols = _run(tmp_path, _cfg(tmp_path, "{law: 'bad_laws:Interrupts', after_ticks: 100}"))
    assert code == 1 and svc.ctl.law_fault is not None and "KeyboardInterrupt" in svc.ctl.law_fault.detail
    assert cols["I"][-1] == 0.0 and int(cols["fault"][-1]) & LAW and svc.exit_current_A == 0.0
