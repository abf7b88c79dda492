"""The LabJack T7 preset (mrctl/io/devices), hil_sim's T7 emulation, mrctl calibrate (issue 25).

Runs the daemon against ``python -m hil_sim --device labjack_t7`` on loopback
at the rate its start-up probe chooses (500 Hz with the emulator's datasheet
latency model, 1.22 ms a tick, when the machine holds it).
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import threading
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from hil_sim.state import DeviceState
from hil_sim.testing.harness import ROOT, HilSim, Run, env
from mrctl.cli import main as mrctl_main

BENCH = ROOT / "config" / "hil_labjack_t7_bench.yaml"
EXPERIMENT = ROOT / "config" / "experiments" / "labjack_t7.yaml"


# -- the preset: LabJack's published addresses ------------------------------------------
def test_preset_addresses_are_ljm_constants() -> None:
    """The addresses in the preset are ljm_constants.json's (a typo here drives the wrong pin)."""
    from mrctl.io.devices import load_preset

    p = load_preset("labjack_t7")
    assert [p.address("ain", n) for n in (0, 1, 13)] == [0, 2, 26]
    assert [p.address("dac", n) for n in (0, 1)] == [1000, 1002]
    assert [p.address("dio", n) for n in (0, 8, 16, 20)] == [2000, 2008, 2016, 2020]  # FIO0, EIO0, CIO0, MIO0
    assert p.io("ain")["range_register"]["address"] == 40000
    assert p.io("ain")["resolution_register"]["address"] == 41500
    wd = {k: v["address"] for k, v in p.watchdog["registers"].items()}
    assert wd == {"enable": 61600, "advanced": 61602, "timeout_s": 61604, "startup_delay_s": 61606,
                  "strict_enable": 61610, "strict_key": 61612, "reset_enable": 61620, "dio_enable": 61630,
                  "dio_state": 61632, "dio_direction": 61634, "dio_inhibit": 61636, "dac0_enable": 61640,
                  "dac0_value": 61642, "dac1_enable": 61650, "dac1_value": 61652}
    assert p.watchdog["strict_clear"]["address"] == 61614
    assert p.data["firmware"]["address"] == 60004 and p.data["core_timer"]["address"] == 61520
    assert p.data["firmware"]["min"] == 1.0016 and p.data["firmware"]["min_core_timer"] == 1.0071
    assert p.io("ain")["negative_register"]["address"] == 41000
    assert p.io("ain")["settling_register"]["address"] == 42000
    assert [p.io("dio")[k]["address"] for k in ("state_register", "direction_register", "inhibit_register")] \
        == [2800, 2850, 2900]
    assert p.fc23 is False and p.port == 502 and p.data["modbus"]["mbfb"] == 76


# -- mrctl check: every new input is a clear error with its key path ----------------------
def _experiment(tmp_path: Path, **backend_changes) -> Path:
    data = yaml.safe_load(EXPERIMENT.read_text())
    for k, v in backend_changes.items():
        if v is None:
            data["backend"].pop(k, None)
        else:
            data["backend"][k] = v
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


@pytest.mark.parametrize("change, message", [
    ({"channels": {"x": {"ain": 14, "m_per_V": 0.0025}, "current": {"dac": 0, "V_per_A": 2.5}}},
     "backend.channels.x.ain: 14 not allowed: a labjack_t7 has AIN0-AIN13"),
    ({"channels": {"x": {"ain": 0, "m_per_V": 0.0025}, "current": {"dac": 2, "V_per_A": 2.5}}},
     "backend.channels.current.dac: 2 not allowed: a labjack_t7 has DAC0-DAC1"),
    ({"channels": {"x": {"ain": 0, "m_per_V": 0}, "current": {"dac": 0, "V_per_A": 2.5}}},
     "backend.channels.x.m_per_V: 0 not allowed (must be a finite non-zero number)"),
    ({"channels": {"x": {"ain": 0, "m_per_V": 0.0025}, "current": {"dac": 0, "V_per_A": 10.0}}},
     "backend.channels.current.V_per_A: safety.I_max 0.6 A needs 6 V on DAC0; a labjack_t7's DAC gives 0-5 V"),
    ({"channels": {"x": {"ain": 0, "m_per_V": 0.0025}, "current": {"dac": 0, "V_per_A": 2.5, "offset_V": -1}}},
     "backend.channels.current.offset_V: -1 V (the DAC at 0 A) is outside DAC's 0-5 V"),
    ({"channels": {"x": {"ain": 0, "m_per_V": 0.0025}, "F": {"ain": 0, "N_per_V": 400},
                   "current": {"dac": 0, "V_per_A": 2.5}}},
     "backend.channels.F.ain: AIN0 is already backend.channels.x"),
    ({"channels": {"x": {"ain": 0, "m_per_V": 0.0025}}}, "backend.channels.current: required"),
    ({"channels": {"x": {"ain": 0, "m_per_V": 0.0025}, "current": {"dac": 0, "V_per_A": 2.5},
                   "temperature": {"ain": 3}}},
     "backend.channels.temperature: unknown channel (allowed here: x, v, F, current_monitor, current)"),
    ({"device_watchdog_s": 0.5}, "backend.device_watchdog_s: 0.5 not allowed"),
    ({"ain_range_V": 5.0}, "backend.ain_range_V: 5.0 not allowed (a labjack_t7 has +/- 10, 1, 0.1, 0.01 V)"),
    ({"ain_resolution_index": 9}, "backend.ain_resolution_index: 9 not allowed (a labjack_t7 takes 1-8)"),
    ({"enable_dio": 23}, "backend.enable_dio: 23 not allowed: a labjack_t7 has DIO0-DIO22"),
    ({"register_map": {}}, "backend.register_map: a device preset builds the register map"),
    ({"device": "labjack_t4"}, "backend.device: 'labjack_t4' not allowed (allowed: labjack_t7)"),
    ({"time_stamps": "sometimes"}, "backend.time_stamps: 'sometimes' not allowed"),
])
def test_check_refuses_bad_device_input(tmp_path, capsys, change, message) -> None:
    assert mrctl_main(["check", str(_experiment(tmp_path, **change))]) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert "Traceback" not in err


