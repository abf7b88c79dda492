"""Every exit code of every command, driven (docs/cli.md, "Exit codes";
``mrctl.runlog.format.COMMAND_EXITS`` is the table, each command's --help
prints its row). The table and this file are checked against each other: a
code added to the table without a driver here fails, and so does a driver
for a code the table does not give.

A run that runs until stopped is stopped by SIGINT/SIGTERM here as a user
would: exit 0, and the run's sidecar says which signal and how long it ran
of how long it was asked to."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest
import yaml

import mrctl.cli as cli
from hil_sim.testing.harness import env
from hil_sim.testing.peers import free_port
from mrctl.cli import main
from mrctl.runlog.format import COMMAND_EXITS

ROOT = Path(__file__).resolve().parents[1]
EXP = ROOT / "config" / "experiments"
FIG5 = EXP / "fig5.yaml"
#: a real clock on a shared machine: timing is bench/'s figure, not these tests' subject
LOOSE = {"max_skipped_share": 1.0, "max_gap_s": 3600.0}
DRIVEN: dict[tuple[str, int], Callable[..., None]] = {}


def drives(command: str, code: int):
    def put(f):
        DRIVEN[(command, code)] = f
        return f
    return put


def _fig5(tmp_path: Path, **changes) -> Path:
    data = yaml.safe_load(FIG5.read_text())
    data["acceptance"] = {**LOOSE, **changes.pop("acceptance", {})}
    data.update(changes)
    p = tmp_path / "fig5.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def _mrctl(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mrctl", *args], cwd=kw.pop("cwd", ROOT), env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _internal(command: str, argv: list[str]):
    """Code 1, the internal error: the command's handler raises what no handler expects."""
    def driver(tmp_path, capsys, monkeypatch):
        def boom(args):
            raise RuntimeError("a bug")
        monkeypatch.setattr(cli, f"cmd_{command}", boom)
        assert main([command, *argv]) == 1
        err = capsys.readouterr().err
        assert "internal error: RuntimeError: a bug" in err and "Traceback" not in err
    return driver


for _cmd, _argv in {"run": [str(FIG5)], "simulate": [str(FIG5)], "sweep": ["s.yaml"], "report": ["r.csv"],
                    "identify": ["r.csv"], "calibrate": [str(FIG5)], "check": [str(FIG5)], "status": [], "ls": [],
                    "tap": [], "arm": [], "exporter": [], "examples": ["d"], "docs": [],
                    "device": ["disarm", str(FIG5)]}.items():
    DRIVEN[(_cmd, 1)] = _internal(_cmd, _argv)


def _interrupted(command: str, where: str, argv: Callable[[Path], list[str]]):
    """Code 130: a one-shot command interrupted by Ctrl-C while it works: nothing written."""
    def driver(tmp_path, capsys, monkeypatch):
        import importlib

        mod, _, name = where.rpartition(".")

        def ctrl_c(*a, **k):
            raise KeyboardInterrupt
        monkeypatch.setattr(importlib.import_module(mod), name, ctrl_c)
        args = argv(tmp_path)
        before = set(tmp_path.rglob("*"))
        assert main([command, *args]) == 130
        assert "interrupted: nothing written" in capsys.readouterr().err
        assert set(tmp_path.rglob("*")) == before
    return driver


DRIVEN[("simulate", 130)] = _interrupted("simulate", "mrctl.offline.simulate_log.simulate_blocks",
                                         lambda d: [str(FIG5), "--out", str(d / "x.csv")])
DRIVEN[("report", 130)] = _interrupted("report", "mrctl.offline.report.build_figure",
                                       lambda d: [str(_sim(d)), "--out", str(d / "x.png")])
DRIVEN[("identify", 130)] = _interrupted("identify", "mrctl.offline.identify_command.identify_command",
                                         lambda d: [str(_sim(d))])
DRIVEN[("calibrate", 130)] = _interrupted("calibrate", "mrctl.daemon.calibrate.run_from_args",
                                          lambda d: [str(FIG5), "--out", str(d / "c.yaml")])


