"""Every run log replays (issue 35, item 2): whatever wrote it (``mrctl
simulate`` of every shipped experiment; ``mrctl run`` over serial, Modbus
TCP and RTU against hil_sim, the LabJack T7 preset against its emulation,
the reference firmware's host build on a pty), ``mrctl simulate --replay``
of the log exits 0 with the same experiment (the sidecar's config validates
back to itself), its figures over the same window as the original's (after
the settling window), and ``mrctl report RUN REPLAY`` draws both on one
force quantity, said in the legend.

The HIL runs are 2.5 s at 200 Hz (hil_util: what CI holds), a few seconds
per backend."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from hil_util import ROOT, HilSim, bench_at_test_rate, experiment_at_test_rate, run_daemon
from mrctl.cli import main
from mrctl.config.experiment import load_experiment, validate_experiment
from mrctl.config.saved import readable_config, saved_config
from mrctl.runlog.read import read_sidecar

EXP = ROOT / "config" / "experiments"
SHIPPED = sorted(EXP.rglob("*.yaml"))
#: a run long enough to leave a window after fig5's 1 s settling
RUN_S = 2.5
#: keys a replay sets itself: the rest of the config is the logged experiment's
REPLAY_SETS = ("excitation", "name", "duration_s")


def _id(p: Path) -> str:
    return str(p.relative_to(EXP))


def _experiment_of(side: dict) -> dict:
    data, _ = readable_config(side["config"])
    return {k: v for k, v in data.items() if k not in REPLAY_SETS}


@pytest.mark.parametrize("path", SHIPPED, ids=_id)
def test_the_saved_config_validates_back_to_itself(path):
    """The sidecar's form of every shipped experiment is JSON that validates
    to the same experiment (a T7's preset, a Modbus register map included)."""
    cfg = load_experiment(path)
    saved = saved_config(cfg)
    back = validate_experiment(json.loads(json.dumps(saved, allow_nan=False)), path.parent, "sidecar")
    assert saved_config(back) == saved


def _replay(log: Path, capsys) -> tuple[dict, dict, str]:
    out = log.with_name(log.stem + "-replay.csv")
    code = main(["simulate", "--replay", str(log), "--out", str(out), "-q"])
    text = capsys.readouterr()
    assert code in (0, 5), text.err  # 5: the offline verdict of a degraded bench (never a refused config)
    assert "Traceback" not in text.err
    return read_sidecar(log), read_sidecar(out), text.err


@pytest.mark.parametrize("path", SHIPPED, ids=_id)
def test_a_simulated_run_of_every_shipped_experiment_replays(path, tmp_path, capsys):
    log = tmp_path / "sim.csv"
    code = main(["simulate", str(path), "--duration", str(RUN_S), "--out", str(log), "-q"])
    assert code in (0, 5), capsys.readouterr().err
    a, b, err = _replay(log, capsys)
    assert "register_map" not in err  # nothing mended: the sidecar held a config that validates
    assert _experiment_of(b) == _experiment_of(a)
    assert b["summary"]["window_start_s"] == pytest.approx(a["summary"]["window_start_s"], abs=1e-9)
    assert b["summary"]["ticks"] == a["summary"]["ticks"]
    if a["law"] == b["law"] and path.parent == EXP and path.stem in ("fig5", "fig5_paper", "fig5_robust"):
        # the same law on the same motion (as the CSV wrote it): the same figures
        assert b["summary"]["force_nrmse"] == pytest.approx(a["summary"]["force_nrmse"], rel=1e-4)


def test_an_older_sidecar_with_live_forms_is_mended_and_said(tmp_path, capsys):
    """A sidecar written before the saved form (a device kept as its set-up, a
    register map as its description) replays, and the replay says what it
    took instead."""
    log = tmp_path / "t7.csv"
    assert main(["simulate", str(EXP / "labjack_t7.yaml"), "--duration", "0.3", "--out", str(log), "-q"]) == 0
    side = json.loads(log.with_suffix(".json").read_text())
    side["config"]["backend"]["device"] = {"device": "labjack_t7", "source": "...", "channels": {}}
    side["config"]["backend"]["register_map"] = "RegisterMap(unit 1, read holding 0+6, write holding 1000+2)"
    log.with_suffix(".json").write_text(json.dumps(side))
    _, b, err = _replay(log, capsys)
    assert b["config"]["backend"]["device"] in ("labjack_t7", {**b["config"]["backend"]["device"]})
    tcp = tmp_path / "tcp.csv"
    assert main(["simulate", str(EXP / "hil_modbus_tcp.yaml"), "--duration", "0.3", "--out", str(tcp), "-q"]) == 0
    side = json.loads(tcp.with_suffix(".json").read_text())
    side["config"]["backend"]["register_map"] = "RegisterMap(unit 1, read holding 0+6, write holding 1000+2)"
    tcp.with_suffix(".json").write_text(json.dumps(side))
    _, _, err = _replay(tcp, capsys)
    assert "backend.register_map" in err and "default map" in err


# -- over the real links ------------------------------------------------------------------------------------------
BENCH = str(ROOT / "config" / "hil_fig5_bench.yaml")


def _serial(d: Path):
    hil = HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "serial", "--link", str(d / "tty"),
                 "--duration", "30", workdir=d)
    return hil, experiment_at_test_rate(EXP / "hil_serial.yaml", d, **{"/tmp/mrctl-sim-tty": str(d / "tty")})