def test_check_refuses_device_keys_without_a_device(tmp_path, capsys) -> None:
    p = _experiment(tmp_path, device=None)
    assert mrctl_main(["check", str(p)]) == 2
    assert "backend.channels: only with backend.device" in capsys.readouterr().err


def test_time_stamps_default_to_the_devices_and_host_is_recorded(tmp_path) -> None:
    """backend.time_stamps: null = device; host is carried in the set-up and the sidecar's form."""
    from mrctl.config import load_experiment

    assert load_experiment(_experiment(tmp_path)).backend.device.device_time_stamps is True
    setup = load_experiment(_experiment(tmp_path, time_stamps="host")).backend.device
    assert setup.device_time_stamps is False and setup.to_dict()["time_stamps"] == "host"


def test_velocity_defaults_to_the_observer_without_a_velocity_channel(tmp_path) -> None:
    from mrctl.config import load_experiment

    data = yaml.safe_load(EXPERIMENT.read_text())
    data.pop("sensing")
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    assert load_experiment(p).sensing.velocity == "observer"
    data["sensing"] = {"velocity": "measured"}
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(Exception, match="sensing.velocity: 'measured', but the register map has no velocity"):
        load_experiment(p)


def test_channels_become_the_links_scaling() -> None:
    """x = (V - offset_V) * m_per_V on the read side; V = I * V_per_A + offset_V on the DAC: the
    link's own tick (one MBFB request) against a wire that answers AIN0 = 2.9 V."""
    from mrctl.io.devices import resolve_device
    from mrctl.io.devices.link import PresetLink

    setup, errors = resolve_device("labjack_t7", {"x": {"ain": 0, "m_per_V": 0.0025, "offset_V": 2.5},
                                                  "current": {"dac": 0, "V_per_A": 2.5, "offset_V": 0.1}}, {})
    assert errors == []
    sent: list[bytes] = []

    class Wire:
        def write(self, adu, deadline) -> None:
            sent.append(bytes(adu))

        def recv(self, deadline, wake_ns=0) -> bytes:
            pdu = bytes((76,)) + struct.pack(">ff", 0.1, 2.9)  # DAC0 read back, AIN0
            return sent[-1][:2] + struct.pack(">HHB", 0, len(pdu) + 1, 1) + pdu

        def close(self) -> None:
            pass

    link = PresetLink(setup, host="127.0.0.1")
    link._io = Wire()
    link._choose_protocol()
    sample = link._tick(0.4, True, time.monotonic() + 1.0, 0)
    assert sample.x_m == pytest.approx((2.9 - 2.5) * 0.0025)
    # the request: read DAC0 (1000), write DAC0 (1000) its volts, the watchdog key, read AIN0 (address 0)
    assert struct.unpack_from(">BHB", sent[-1], 8) == (0, 1000, 2)
    kind, address, n, volts = struct.unpack_from(">BHBf", sent[-1], 12)
    assert (kind, address, n) == (1, 1000, 2) and volts == pytest.approx(0.4 * 2.5 + 0.1)
    assert struct.unpack_from(">BHB", sent[-1], 28) == (0, 0, 2) and len(sent[-1]) == 32
    link._io = None