def _sim(d: Path, seconds: str = "0.3") -> Path:
    out = d / "sim.csv"
    if not out.exists():
        assert main(["simulate", str(FIG5), "--duration", seconds, "--out", str(out), "-q"]) == 0
    return out


# -- run ------------------------------------------------------------------------------------------------------------
@drives("run", 0)
def _run_0(tmp_path, capsys, monkeypatch):
    """Its duration, then SIGINT and SIGTERM mid-run: 0 each time, the sidecar says how it ended."""
    out = tmp_path / "a.csv"
    assert main(["run", str(_fig5(tmp_path)), "--duration", "0.3", "--out", str(out), "-q",
                 "--socket", str(tmp_path / "a.sock")]) == 0
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["interrupted"] is None and side["requested_duration_s"] == 0.3
    assert side["actual_duration_s"] == pytest.approx(0.3, abs=0.01)
    for sig in (signal.SIGINT, signal.SIGTERM):
        out = tmp_path / f"{sig.name}.csv"
        p = _mrctl("run", str(_fig5(tmp_path)), "--duration", "20", "--out", str(out), "-q",
                   "--socket", str(tmp_path / f"{sig.name}.sock"))
        _wait_rows(out)
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 0, err
        side = json.loads(out.with_suffix(".json").read_text())
        assert side["interrupted"] == sig.name and side["requested_duration_s"] == 20.0
        assert 0.1 < side["actual_duration_s"] < 15.0 and side["exit_code"] == 0 and side["verdict"] == "ok"