def _modbus_tcp(d: Path):
    hil = HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "modbus-tcp", "--bind", "127.0.0.1:0",
                 "--duration", "30", workdir=d)
    port = hil.field("bind").rsplit(":", 1)[1]
    return hil, experiment_at_test_rate(EXP / "hil_modbus_tcp.yaml", d, **{"port: 5020": f"port: {port}"})


def _modbus_rtu(d: Path):
    hil = HilSim("--config", bench_at_test_rate(BENCH, d), "--transport", "modbus-rtu", "--link", str(d / "rtu"),
                 "--baud", "921600", "--duration", "30", workdir=d)
    return hil, experiment_at_test_rate(EXP / "hil_modbus_rtu.yaml", d, **{"/tmp/mrctl-sim-rtu": str(d / "rtu")})


def _labjack_t7(d: Path):
    hil = HilSim("--config", str(ROOT / "config" / "hil_labjack_t7_bench.yaml"), "--device", "labjack_t7",
                 "--transport", "modbus-tcp", "--bind", "127.0.0.1:0", "--duration", "30", workdir=d)
    data = yaml.safe_load((EXP / "labjack_t7.yaml").read_text())
    data["backend"]["port"] = int(hil.field("bind").rpartition(":")[2])
    data["acceptance"] = {"max_skipped_share": 1.0, "max_gap_s": 3600.0}  # a real clock, a shared machine
    p = d / "labjack_t7.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return hil, p