# -- the emulator, in process, on a virtual clock ----------------------------------------------
class _Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def _wiring(enable: bool):
    from hil_sim.labjack_t7 import t7_fields
    from mrctl.util.schema import validate_fields

    data = {"latency_s": 0.0, "x": {"ain": 0, "m_per_V": 0.0025, "offset_V": 2.47},
            "F": {"ain": 1, "N_per_V": 400.0, "offset_V": 0.012}, "driver": {"dac": 0, "A_per_V": 0.4},
            "enable": {"dio": 0, "hold_s": 0.02} if enable else None}
    node, errors = validate_fields(t7_fields(), data, "labjack_t7")
    assert errors == []
    return node


def _pdu(dev, pdu: bytes) -> bytes:
    return dev.handle_pdu(pdu)


def _write_f32(address: int, v: float) -> bytes:
    return struct.pack(">BHHBf", 16, address, 2, 4, v)


def _write_u32(address: int, v: int) -> bytes:
    return struct.pack(">BHHBI", 16, address, 2, 4, v)


def test_emulator_serves_volts_and_refuses_what_a_t7_refuses() -> None:
    from hil_sim.labjack_t7 import T7Device
    from mrctl.io.base import Sample

    state = DeviceState()
    state.publish(Sample(0, 0.0, 0.001, math.nan, 20.0, 0, 0.0))
    dev = T7Device(state, _wiring(False), clock_ns=_Clock())
    r = _pdu(dev, struct.pack(">BHH", 3, 0, 4))  # AIN0, AIN1
    assert r[:2] == bytes((3, 8))
    ain0, ain1 = struct.unpack(">ff", r[2:])
    lsb = 20.0 / 65536  # the 16-bit converter over +/-10 V: readings are whole LSBs, with ~1 LSB rms noise
    assert ain0 == pytest.approx(0.001 / 0.0025 + 2.47, abs=5 * lsb)
    assert ain1 == pytest.approx(20.0 / 400.0 + 0.012, abs=5 * lsb)
    assert abs(ain0 / lsb - round(ain0 / lsb)) < 1e-3
    reads = {struct.unpack(">f", _pdu(dev, struct.pack(">BHH", 3, 4, 2))[2:])[0] for _ in range(50)}  # AIN2, unwired
    assert len(reads) > 1 and max(abs(v) for v in reads) < 6 * lsb  # an input at 0 V is noisy, not constant
    assert _pdu(dev, struct.pack(">BHH", 4, 0, 2))[:2] == bytes((4, 4))  # FC4 reads the same space
    # DAC0 drives the bench's driver: 1.25 V * 0.4 A/V
    assert _pdu(dev, _write_f32(1000, 1.25))[0] == 16
    assert state.setpoint()[0] == pytest.approx(0.5) and state.setpoint()[1] is True
    refused = {
        "FC23": (struct.pack(">BHHHHBf", 23, 0, 2, 1000, 2, 4, 1.0), 0x01),
        "write AIN0": (_write_f32(0, 1.0), 0x02),
        "half a float": (struct.pack(">BHH", 3, 1, 1), 0x02),
        "no register": (struct.pack(">BHH", 3, 500, 2), 0x02),
        "range 5 V": (_write_f32(40000, 5.0), 0x03),
        "resolution 9": (struct.pack(">BHHBH", 16, 41500, 1, 2, 9), 0x03),
        "DIO level 2": (struct.pack(">BHHBH", 16, 2000, 1, 2, 2), 0x03),
        "DAC NaN": (_write_f32(1000, math.nan), 0x03),
    }
    for what, (pdu, code) in refused.items():
        assert _pdu(dev, pdu) == bytes((pdu[0] | 0x80, code)), what
    assert state.setpoint()[0] == pytest.approx(0.5)  # the NaN did not reach the driver
    # watchdog registers: only while the watchdog is disabled
    assert _pdu(dev, _write_u32(61604, 1))[0] == 16
    assert _pdu(dev, _write_u32(61600, 1))[0] == 16
    assert _pdu(dev, _write_u32(61604, 2)) == bytes((0x90, 0x03))