def _wait_rows(out: Path, timeout_s: float = 30.0) -> None:
    """Until the run log has rows (the loop runs)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if out.exists() and out.stat().st_size > 4096:
            return
        time.sleep(0.05)
    raise AssertionError(f"{out}: no rows within {timeout_s} s")


@drives("run", 2)
def _run_2(tmp_path, capsys, monkeypatch):
    assert main(["run", str(tmp_path / "none.yaml"), "--no-log"]) == 2


@drives("run", 3)
def _run_3(tmp_path, capsys, monkeypatch):
    cfg = tmp_path / "serial.yaml"
    cfg.write_text((EXP / "hil_serial.yaml").read_text().replace("/tmp/mrctl-sim-tty", str(tmp_path / "no-tty")))
    assert main(["run", str(cfg), "--no-log", "--socket", str(tmp_path / "s.sock")]) == 3
    assert "no-tty" in capsys.readouterr().err


@drives("run", 4)
def _run_4(tmp_path, capsys, monkeypatch):
    from test_disk_full import _failing_log

    _failing_log(monkeypatch, ok_lines=51)
    out = tmp_path / "r.csv"
    assert main(["run", str(_fig5(tmp_path)), "--duration", "1.0", "--out", str(out), "-q",
                 "--socket", str(tmp_path / "r.sock")]) == 4
    assert json.loads(out.with_suffix(".json").read_text())["dropped_rows"] > 0


@drives("run", 5)
def _run_5(tmp_path, capsys, monkeypatch):
    cfg = _fig5(tmp_path, acceptance={"max_force_nrmse": 1e-6})
    assert main(["run", str(cfg), "--duration", "2.5", "--out", str(tmp_path / "r.csv"), "-q",
                 "--socket", str(tmp_path / "r.sock")]) == 5
    assert "acceptance.max_force_nrmse" in capsys.readouterr().err


# -- simulate -------------------------------------------------------------------------------------------------------
@drives("simulate", 0)
def _simulate_0(tmp_path, capsys, monkeypatch):
    assert main(["simulate", str(FIG5), "--duration", "0.2"]) == 0


@drives("simulate", 2)
def _simulate_2(tmp_path, capsys, monkeypatch):
    assert main(["simulate", "--replay", str(tmp_path / "none.csv")]) == 2


@drives("simulate", 4)
def _simulate_4(tmp_path, capsys, monkeypatch):
    # the file size limit stands in for a full disk (EFBIG where ENOSPC would be): the log
    # streams while the loop runs (tests/test_simulate_stream.py), so a later block fails
    import subprocess
    import sys

    code = ("import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            "resource.setrlimit(resource.RLIMIT_FSIZE, (3_000_000, 3_000_000)); "
            "from mrctl.cli import main; sys.exit(main(sys.argv[1:]))")
    res = subprocess.run([sys.executable, "-c", code, "simulate", str(FIG5), "--duration", "100",
                          "--out", str(tmp_path / "x.csv")], capture_output=True, text=True, timeout=300)
    assert res.returncode == 4, res.stderr


@drives("simulate", 5)
def _simulate_5(tmp_path, capsys, monkeypatch):
    assert main(["simulate", str(_fig5(tmp_path, acceptance={"max_force_nrmse": 1e-6})), "--duration", "2.5"]) == 5


# -- sweep ----------------------------------------------------------------------------------------------------------
def _sweep(tmp_path: Path, n: int, seconds: float = 0.3) -> Path:
    p = tmp_path / "s.yaml"
    base = tmp_path / "base.yaml"
    base.write_text(FIG5.read_text().replace("duration_s: 4.0", f"duration_s: {seconds}"))
    p.write_text(f"version: 1\nname: s\nbase: base.yaml\n"
                 f"grid:\n  demand.c_des: {list(range(100, 100 + 10 * n, 10))}\nmetrics: [force_nrmse]\n")
    return p


@drives("sweep", 0)
def _sweep_0(tmp_path, capsys, monkeypatch):
    """Done; and SIGINT, SIGTERM mid-sweep: 0, a valid partial table that the same command resumes."""
    assert main(["sweep", str(_sweep(tmp_path, 2)), "--out", str(tmp_path / "a.csv"), "--workers", "1",
                 "--allow-outside-paths", "-q"]) == 0
    for sig in (signal.SIGINT, signal.SIGTERM):
        out = tmp_path / f"{sig.name}.csv"
        p = _mrctl("sweep", str(_sweep(tmp_path, 5000, seconds=2.0)), "--out", str(out), "--workers", "1",
                   "--allow-outside-paths", "--no-progress")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (out.with_name(out.name + ".partial.csv").exists()
                                                   or out.exists()):
            time.sleep(0.05)
        time.sleep(0.5)
        p.send_signal(sig)
        _, err = p.communicate(timeout=120)  # the points under way finish first
        assert p.returncode == 0, err
        assert "interrupted" in err and "resume" in err, err
        assert out.exists() or out.with_name(out.name + ".partial.csv").exists()


@drives("sweep", 2)
def _sweep_2(tmp_path, capsys, monkeypatch):
    assert main(["sweep", str(tmp_path / "none.yaml"), "--out", str(tmp_path / "x.csv")]) == 2


@drives("sweep", 3)
def _sweep_3(tmp_path, capsys, monkeypatch):
    assert main(["sweep", str(_sweep(tmp_path, 2)), "--out", str(tmp_path / "x.csv"), "--allow-outside-paths",
                 "--scheduler", f"tcp://127.0.0.1:{free_port()}", "-q"]) == 3  # a port nobody listens on


# -- report, identify, calibrate, check ----------------------------------------------------------------------------
@drives("report", 0)
def _report_0(tmp_path, capsys, monkeypatch):
    assert main(["report", str(_sim(tmp_path)), "--out", str(tmp_path / "r.png")]) == 0


@drives("report", 2)
def _report_2(tmp_path, capsys, monkeypatch):
    assert main(["report", str(tmp_path / "none.csv")]) == 2


@drives("identify", 0)
def _identify_0(tmp_path, capsys, monkeypatch):
    from test_identify import staircase, write_run_csv

    run = write_run_csv(tmp_path / "run.csv", staircase([0.0, 0.25, 0.5], step_s=2.0))
    assert main(["identify", str(run), "--out", str(tmp_path / "p.yaml"), "--no-progress"]) == 0, \
        capsys.readouterr().err
    assert (tmp_path / "p.yaml").is_file()


@drives("identify", 2)
def _identify_2(tmp_path, capsys, monkeypatch):
    assert main(["identify", str(tmp_path / "none.csv")]) == 2


@drives("calibrate", 0)
def _calibrate_0(tmp_path, capsys, monkeypatch):
    from test_labjack_t7 import _bench, _exp_for, _start

    hil, port = _start(tmp_path, _bench(tmp_path, rest=True))
    try:
        code = main(["calibrate", str(_exp_for(tmp_path, port)), "--out", str(tmp_path / "cal.yaml")])
    finally:
        hil.stop()
    assert code == 0, capsys.readouterr().err


@drives("calibrate", 2)
def _calibrate_2(tmp_path, capsys, monkeypatch):
    assert main(["calibrate", str(tmp_path / "none.yaml")]) == 2


@drives("calibrate", 3)
def _calibrate_3(tmp_path, capsys, monkeypatch):
    from test_labjack_t7 import _exp_for

    assert main(["calibrate", str(_exp_for(tmp_path, free_port())), "--out", str(tmp_path / "cal.yaml")]) == 3


@drives("check", 0)
def _check_0(tmp_path, capsys, monkeypatch):
    assert main(["check", str(FIG5)]) == 0


@drives("check", 2)
def _check_2(tmp_path, capsys, monkeypatch):
    bad = tmp_path / "bad.yaml"
    bad.write_text(FIG5.read_text().replace("I_max: 0.6", "I_max: -1"))
    assert main(["check", str(bad)]) == 2


# -- a running daemon: status, ls, tap, arm, exporter --------------------------------------------------------------
@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    d = tmp_path_factory.mktemp("daemon")
    sock = d / "run.sock"
    p = _mrctl("run", str(_fig5(d)), "--duration", "120", "--no-log", "-q", "--socket", str(sock))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and main(["status", "--socket", str(sock), "--json"]) != 0:
        time.sleep(0.2)
    yield str(sock)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 0, err


@drives("status", 0)
def _status_0(tmp_path, capsys, monkeypatch, daemon):
    assert main(["status", "--socket", daemon]) == 0


@drives("status", 2)
def _status_2(tmp_path, capsys, monkeypatch):
    with pytest.raises(SystemExit) as exc:
        main(["status", "--format", "nope"])
    assert exc.value.code == 2


@drives("status", 3)
def _status_3(tmp_path, capsys, monkeypatch):
    assert main(["status", "--socket", str(tmp_path / "none.sock")]) == 3
    assert "no mrctl running" in capsys.readouterr().err


@drives("ls", 0)
def _ls_0(tmp_path, capsys, monkeypatch):
    assert main(["ls", "--json"]) == 0


@drives("tap", 0)
def _tap_0(tmp_path, capsys, monkeypatch, daemon):
    assert main(["tap", "--socket", daemon, "-n", "5"]) == 0
    for sig in (signal.SIGINT, signal.SIGTERM):  # until stopped
        p = _mrctl("tap", "--socket", daemon)
        first = p.stdout.readline()  # tapping: its header is out
        p.send_signal(sig)
        _, err = p.communicate(timeout=30)
        assert p.returncode == 0, err
        assert first.startswith("t,") or "t," in first


@drives("tap", 2)
def _tap_2(tmp_path, capsys, monkeypatch):
    assert main(["tap", "--socket", str(tmp_path / "none.sock"), "--columns", "t,nope"]) == 2


@drives("tap", 3)
def _tap_3(tmp_path, capsys, monkeypatch):
    assert main(["tap", "--socket", str(tmp_path / "none.sock"), "-n", "5"]) == 3


@drives("arm", 0)
def _arm_0(tmp_path, capsys, monkeypatch, daemon):
    assert main(["arm", "--socket", daemon]) == 0
    assert "nothing to re-arm" in capsys.readouterr().out


@drives("arm", 3)
def _arm_3(tmp_path, capsys, monkeypatch):
    assert main(["arm", "--socket", str(tmp_path / "none.sock")]) == 3


@drives("exporter", 0)
def _exporter_0(tmp_path, capsys, monkeypatch, daemon):
    for sig in (signal.SIGINT, signal.SIGTERM):
        p = _mrctl("exporter", "--listen", "127.0.0.1:0", "--socket", daemon)
        assert "mrctl exporter: http://" in p.stdout.readline()
        p.send_signal(sig)
        _, err = p.communicate(timeout=30)
        assert p.returncode == 0, err


@drives("exporter", 2)
def _exporter_2(tmp_path, capsys, monkeypatch):
    assert main(["exporter", "--listen", "nope"]) == 2


# -- examples, docs -----------------------------------------------------------------------------------------------
@drives("examples", 0)
def _examples_0(tmp_path, capsys, monkeypatch):
    assert main(["examples", str(tmp_path / "ex"), "-q"]) == 0


@drives("examples", 2)
def _examples_2(tmp_path, capsys, monkeypatch):
    assert main(["examples", str(tmp_path / "ex"), "-q"]) == 0
    assert main(["examples", str(tmp_path / "ex"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "Traceback" not in err


@drives("docs", 0)
def _docs_0(tmp_path, capsys, monkeypatch):
    assert main(["docs", "config"]) == 0


@drives("docs", 2)
def _docs_2(tmp_path, capsys, monkeypatch):
    assert main(["docs", "nosuchtopic"]) == 2


# -- the table and the drivers ------------------------------------------------------------------------------------
TABLE = [(cmd, code) for cmd, codes in COMMAND_EXITS.items() for code in codes]


def test_every_code_of_the_table_has_a_driver_and_every_driver_a_row():
    assert set(DRIVEN) == set(TABLE), {"undriven": set(TABLE) - set(DRIVEN), "not in the table": set(DRIVEN) - set(TABLE)}
    commands = set(cli.build_parser()._subparsers._group_actions[0].choices)
    assert commands == set(COMMAND_EXITS), commands ^ set(COMMAND_EXITS)


@pytest.mark.parametrize("command", list(COMMAND_EXITS))
def test_each_commands_help_ends_with_its_codes(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = capsys.readouterr().out
    assert f"mrctl {command} exits:" in text
    for code in COMMAND_EXITS[command]:
        assert f"\n  {code:<3}  " in text, code


@pytest.mark.parametrize("command,code", TABLE, ids=[f"{c}-{k}" for c, k in TABLE])
def test_the_code(command, code, tmp_path, capsys, monkeypatch, request):
    driver = DRIVEN[(command, code)]
    monkeypatch.chdir(tmp_path)
    extra = {"daemon": request.getfixturevalue("daemon")} if "daemon" in driver.__code__.co_varnames[
        :driver.__code__.co_argcount] else {}
    driver(tmp_path, capsys, monkeypatch, **extra)


# -- device ----------------------------------------------------------------------------------------------------------
T7 = ROOT / "config" / "experiments" / "labjack_t7.yaml"


def _t7(tmp_path: Path, port: int) -> Path:
    data = yaml.safe_load(T7.read_text())
    data["backend"]["port"] = port
    p = tmp_path / "t7.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


@drives("device", 0)
def _device_0(tmp_path, capsys, monkeypatch):
    from hil_sim.testing.harness import HilSim

    monkeypatch.setenv("MRCTL_LOCK_DIR", str(tmp_path / "locks"))
    hil = HilSim("--config", str(ROOT / "config" / "hil_labjack_t7_bench.yaml"), "--device", "labjack_t7",
                 "--transport", "modbus-tcp", "--bind", "127.0.0.1:0", workdir=tmp_path)
    try:
        port = int(hil.field("bind").rpartition(":")[2])
        assert main(["device", "disarm", str(_t7(tmp_path, port))]) == 0
    finally:
        hil.stop()


@drives("device", 2)
def _device_2(tmp_path, capsys, monkeypatch):
    assert main(["device", "disarm", str(FIG5)]) == 2  # the in-process bench: no device preset


@drives("device", 3)
def _device_3(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MRCTL_LOCK_DIR", str(tmp_path / "locks"))
    assert main(["device", "disarm", str(_t7(tmp_path, 1))]) == 3  # nothing listens on port 1