class _Firmware:
    """The reference firmware's host build on a pty, as a HilSim-like handle."""

    def __init__(self, exe: Path, d: Path) -> None:
        self.link = d / "fw-tty"
        self.proc = subprocess.Popen([str(exe), "--link", str(self.link), "--rate-hz", "200"],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        ready = self.proc.stdout.readline()
        assert ready.startswith("mrctl_fw_host ready"), ready

    def stop(self) -> int:
        self.proc.terminate()
        self.proc.communicate(timeout=10)
        return self.proc.returncode


def _firmware(d: Path):
    gxx = shutil.which("g++")
    assert gxx is not None, "g++ builds the firmware's host program (tests/test_firmware.py)"
    exe = d / "mrctl_fw_host"
    fw = ROOT / "firmware"
    res = subprocess.run([gxx, "-std=c++17", "-O1", f"-I{fw / 'core'}", f"-I{fw / 'boards/teensy4/mrctl_teensy4'}",
                          *sorted(str(p) for p in (fw / "core").glob("*.cpp")), str(fw / "host" / "mrctl_fw_host.cpp"),
                          "-o", str(exe)], capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr
    fwh = _Firmware(exe, d)
    cfg = d / "firmware_host.yaml"
    data = yaml.safe_load((EXP / "firmware_host.yaml").read_text())
    data["backend"]["url"] = str(fwh.link)
    data["acceptance"] = {**data.get("acceptance", {}), "max_skipped_share": 1.0, "max_gap_s": 3600.0}
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    return fwh, cfg


@pytest.mark.hil
@pytest.mark.parametrize("start", [_serial, _modbus_tcp, _modbus_rtu, _labjack_t7, _firmware],
                         ids=["serial", "modbus-tcp", "modbus-rtu", "labjack-t7", "firmware"])
def test_a_run_log_of_every_backend_replays(start, tmp_path, capsys):
    hil, cfg = start(tmp_path)
    log = tmp_path / "run.csv"
    try:
        res = run_daemon(cfg, log, duration_s=RUN_S)
    finally:
        hil.stop()
    if res.returncode == 3 and "refusing to start" in res.stderr:  # the probe found the link too slow just then
        pytest.fail(f"the run did not start: {res.stderr.strip()[-500:]}")
    assert res.returncode in (0, 5), res.stderr
    a, b, err = _replay(log, capsys)
    assert "mended" not in err and "register_map" not in err, err
    assert _experiment_of(b) == _experiment_of(a)
    window = a["summary"]["tracking"]["window_start_s"]
    assert window >= a["settle_s"] > 0
    assert b["summary"]["window_start_s"] == pytest.approx(window, abs=1.5 / float(a["rate_hz"])), \
        (window, b["summary"]["window_start_s"], a["rate_hz"], b["rate_hz"])
    fig = tmp_path / "both.png"
    assert main(["report", str(log), str(log.with_name("run-replay.csv")), "--out", str(fig)]) == 0, \
        capsys.readouterr().err
    assert fig.stat().st_size > 10_000
    _like_with_like(log, log.with_name("run-replay.csv"))


def _like_with_like(run: Path, replay: Path) -> None:
    """The report of a run and its replay: one force quantity (the load cell's
    when the run has no plant force), one window, both said on the figure."""
    from mrctl.offline.report import build_figure

    fig, (a, b) = build_figure([run, replay])
    assert a["force_from"] == b["force_from"]
    assert b["t_start"] == pytest.approx(a["t_start"], abs=0.011)
    force = next(ax for ax in fig.axes if ax.get_label() == "force")
    plant = a["force_from"] == "F_true"
    assert ("F_{true}" if plant else "load cell") in force.get_title()
    caption = fig.get_suptitle()
    assert caption.count("of the plant's F_true" if plant else "of the load cell's F") == 2, caption


def test_a_simulated_run_and_its_replay_are_drawn_on_one_force(tmp_path, capsys):
    """A simulated run has the plant's force: its replay too, so both are drawn on F_true;
    a run without it (hardware) beside its replay: both on the load cell."""
    log = tmp_path / "sim.csv"
    assert main(["simulate", str(EXP / "fig5.yaml"), "--duration", str(RUN_S), "--out", str(log), "-q"]) == 0
    _replay(log, capsys)
    _like_with_like(log, log.with_name("sim-replay.csv"))
    from mrctl.offline.report import build_figure
    from mrctl.runlog.read import read_run

    hw = tmp_path / "hw.csv"  # the same log as hardware writes it: no plant force
    cols = read_run(log)
    names = [c for c in cols if c != "F_true"]
    hw.write_text(",".join(names) + "\n" + "\n".join(",".join(repr(float(cols[c][i])) for c in names)
                                                     for i in range(len(cols["t"]))) + "\n")
    hw.with_suffix(".json").write_text(log.with_suffix(".json").read_text())
    _, (a, b) = build_figure([hw, log.with_name("sim-replay.csv")])
    assert a["force_from"] == b["force_from"] == "F"