def test_emulator_watchdog_and_enable_monostable_on_a_virtual_clock() -> None:
    from hil_sim.labjack_t7 import T7Device

    clock = _Clock()
    state = DeviceState()
    dev = T7Device(state, _wiring(True), clock_ns=clock)
    for a, v in ((61604, 1), (61640, 1), (61600, 1)):  # timeout 1 s, DAC0 -> its value (0 V), enable
        assert _pdu(dev, _write_u32(a, v))[0] == 16
    _pdu(dev, _write_f32(1000, 2.0))
    assert state.setpoint()[:2] == (pytest.approx(0.8), False)  # enable wired, no edge yet: driver off
    for level in (1, 0, 1):
        clock.ns += 5_000_000
        _pdu(dev, struct.pack(">BHHBH", 16, 2000, 1, 2, level))
        dev.check()
        assert state.setpoint()[1] is True
    t_rise = clock.ns
    clock.ns += 5_000_000
    _pdu(dev, struct.pack(">BHHBH", 16, 2000, 1, 2, 0))  # a falling edge does not retrigger
    clock.ns = t_rise + 19_000_000
    dev.check()
    assert state.setpoint()[1] is True and dev.enable_drops == []
    clock.ns = t_rise + 21_000_000  # 21 ms after the last rising edge: the monostable has run out
    dev.check()
    assert state.setpoint()[1] is False and dev.enable_drops == [clock.ns]
    last_comm = t_rise + 5_000_000
    clock.ns = last_comm + 999_000_000
    dev.check()
    assert dev.dac_V[0] == 2.0 and dev.watchdog_trips == []
    clock.ns = last_comm + 1_001_000_000
    dev.check()
    assert dev.dac_V[0] == 0.0 and dev.watchdog_trips == [clock.ns]
    assert state.setpoint()[0] == 0.0


# -- against the emulator: calibrate, run, SIGKILL ------------------------------------------------
def _bench(tmp_path: Path, *, rest: bool = False, enable: bool = False) -> Path:
    data = yaml.safe_load(BENCH.read_text())
    if rest:
        data["excitation"]["amplitude_m"] = 0.0
    if enable:
        data["labjack_t7"]["enable"] = {"dio": 0, "hold_s": 0.04}
    p = tmp_path / "bench.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def _start(tmp_path: Path, bench: Path, *extra: str) -> tuple[HilSim, int]:
    hil = HilSim("--config", str(bench), "--device", "labjack_t7", "--transport", "modbus-tcp",
                 "--bind", "127.0.0.1:0", *extra, workdir=tmp_path)
    return hil, int(hil.field("bind").rpartition(":")[2])


def _exp_for(tmp_path: Path, port: int, **changes) -> Path:
    data = yaml.safe_load(EXPERIMENT.read_text())
    data["backend"]["port"] = port
    data.setdefault("acceptance", {"max_skipped_share": 1.0, "max_gap_s": 3600.0})  # a real clock, a shared machine
    for k, v in changes.items():
        if k in ("enable_dio", "device_watchdog_s"):
            data["backend"][k] = v
        else:
            data[k] = v
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def _mrctl(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=ROOT, env=env(), capture_output=True,
                          text=True, timeout=timeout)


def test_calibrate_recovers_the_benchs_offsets_and_lag(tmp_path) -> None:
    """Offsets within 2 %, tau within 10 % of what the bench is configured with."""
    bench = yaml.safe_load(BENCH.read_text())
    hil, port = _start(tmp_path, _bench(tmp_path, rest=True))
    try:
        res = _mrctl("calibrate", str(_exp_for(tmp_path, port)), "--out", str(tmp_path / "cal.yaml"))
    finally:
        hil.stop()
    assert res.returncode == 0, res.stderr
    cal = yaml.safe_load((tmp_path / "cal.yaml").read_text())
    w = bench["labjack_t7"]
    assert cal["channels"]["x"]["offset_V"] == pytest.approx(w["x"]["offset_V"], rel=0.02)
    assert cal["channels"]["F"]["offset_V"] == pytest.approx(w["F"]["offset_V"], rel=0.02)
    assert cal["driver"]["tau_s"] == pytest.approx(bench["plant"]["driver_tau_s"], rel=0.10)
    assert cal["noise"]["x_m"] == pytest.approx(bench["plant"]["sensors"]["x_noise_m"], rel=0.25)
    # an experiment takes it: offsets, the observer's noise, the law's lag
    from mrctl.config import load_experiment

    exp = _exp_for(tmp_path, port, calibration="cal.yaml", sensing={"velocity": "observer"})
    cfg = load_experiment(exp)
    assert cfg.backend.device.channels["x"].offset_V == cal["channels"]["x"]["offset_V"]
    assert cfg.sensing.x_noise_m == cal["noise"]["x_m"]
    assert cfg.parameters.tau_input == cal["driver"]["tau_s"]
    # the shipped experiment's own x_noise_m (noise plus the host clock's timing jitter) wins
    shipped = load_experiment(_exp_for(tmp_path, port, calibration="cal.yaml"))
    assert shipped.sensing.x_noise_m == yaml.safe_load(EXPERIMENT.read_text())["sensing"]["x_noise_m"]


def test_calibrate_with_the_e_stop_open_is_refused_before_a_current_step(tmp_path) -> None:
    """The emulated T7's E-stop DIO reads its active level from the start: calibrate exits 3 naming
    the E-stop, writes nothing, and the emulated driver never saw a current."""
    data = yaml.safe_load(_bench(tmp_path, rest=True).read_text())
    data["labjack_t7"]["estop"] = {"dio": 4, "active": "high"}
    bench = tmp_path / "bench.yaml"
    bench.write_text(yaml.safe_dump(data, sort_keys=False))
    truth = tmp_path / "truth.csv"
    hil, port = _start(tmp_path, bench, "--fault", "estop@0+600", "--truth", str(truth))
    try:
        res = _mrctl("calibrate", str(_exp_for(tmp_path, port)), "--out", str(tmp_path / "cal.yaml"))
    finally:
        hil.stop()
    assert res.returncode == 3, res.stderr
    assert "refusing to start: the E-stop input is open" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "cal.yaml").exists()
    t7 = json.loads(truth.with_suffix(".json").read_text())["modbus"]
    assert t7["requests"] > 0 and t7["dac_V"][0] == 0.0
    I_cmd = np.genfromtxt(truth, delimiter=",", names=True)["I_cmd"]
    assert len(I_cmd) > 0 and np.nanmax(I_cmd) == 0.0  # the driver never saw a current


def _nrmse_load_cell(path: Path) -> float:
    from mrctl.runlog.metrics import tracking_summary
    from mrctl.runlog.read import read_run

    c = read_run(path)
    return tracking_summary(c["t"], c["F_des"], c["F"], c["I"], 0.6, 1.0)["force_nrmse"]


def test_hil_run_over_the_emulated_t7_at_the_probes_rate(tmp_path) -> None:
    """Day one, then a run: calibrate on the bench at rest, run the experiment
    with the calibration at the rate the start-up probe picks (exit 0), and
    measure the force tracking (load cell against F_des) beside mrctl
    simulate of the same experiment and calibration at that rate."""
    hil, port = _start(tmp_path, _bench(tmp_path, rest=True))
    try:
        res = _mrctl("calibrate", str(_exp_for(tmp_path, port)), "--out", str(tmp_path / "cal.yaml"))
    finally:
        hil.stop()
    assert res.returncode == 0, res.stderr
    hil, port = _start(tmp_path, BENCH)
    exp = _exp_for(tmp_path, port, duration_s=4.0, calibration="cal.yaml")
    out = tmp_path / "run.csv"
    try:
        res = _mrctl("run", str(exp), "--out", str(out), "--quiet", "--status-socket", str(tmp_path / "s.sock"))
    finally:
        hil.stop()
    assert res.returncode == 0, res.stderr
    m = re.search(r"Running at (\d+) Hz instead", res.stderr)
    rate = float(m.group(1)) if m else 1000.0
    sim_exp = _exp_for(tmp_path, port, duration_s=4.0, rate_hz=rate, calibration="cal.yaml")
    sim = _mrctl("simulate", str(sim_exp), "--out", str(tmp_path / "sim.csv"))
    assert sim.returncode == 0, sim.stderr
    hil_nrmse, sim_nrmse = _nrmse_load_cell(out), _nrmse_load_cell(tmp_path / "sim.csv")
    print(f"rate {rate:g} Hz: HIL force NRMSE {100 * hil_nrmse:.3f} %, simulate {100 * sim_nrmse:.3f} %, "
          f"ratio {hil_nrmse / sim_nrmse:.2f}")
    assert math.isfinite(hil_nrmse) and hil_nrmse < 0.12, (hil_nrmse, sim_nrmse)


def _read_f32(port: int, address: int) -> float:
    with socket.create_connection(("127.0.0.1", port), timeout=2.0) as s:
        s.sendall(struct.pack(">HHHBBHH", 7, 0, 6, 1, 3, address, 2))
        data = b""
        while len(data) < 13:
            chunk = s.recv(64)
            assert chunk, "the emulator closed the connection"
            data += chunk
    assert data[7] == 3, data
    return struct.unpack(">f", data[9:13])[0]


def test_sigkill_dac0_to_0v_within_the_watchdog_and_enable_off_within_50ms(tmp_path) -> None:
    """SIGKILL the daemon: the enable output stops toggling, the monostable
    disables the driver within its 40 ms; the T7's watchdog (1 s) puts DAC0
    at 0 V within its timeout of the last request."""
    truth = tmp_path / "truth.csv"
    hil, port = _start(tmp_path, _bench(tmp_path, enable=True), "--truth", str(truth))
    try:
        exp = _exp_for(tmp_path, port, duration_s=30.0, enable_dio=0)
        run = Run(exp, tmp_path / "run.csv", 30.0)
        st = run.wait_for(lambda s: s.get("ticks", 0) > 200 or s.get("loop", {}).get("ticks", 0) > 200, 30.0)
        assert st is not None, run.stderr()
        dac_before = 0.0
        for _ in range(20):  # the command follows the demand through zero: driven is its peak, not one sample
            dac_before = max(dac_before, _read_f32(port, 1000))
            time.sleep(0.025)
        t_kill = time.monotonic_ns()
        os.kill(run.pid, signal.SIGKILL)
        run.wait(10)
        time.sleep(1.5)
        dac_after = _read_f32(port, 1000)
    finally:
        hil.stop()
    summary = json.loads(truth.with_suffix(".json").read_text())
    t7 = summary["modbus"]
    assert dac_before > 0.05, "the damper was not being driven before the kill"
    assert dac_after == 0.0
    # the driver's enable: on while the daemon ran, off from 50 ms after the kill on (a loop
    # stall before the kill may have dropped it already: that is the same protection)
    events = sorted([(t, "on") for t in t7["enable_rises_ns"]] + [(t, "off") for t in t7["enable_drops_ns"]])
    assert any(e == "on" and t < t_kill for t, e in events), events
    state_50ms = [e for t, e in events if t <= t_kill + 50e6][-1]
    assert state_50ms == "off" and not [t for t, e in events if e == "on" and t > t_kill], (events, t_kill)
    off_at = [t for t, e in events if e == "off" and t <= t_kill + 50e6][-1]
    trips = [t for t in t7["watchdog_trips_ns"] if t >= t_kill]
    assert trips and (trips[0] - t_kill) <= 1.0e9 + 50e6, (trips, t_kill)
    print(f"enable off {(off_at - t_kill) / 1e6:.1f} ms, DAC0 0 V {(trips[0] - t_kill) / 1e6:.0f} ms after SIGKILL")


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="mbpoll not installed (apt-get install -y mbpoll)")
def test_mbpoll_reads_ain0_as_big_endian_float_at_address_0(tmp_path) -> None:
    """A client nobody here wrote reads the emulated T7 while the bench moves."""
    hil, port = _start(tmp_path, BENCH)
    try:
        vals = []
        for _ in range(3):
            r = subprocess.run(["mbpoll", "-m", "tcp", "-a", "1", "-0", "-1", "-o", "2", "-p", str(port),
                                "-t", "4:float", "-B", "-r", "0", "-c", "1", "127.0.0.1"],
                               capture_output=True, text=True, timeout=20)
            assert r.returncode == 0, r.stdout + r.stderr
            vals.append(float(re.search(r"^\[0\]:\s+(\S+)", r.stdout, re.M).group(1)))
            time.sleep(0.1)
    finally:
        hil.stop()
    # the LVDT: 2.47 V at the centre, +/-10 mm at 2.5 mm/V = +/-4 V, and the shaker moves
    assert all(2.47 - 4.1 < v < 2.47 + 4.1 for v in vals), vals
    assert len(set(vals)) > 1, vals


def test_fit_lag_recovers_tau_and_dead_time_despite_a_stall() -> None:
    """Synthetic steps of a 10 ms lag with a 1 ms dead time, 200 Hz readings
    with jitter, one step spoiled by a 40 ms stall (readings stamped late)."""
    from mrctl.daemon.calibrate import _step_response, fit_lag

    rng = np.random.default_rng(3)
    t_cmd = np.arange(16) * 0.08
    I_cmd = np.array([0.3, 0.0] * 8)
    t = np.arange(0, 1.28, 0.005) + rng.uniform(0, 3e-4, 256)
    y = _step_response(t, t_cmd, I_cmd, 0.010, 0.001) + rng.normal(0, 1e-3, t.size)
    stall = (t > 0.40) & (t < 0.44)
    t[stall] += 0.02  # these readings were asked for earlier than their stamps say
    tau, d, spread = fit_lag(t, y, t_cmd, I_cmd)
    assert tau == pytest.approx(0.010, rel=0.03) and d == pytest.approx(0.001, abs=5e-4)
    assert spread < 3e-3


def test_a_device_that_is_not_a_t7_is_refused_at_start(tmp_path) -> None:
    """mrctl's own register map (plain hil_sim) answers no PRODUCT_ID: exit 3, named."""
    hil = HilSim("--transport", "modbus-tcp", "--bind", "127.0.0.1:0", workdir=tmp_path)
    port = int(hil.field("bind").rpartition(":")[2])
    try:
        res = _mrctl("run", str(_exp_for(tmp_path, port, duration_s=1.0)), "--quiet",
                     "--status-socket", str(tmp_path / "s.sock"))
    finally:
        hil.stop()
    assert res.returncode == 3, res.stderr
    assert "cannot open backend" in res.stderr and "reading register 60000 refused" in res.stderr, res.stderr
    assert "is this a labjack_t7?" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr


def test_calibrate_refuses_bad_input_before_touching_a_device(tmp_path, capsys) -> None:
    sim = ROOT / "config" / "experiments" / "fig5.yaml"
    assert mrctl_main(["calibrate", str(sim), "--out", str(tmp_path / "cal.yaml")]) == 2
    assert "backend has no device preset" in capsys.readouterr().err
    exp = _exp_for(tmp_path, 1)  # nothing listens on port 1: the options are checked first
    assert mrctl_main(["calibrate", str(exp), "--out", str(tmp_path / "cal.yaml"), "--steps", "-1"]) == 2
    assert "--steps: must be >= 0" in capsys.readouterr().err
    assert mrctl_main(["calibrate", str(exp), "--out", str(tmp_path / "cal.yaml"), "--rate-hz", "0"]) == 2
    assert "--rate-hz: must be > 0" in capsys.readouterr().err
    (tmp_path / "cal.yaml").write_text("x")
    assert mrctl_main(["calibrate", str(exp), "--out", str(tmp_path / "cal.yaml")]) == 2
    assert "exists; refusing to replace it" in capsys.readouterr().err


def test_a_bad_calibration_file_is_a_clear_error(tmp_path, capsys) -> None:
    (tmp_path / "cal.yaml").write_text("version: 1\nchannels: {x: {offset_V: nan}, z: {}}\ndriver: {tau_s: -1}\n")
    exp = _exp_for(tmp_path, 5021, calibration="cal.yaml")
    assert mrctl_main(["check", str(exp)]) == 2
    err = capsys.readouterr().err
    assert "calibration (" in err and "channels.z: unknown channel" in err and "driver.tau_s" in err, err
    assert "Traceback" not in err


def test_sigkill_while_another_client_polls_dac0_and_enable_drop_within_the_timeout(tmp_path) -> None:
    """Issue 32: a second Modbus client polling the T7 every 100 ms (Kipling, an IOC) does not
    keep DAC0 or the enable alive after mrctl is SIGKILLed: the strict watchdog ignores it.
    The trip is the emulator's own record (its truth summary); every poll sent after it reads
    0 V and the enable low."""
    truth = tmp_path / "truth.csv"
    hil, port = _start(tmp_path, _bench(tmp_path, enable=True), "--truth", str(truth))
    polls: list[tuple[int, float, int]] = []  # (sent at, DAC0, DIO0)
    stop = [False]

    def poller() -> None:
        with socket.create_connection(("127.0.0.1", port), timeout=2.0) as s:
            tid = 0
            while not stop[0]:
                sent = time.monotonic_ns()
                got = []
                for address in (1000, 2800):  # DAC0 (FLOAT32), DIO_STATE (UINT32)
                    tid += 1
                    s.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, address, 2))
                    data = b""
                    while len(data) < 13:
                        chunk = s.recv(64)
                        if not chunk:
                            return
                        data += chunk
                    got.append(data[9:13])
                polls.append((sent, struct.unpack(">f", got[0])[0], struct.unpack(">I", got[1])[0] & 1))
                time.sleep(0.1)

    try:
        exp = _exp_for(tmp_path, port, duration_s=30.0, enable_dio=0)
        run = Run(exp, tmp_path / "run.csv", 30.0)
        st = run.wait_for(lambda s: s.get("ticks", 0) > 200 or s.get("loop", {}).get("ticks", 0) > 200, 30.0)
        assert st is not None, run.stderr()
        t = threading.Thread(target=poller, daemon=True)
        t.start()
        deadline = time.monotonic() + 10.0
        while len(polls) < 10 and time.monotonic() < deadline:  # a second of polls of the driven DAC0
            time.sleep(0.02)
        t_kill = time.monotonic_ns()
        os.kill(run.pid, signal.SIGKILL)
        run.wait(10)
        # polls sent after the watchdog's 1 s + 1 s (the bound on the trip checked below)
        deadline = time.monotonic() + 10.0
        while sum(p[0] > t_kill + 2.0e9 for p in polls) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        stop[0] = True
        t.join(3)
    finally:
        hil.stop()
    t7 = json.loads(truth.with_suffix(".json").read_text())["modbus"]
    trips = [t for t in t7["watchdog_trips_ns"] if t >= t_kill]
    assert trips and trips[0] - t_kill <= 2.0e9, (trips, t_kill)  # the watchdog's 1 s + 1 s
    before = [p for p in polls if p[0] < t_kill]
    after = [p for p in polls if p[0] > trips[0]]
    assert before and max(p[1] for p in before) > 0.05, before
    assert after and all(p[1] == 0.0 and p[2] == 0 for p in after), after
    off = [p[0] for p in polls if p[0] > t_kill and p[1] == 0.0 and p[2] == 0]
    print(f"watchdog trip {(trips[0] - t_kill) / 1e6:.0f} ms after SIGKILL (the emulator's record); "
          f"DAC0 0 V and enable low at the 100 ms poller {(off[0] - t_kill) / 1e6:.0f} ms after SIGKILL")


def test_estop_on_the_t7s_dio_latches_the_run_until_mrctl_arm_then_ramps(tmp_path) -> None:
    """Issue 32's done-when on the emulated T7: the E-stop's NC contact on FIO4 (active high)
    opens 5 s into the bench's time (the daemon is in its loop by then) for 0.5 s. The daemon
    commands 0 A on the tick whose
    sample reads it (no hold) and disables the output (the enable line stops toggling, the
    monostable drops); it stays at 0 A after the contact closed, until `mrctl arm`, which
    ramps the current back at the slew limit. The run ends with its time latched (exit 5)."""
    from mrctl.daemon.arm import arm
    from mrctl.runlog.read import read_run, read_sidecar

    data = yaml.safe_load(BENCH.read_text())
    data["labjack_t7"]["enable"] = {"dio": 0, "hold_s": 0.04}
    data["labjack_t7"]["estop"] = {"dio": 4, "active": "high"}
    bench = tmp_path / "bench.yaml"
    bench.write_text(yaml.safe_dump(data, sort_keys=False))
    hil, port = _start(tmp_path, bench, "--fault", "estop@5+0.5")
    said: dict = {}
    try:
        exp = _exp_for(tmp_path, port, duration_s=9.0, enable_dio=0)
        cfg = yaml.safe_load(exp.read_text())
        cfg["safety"]["estop"] = {"input": "FIO4", "active": "high"}
        exp.write_text(yaml.safe_dump(cfg, sort_keys=False))
        run = Run(exp, tmp_path / "run.csv", 9.0)
        st = run.wait_for(lambda s: s.get("safety_state") == "LATCHED", timeout_s=30.0)
        assert st is not None, run.stderr()
        said["latched"] = st
        time.sleep(1.0)  # the contact has closed again (0.5 s window)
        said["before"] = run.status()
        said["arm"] = arm(run.sock)
        code = run.wait(timeout_s=60.0)
    finally:
        hil.stop()
    assert code == 5, run.stderr()
    assert said["latched"]["latch_cause"] == "estop" and said["before"]["safety_state"] == "LATCHED"
    assert "re-armed" in said["arm"]
    cols = read_run(tmp_path / "run.csv")
    fault = np.nan_to_num(cols["fault"]).astype(int)
    I = np.nan_to_num(cols["I"])
    first = int(np.argmax(fault & 256))  # Fault.ESTOP: the first tick whose sample read the input open
    assert fault[first] & 1024 and I[first] == 0.0  # latched and 0 A on that very tick
    side = read_sidecar(tmp_path / "run.csv")
    rate = float(side["rate_hz"])  # 500 Hz, or what the start-up probe reduced it to
    back = first + int(np.argmax(I[first:] > 0))
    assert cols["k"][back] - cols["k"][first] > 0.75 * rate and (I[first:back] == 0).all()
    assert np.diff(np.concatenate(([0.0], I))).max() <= 50.0 / rate + 1e-9  # the slew limit per tick
    assert side["summary"]["safety"]["latches"] == 1 and side["summary"]["safety"]["arms"] == 1
    assert any("time latched" in r for r in side["verdict_reasons"])


def test_calibrate_on_the_shipped_bench_at_rest_and_the_run_says_what_it_applied(tmp_path) -> None:
    """No hand-made bench file: hil_sim --at-rest holds the shipped bench's shaker
    still; calibrate writes EXP.cal.yaml beside the experiment and prints the
    line that takes it; the run's start-up line names the file and its offsets."""
    hil, port = _start(tmp_path, BENCH, "--at-rest")
    exp = _exp_for(tmp_path, port)
    try:
        res = _mrctl("calibrate", str(exp))
    finally:
        hil.stop()
    assert res.returncode == 0, res.stderr
    cal = tmp_path / "exp.cal.yaml"
    assert cal.is_file() and "calibration: exp.cal.yaml" in res.stdout
    x_offset = yaml.safe_load(cal.read_text())["channels"]["x"]["offset_V"]
    w = yaml.safe_load(BENCH.read_text())["labjack_t7"]
    assert x_offset == pytest.approx(w["x"]["offset_V"], rel=0.02)  # at rest: the offset, not the stroke's mean
    hil, port = _start(tmp_path, BENCH)
    exp = _exp_for(tmp_path, port, calibration="exp.cal.yaml", duration_s=1.0)
    try:
        res = _mrctl("run", str(exp), "--no-log", "--status-socket", str(tmp_path / "s.sock"))
    finally:
        hil.stop()
    assert res.returncode == 0, res.stderr
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("calibration:"))
    assert str(cal.resolve()) in line and f"x offset {x_offset:.5f} V" in line and "applied" in line
