"""hil_sim: the simulated bench as its own process, behind the serial protocol.

The end-to-end tests start ``python -m hil_sim`` as a subprocess (cwd = repo
root), wait for its READY line and talk to it with mrctl's own SerialLink.
The device logic (watchdog, status bits, protocol errors) is also tested
in-process with an explicit clock, where timing can be exact. No latency or
wall-clock timing is asserted: the box is a shared, noisy 2-core VM.
"""

from __future__ import annotations

import bisect
import csv
import json
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import pytest

import serial

from hil_sim.bench import BenchDevice, clamp_setpoint  # noqa: E402
from hil_sim.config import ConfigError, validate_bench  # noqa: E402
from hil_sim.pty_endpoint import LinkPathError, PtyEndpoint  # noqa: E402
from hil_sim.serial_device import SerialDevice  # noqa: E402
from hil_sim.state import DeviceState  # noqa: E402
from hil_sim.truth import COLUMNS, TruthLog, summary_path  # noqa: E402
from mrctl.model.excitation import Sine  # noqa: E402
from mrctl.io.base import LinkError, Status  # noqa: E402
from mrctl.io.protocol import (  # noqa: E402
    PROTOCOL_VERSION,
    ErrorCode,
    ErrorFrame,
    FrameDecoder,
    FrameType,
    SampleFrame,
    SetpointFlag,
    encode_frame,
    encode_sample,
    encode_setpoint,
)
from mrctl.io.serial import SerialLink  # noqa: E402

pytestmark = pytest.mark.hil

ROOT = Path(__file__).resolve().parent.parent
READY_TIMEOUT_S = 10.0
EXIT_TIMEOUT_S = 15.0
SETPOINT_A = 0.4
SETPOINT_F32 = 0.4000000059604645  # 0.4 A after the float32 wire

WD = int(Status.WATCHDOG_TRIPPED)
ENABLED = int(Status.OUTPUT_ENABLED)


# --- helpers ---------------------------------------------------------------------
class SimProcess:
    """``python -m hil_sim`` in a subprocess; stdout lines collected by a thread."""

    def __init__(self, args: list[str], tmp_path: Path) -> None:
        env = dict(os.environ)
        env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.stderr_path = tmp_path / f"hil_sim-{time.monotonic_ns()}.stderr"
        self._err = open(self.stderr_path, "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil_sim", *args],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=self._err, text=True,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stdout: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def wait_ready(self, timeout: float = READY_TIMEOUT_S) -> str:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no READY line within {timeout} s; stderr: {self.stderr()}")
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                continue
            if line is None:
                raise AssertionError(f"hil_sim exited ({self.proc.wait()}) before READY; stderr: {self.stderr()}")
            self.stdout.append(line)
            if line.startswith("hil_sim ready"):
                return line

    def stderr(self) -> str:
        self._err.flush()
        return self.stderr_path.read_text()

    def wait(self, timeout: float = EXIT_TIMEOUT_S) -> int:
        return self.proc.wait(timeout)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        self._err.close()


@pytest.fixture
def spawn(tmp_path: Path):
    procs: list[SimProcess] = []

    def make(*args: str) -> SimProcess:
        p = SimProcess(list(args), tmp_path)
        procs.append(p)
        return p

    yield make
    for p in procs:
        p.close()


def run_to_exit(args: list[str], timeout: float = EXIT_TIMEOUT_S) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "hil_sim", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def read_truth(path: Path) -> list[dict[str, float]]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return [{k: (int(v) if k in ("k", "status") else float(v)) for k, v in r.items()} for r in rows]


def wait_for(pred, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while True:
        got = pred()
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def write_config(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bench.yaml"
    p.write_text(text)
    return p


# --- end to end over the serial protocol ----------------------------------------
def test_serial_exchanges_against_truth(spawn, tmp_path: Path) -> None:
    link_path = tmp_path / "tty"
    truth_path = tmp_path / "truth.csv"
    sim = spawn("--transport", "serial", "--link", str(link_path), "--duration", "60",
                "--truth", str(truth_path), "--seed", "3")
    ready = sim.wait_ready()
    assert f"link={link_path}" in ready and "transport=serial" in ready
    assert link_path.is_symlink() and os.readlink(link_path).startswith("/dev/")

    # ~500 exchanges at ~1 kHz with a constant setpoint (generous reply timeout:
    # the exchange returns as soon as the reply is there).
    link = SerialLink(str(link_path), 921600, timeout_s=0.2)
    link.open()
    samples = []
    errors = 0
    first_ok = True
    t0 = time.monotonic()
    for i in range(500):
        try:
            samples.append(link.exchange(SETPOINT_A))
        except LinkError:
            errors += 1
            first_ok = first_ok and i > 0
        nxt = t0 + (i + 1) * 1e-3
        while (left := nxt - time.monotonic()) > 0:
            time.sleep(left)
    last_seq = samples[-1].seq
    assert errors <= 25, link.counters()  # a noisy box may lose a few; not a protocol failure
    assert link.counters()["crc_errors"] == 0 and link.counters()["device_errors"] == 0

    # Device seq = device tick index: never goes back, advances with device time.
    seqs = [s.seq for s in samples]
    assert all(b >= a for a, b in zip(seqs, seqs[1:]))
    assert seqs[-1] - seqs[0] >= 200
    for s in samples:
        assert s.t_dev_s == pytest.approx(s.seq * 1e-3, abs=2e-6)
    # x and v follow the configured 10 mm / 1 Hz sine at the device time (noise: µm, 0.1 mm/s).
    sine = Sine(0.010, 1.0)
    for s in samples:
        assert abs(s.x_m - sine.position(s.t_dev_s)) < 5e-5, s
        assert abs(s.v_mps - sine.velocity(s.t_dev_s)) < 2e-3, s
        assert math.isfinite(s.F_N)  # the default bench has a load cell
    # the setpoint is applied (driver lag 2 ms) and the output reported enabled
    late = samples[len(samples) // 2:]
    assert sum(abs(s.current_A - SETPOINT_A) < 1e-3 for s in late) >= 0.8 * len(late)
    assert sum(bool(s.status & ENABLED) for s in late) >= 0.8 * len(late)

    # Stop sending (port stays open): after watchdog_ms the device applies 0 A
    # and latches WATCHDOG_TRIPPED. The truth log is flushed ~10x per second.
    def tripped():
        if not truth_path.exists():
            return None
        rows = read_truth(truth_path)
        after = [r for r in rows if r["k"] > last_seq and r["status"] & WD and r["I_cmd"] == 0.0]
        return rows if after else None

    rows = wait_for(tripped, 5.0, "the watchdog trip in the truth log")
    by_k = {r["k"]: r for r in rows}
    first_seq = seqs[0]
    ks = sorted(by_k)

    def applied_after(seq: int) -> bool:
        """The setpoint answered by the sample of tick ``seq`` is I_cmd within
        the next two device ticks (the clock reads the setpoint once per tick)."""
        i = bisect.bisect_right(ks, seq)
        return any(by_k[k]["I_cmd"] == SETPOINT_F32 for k in ks[i:i + 2])

    if first_ok:
        assert applied_after(first_seq), [(k, by_k[k]["I_cmd"]) for k in ks if first_seq - 2 <= k <= first_seq + 4]
        assert all(by_k[k]["I_cmd"] == 0.0 for k in ks if k <= first_seq)  # 0 A before any setpoint
    # every setpoint reaches the driver within a few ticks; a device stall of
    # more than watchdog_ms between two ticks (overloaded box) may trip it instead
    assert sum(applied_after(s.seq) for s in samples) >= 0.9 * len(samples)
    during = [by_k[k] for k in ks if first_seq < k <= last_seq]
    assert {r["I_cmd"] for r in during} <= {SETPOINT_F32, 0.0}
    k_trip = min(k for k in ks if k > last_seq and by_k[k]["status"] & WD and by_k[k]["I_cmd"] == 0.0)
    assert by_k[k_trip]["I_cmd"] == 0.0
    assert not by_k[k_trip]["status"] & ENABLED
    assert all(by_k[k]["I_cmd"] == 0.0 and by_k[k]["status"] & WD for k in ks if k >= k_trip)
    # truth x/v are the exact shaker motion; measured = truth + noise
    for k in ks[:: 97]:
        r = by_k[k]
        assert r["t"] == pytest.approx(k * 1e-3)
        assert r["x"] == pytest.approx(sine.position(r["t"]), abs=1e-12)
        assert abs(r["x_meas"] - r["x"]) < 2e-5
    # the samples the host got are the truth log's measured values of that tick
    for s in samples[::50]:
        r = by_k[s.seq]
        assert s.x_m == pytest.approx(r["x_meas"], abs=1e-8)
        assert s.F_N == pytest.approx(r["F_meas"], rel=1e-6, abs=1e-4)

    # Setpoints resume: applied again, the latched bit stays until CLEAR_FAULTS.
    s = link.exchange(SETPOINT_A)
    assert s.status & WD
    link.close()  # sends a disabled 0 A setpoint

    # Raw frames: echo of the host seq, BAD_VERSION, CLEAR_FAULTS.
    port = serial.serial_for_url(str(link_path), baudrate=921600, timeout=0.2)
    try:
        port.reset_input_buffer()
        dec = FrameDecoder()

        def ask(frame: bytes, seq: int):
            """The reply echoing ``seq`` (a late reply to the close setpoint may come first)."""
            port.write(frame)
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                for f in dec.feed(port.read(dec.bytes_needed())):
                    if f.echo_seq == seq:
                        return f
            raise AssertionError(f"no reply to seq {seq}")

        f = ask(encode_setpoint(0xFFFFFFF0, SETPOINT_A, SetpointFlag.ENABLE), 0xFFFFFFF0)
        assert isinstance(f, SampleFrame) and f.status & WD
        payload = encode_setpoint(7, 0.1)[9:15]
        f = ask(encode_frame(FrameType.SETPOINT, 0x1234, payload, version=2), 0x1234)
        assert isinstance(f, ErrorFrame) and f.code == ErrorCode.BAD_VERSION
        assert f.detail == PROTOCOL_VERSION
        f = ask(encode_setpoint(42, SETPOINT_A, SetpointFlag.ENABLE | SetpointFlag.CLEAR_FAULTS), 42)
        assert isinstance(f, SampleFrame)
        assert not f.status & WD and not f.status & int(Status.RX_ERROR)
    finally:
        port.close()

    # SIGTERM: clean stop, exit 0, symlink removed, truth log ends at 0 A, summary written.
    sim.proc.send_signal(signal.SIGTERM)
    assert sim.wait() == 0, sim.stderr()
    assert not link_path.exists() and not link_path.is_symlink()
    assert "Traceback" not in sim.stderr()
    rows = read_truth(truth_path)
    assert list(rows[0]) == list(COLUMNS)
    assert rows[-1]["I_cmd"] == 0.0
    ks = [r["k"] for r in rows]
    assert ks == sorted(set(ks))
    summ = json.loads(summary_path(truth_path).read_text())
    assert summ["bench"]["watchdog_trips"] >= 1
    assert summ["serial"]["replies"] >= 480
    assert summ["truth_log"]["rows_written"] == len(rows)
    assert summ["truth_log"]["rows_dropped"] == 0
    assert summ["config"]["seed"] == 3


def test_duration_stops_by_itself(tmp_path: Path) -> None:
    link_path = tmp_path / "tty"
    truth_path = tmp_path / "t.csv"
    r = run_to_exit(["--link", str(link_path), "--duration", "0.5", "--truth", str(truth_path)])
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("hil_sim ready") == 1
    assert not link_path.is_symlink()
    rows = read_truth(truth_path)
    assert 1 <= len(rows) <= 501
    assert rows[-1]["k"] <= 500  # deadlines 0..499, then the closing 0 A tick
    assert all(r["I_cmd"] == 0.0 and not r["status"] & WD for r in rows)  # no host: 0 A, no trip


def test_seeded_noise_is_reproducible_per_tick(tmp_path: Path) -> None:
    """Same seed → same measured values at the same tick, whatever deadlines
    each run happened to miss; another seed → other noise."""
    runs = {}
    for name, seed in (("a", "5"), ("b", "5"), ("c", "6")):
        truth = tmp_path / f"{name}.csv"
        r = run_to_exit(["--link", str(tmp_path / f"tty{name}"), "--duration", "0.5",
                         "--seed", seed, "--truth", str(truth)])
        assert r.returncode == 0, r.stderr
        runs[name] = {row["k"]: row for row in read_truth(truth)}
    common = sorted(set(runs["a"]) & set(runs["b"]) & set(runs["c"]))[:-1]  # last: closing tick
    assert len(common) >= 30  # runs on a loaded box skip different deadlines
    cols = ("x_meas", "v_meas", "F_meas")
    assert all(runs["a"][k][c] == runs["b"][k][c] for k in common for c in cols)
    assert sum(runs["a"][k]["x_meas"] != runs["c"][k]["x_meas"] for k in common) > len(common) // 2


def test_bad_config_exits_2_naming_the_key(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, "version: 1\nexcitation: {type: sine, amplitude_m: -1, frequency_hz: 1}\n"
                                 "plant: {sensors: {seed: 3}}\nwatchdog_ms: 0\n")
    r = run_to_exit(["--config", str(cfg), "--link", str(tmp_path / "tty")])
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert "excitation.amplitude_m" in r.stderr
    assert "plant.sensors.seed: unknown key" in r.stderr
    assert "watchdog_ms" in r.stderr
    assert all(line.startswith("hil_sim: ") for line in r.stderr.splitlines())
    assert r.stdout == "" and not (tmp_path / "tty").exists()


def test_missing_config_and_bad_yaml_exit_2(tmp_path: Path) -> None:
    r = run_to_exit(["--config", str(tmp_path / "nope.yaml")])
    assert r.returncode == 2 and "cannot read" in r.stderr and "Traceback" not in r.stderr
    cfg = write_config(tmp_path, "version: 1\nversion: 1\n")
    r = run_to_exit(["--config", str(cfg)])
    assert r.returncode == 2 and "duplicate key" in r.stderr and "Traceback" not in r.stderr


def test_link_path_regular_file_is_refused(tmp_path: Path) -> None:
    target = tmp_path / "important.txt"
    target.write_text("keep me")
    r = run_to_exit(["--link", str(target), "--duration", "1"])
    assert r.returncode == 2
    assert "refusing" in r.stderr and str(target) in r.stderr and "Traceback" not in r.stderr
    assert target.read_text() == "keep me"


def test_existing_symlink_is_replaced_and_removed(tmp_path: Path) -> None:
    link = tmp_path / "tty"
    os.symlink("/nonexistent/old-pty", link)
    ep = PtyEndpoint(link)
    try:
        assert os.readlink(link) == ep.tty_path
    finally:
        ep.close()
    assert not link.is_symlink()
    with pytest.raises(LinkPathError, match="does not exist"):
        PtyEndpoint(tmp_path / "no-dir" / "tty")


def test_truth_path_unwritable_exits_2(tmp_path: Path) -> None:
    r = run_to_exit(["--link", str(tmp_path / "tty"), "--truth", str(tmp_path / "no-dir" / "t.csv")])
    assert r.returncode == 2 and "--truth" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "tty").is_symlink()


def _modbus_exchanges(link, n: int = 30) -> list:
    sine = Sine(0.010, 1.0)
    link.open()
    try:
        got = []
        for _ in range(n):
            try:
                got.append(link.exchange(SETPOINT_A))
            except LinkError:
                pass
            time.sleep(1e-3)
    finally:
        link.close()
    assert len(got) >= n // 2
    assert got[-1].seq > got[0].seq
    for s in got:
        assert abs(s.x_m - sine.position(s.t_dev_s)) < 1e-4, s
    return got


def test_modbus_tcp_serves_and_stops(spawn) -> None:
    from mrctl.io.modbus import ModbusLink

    sim = spawn("--transport", "modbus-tcp", "--bind", "127.0.0.1:0", "--duration", "30")
    ready = sim.wait_ready()
    assert "transport=modbus-tcp" in ready
    host, port = ready.split("bind=")[1].split()[0].rsplit(":", 1)
    assert host == "127.0.0.1" and int(port) > 0
    _modbus_exchanges(ModbusLink("tcp", host=host, port=int(port), timeout_s=0.2))
    sim.proc.send_signal(signal.SIGTERM)
    assert sim.wait() == 0, sim.stderr()


def test_modbus_rtu_serves_on_a_pty_and_stops(spawn, tmp_path: Path) -> None:
    from mrctl.io.modbus import ModbusLink

    link_path = tmp_path / "rtu"
    sim = spawn("--transport", "modbus-rtu", "--link", str(link_path), "--baud", "921600", "--duration", "30")
    assert "transport=modbus-rtu" in sim.wait_ready() and link_path.is_symlink()
    _modbus_exchanges(ModbusLink("rtu", url=str(link_path), baudrate=921600, timeout_s=0.2))
    sim.proc.send_signal(signal.SIGTERM)
    assert sim.wait() == 0, sim.stderr()
    assert not link_path.is_symlink()


def test_modbus_tcp_port_in_use_exits_2() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = run_to_exit(["--transport", "modbus-tcp", "--bind", f"127.0.0.1:{port}", "--duration", "1"])
    assert r.returncode == 2 and "cannot listen" in r.stderr and "Traceback" not in r.stderr


# --- in process: device logic with an explicit clock --------------------------------
def _cfg(**over):
    data = {"version": 1, "excitation": {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0}}
    data.update(over)
    return validate_bench(data, Path("."), "test")


def test_config_defaults_and_overrides() -> None:
    c = _cfg()
    assert (c.rate_hz, c.watchdog_ms, c.load_cell, c.seed, c.duration_s, c.I_max_A) == (1000.0, 50, True, 0, None, 2.0)
    assert c.make_sensors() is None
    c = _cfg(seed=4, duration_s=3, plant={"driver_tau_s": 0.001, "sensors": {"F_noise_N": 1.0}})
    assert c.make_sensors() is not None and c.driver_tau_s == 0.001
    c2 = validate_bench({"version": 1, "seed": 4, "duration_s": 3,
                         "excitation": {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0}},
                        Path("."), seed=9, duration_s=1.5)
    assert (c2.seed, c2.duration_s) == (9, 1.5)
    with pytest.raises(ConfigError) as ei:
        validate_bench({"version": 2, "load_cell": "yes", "bogus": 1}, Path("."))
    text = "\n".join(ei.value.errors)
    for key in ("version", "load_cell", "bogus: unknown key", "excitation: missing"):
        assert key in text


def _device(**over) -> tuple[BenchDevice, DeviceState]:
    state = DeviceState()
    return BenchDevice(_cfg(**over), state), state


def test_a_late_tick_publishes_its_sample_as_of_its_deadline() -> None:
    """The sample is the bench at deadline k (its time k*dt): a device that stamps its samples (the
    emulated T7's CORE_TIMER) stamps that, not when a late clock thread published it."""
    dev, state = _device()
    t0 = 5_000_000_000
    dev.loop.t_start_ns = t0
    dev.tick(3, t0 + 3 * dev.loop.period_ns + 700_000)  # 0.7 ms late
    assert state.latest_sample_ns()[1] == t0 + 3 * dev.loop.period_ns
    dev.tick(7, t0 + 7 * dev.loop.period_ns)
    assert state.latest_sample_ns()[1] == t0 + 7 * dev.loop.period_ns


def test_watchdog_trips_after_watchdog_ms_and_latches() -> None:
    dev, state = _device(load_cell=False)
    dev.tick(0, 1_000_000)  # no setpoint yet: 0 A, no trip
    s = state.latest_sample()
    assert s.seq == 0 and s.current_A == 0.0 and s.status == int(Status.NO_LOAD_CELL) and math.isnan(s.F_N)
    state.set_setpoint(0.3, True)
    _, _, t_sp = state.setpoint()
    dev.tick(1, t_sp + 1_000_000)
    s = state.latest_sample()
    assert s.current_A == 0.3 and s.status & ENABLED and not s.status & WD
    dev.tick(50, t_sp + 50_000_000)  # exactly watchdog_ms: still alive
    assert dev.bench.I_cmd == 0.3 and not state.latest_sample().status & WD
    dev.tick(51, t_sp + 50_000_001)  # expired: 0 A, output off, latched
    s = state.latest_sample()
    assert dev.bench.I_cmd == 0.0 and s.status & WD and not s.status & ENABLED
    assert s.seq == 51 and s.t_dev_s == pytest.approx(0.051)
    assert dev.watchdog_trips == 1 and dev.first_trip_k == 51
    dev.tick(52, t_sp + 60_000_000)
    assert dev.watchdog_trips == 1  # one trip per stretch of silence
    state.set_setpoint(0.2, True)  # resumes: applied, bit stays latched
    _, _, t_sp = state.setpoint()
    dev.tick(53, t_sp)
    s = state.latest_sample()
    assert dev.bench.I_cmd == 0.2 and s.status & WD and s.status & ENABLED
    state.set_setpoint(0.2, True, clear_faults=True)
    dev.tick(54, t_sp)
    assert not state.latest_sample().status & WD


def test_the_emulators_own_stall_is_not_the_hosts_silence(monkeypatch) -> None:
    """A real device never stalls; hil_sim can (a loaded machine), and the
    setpoints sent meanwhile wait in its socket. A tick after a 300 ms stall
    does not trip the 50 ms watchdog; the next one does if still nothing came,
    and a setpoint read in between keeps it alive. Setpoints are stamped on a
    virtual clock, as the ticks are."""
    import hil_sim.state as state_mod

    now = [10_000_000_000]
    monkeypatch.setattr(state_mod, "time", types.SimpleNamespace(monotonic_ns=lambda: now[0]))
    dev, state = _device()
    state.set_setpoint(0.3, True)
    t_sp = now[0]
    dev.tick(1, t_sp + 1_000_000)
    dev.tick(300, t_sp + 300_000_000)  # the process stalled 299 ms
    assert dev.bench.I_cmd == 0.3 and not state.latest_sample().status & WD and dev.watchdog_trips == 0
    dev.tick(301, t_sp + 301_000_000)  # a period later, still no setpoint: the host's silence
    assert dev.bench.I_cmd == 0.0 and state.latest_sample().status & WD and dev.watchdog_trips == 1
    assert dev.first_trip_k == 301

    other, st2 = _device()
    st2.set_setpoint(0.3, True)
    t0 = now[0]
    other.tick(1, t0 + 1_000_000)
    other.tick(300, t0 + 300_000_000)
    now[0] = t0 + 300_500_000  # what waited in the socket, read after the stall
    st2.set_setpoint(0.25, True)
    other.tick(301, t0 + 301_000_000)
    assert other.bench.I_cmd == 0.25 and other.watchdog_trips == 0
    # Without the stall a 299 ms silence does trip (the rule is not "never trip").
    third, st3 = _device()
    st3.set_setpoint(0.3, True)
    t3 = now[0]
    for k in range(1, 300):
        third.tick(k, t3 + k * 1_000_000)
    assert third.watchdog_trips == 1 and third.bench.I_cmd == 0.0


def test_host_requested_watchdog_enable_and_clamp() -> None:
    dev, state = _device(I_max_A=1.0)
    state.set_setpoint(0.5, True, watchdog_ms=10)
    _, _, t_sp = state.setpoint()
    dev.tick(0, t_sp + 9_000_000)
    assert dev.bench.I_cmd == 0.5
    dev.tick(1, t_sp + 11_000_000)
    assert dev.bench.I_cmd == 0.0 and state.latest_sample().status & WD
    state.set_setpoint(0.5, False)  # ENABLE clear → 0 A, output off
    dev.tick(2, state.setpoint()[2])
    assert dev.bench.I_cmd == 0.0 and not state.latest_sample().status & ENABLED
    for req, applied in ((5.0, 1.0), (-1.0, 0.0), (math.nan, 0.0), (math.inf, 0.0)):
        state.set_setpoint(req, True)
        dev.tick(dev.k_last + 1, state.setpoint()[2])
        assert dev.bench.I_cmd == applied and state.latest_sample().status & int(Status.CURRENT_CLAMPED)
    assert clamp_setpoint(0.7, 1.0) == (0.7, False)


def test_skipped_ticks_keep_plant_and_noise_on_the_grid() -> None:
    sensors = {"x_noise_m": 1e-5, "v_noise_mps": 1e-3, "F_noise_N": 1.0}
    a, _ = _device(plant={"sensors": sensors})
    b, _ = _device(plant={"sensors": sensors})
    for k in range(40):
        a.tick(k, 0)
    for k in (0, 1, 7, 8, 30, 39):
        b.tick(k, 0)
    assert a.state.latest_sample() == b.state.latest_sample()
    assert a.bench.F == b.bench.F


def test_truth_log_rows_and_summary(tmp_path: Path) -> None:
    path = tmp_path / "truth.csv"
    log = TruthLog(path, rate_hz=100.0)  # batches of 10 rows
    for k in range(25):
        log.record((k, k * 0.01, 0.0, 0.1, -1.5, 0.25, 0.2, 1e-6, 0.1, math.nan, 8))
    out = log.close({"bench": {"ticks": 25}})
    rows = read_truth(path)
    assert [r["k"] for r in rows] == list(range(25)) and math.isnan(rows[0]["F_meas"])
    assert out["truth_log"]["rows_written"] == 25 and out["truth_log"]["rows_dropped"] == 0
    assert json.loads(summary_path(path).read_text())["bench"]["ticks"] == 25


# --- in process: the serial device's protocol handling -----------------------------
class _Wire:
    """SerialDevice on one end of a socketpair; we are the host on the other."""

    def __init__(self) -> None:
        self.host, dev = socket.socketpair()
        dev.setblocking(False)
        self._dev_sock = dev
        self.state = DeviceState()
        self.state.publish(_sample77())
        self.dev = SerialDevice(self.state, dev.fileno(), threading.Event(), I_max_A=1.0)
        self.dec = FrameDecoder()

    def send(self, data: bytes) -> list:
        self.dev.handle(data)
        self.host.settimeout(0.05)
        out = []
        try:
            while True:
                out += self.dec.feed(self.host.recv(4096))
        except (socket.timeout, BlockingIOError):
            pass
        return out

    def close(self) -> None:
        self.host.close()
        self._dev_sock.close()


def _sample77():
    from mrctl.io.base import Sample

    return Sample(seq=77, t_dev_s=0.077, x_m=0.001, v_mps=0.05, F_N=12.5,
                  status=int(Status.OUTPUT_ENABLED | Status.WATCHDOG_TRIPPED), current_A=0.3)


def test_serial_device_protocol_errors_and_status() -> None:
    w = _Wire()
    try:
        [f] = w.send(encode_setpoint(10, 0.3, SetpointFlag.ENABLE, 20))
        assert isinstance(f, SampleFrame) and (f.seq, f.echo_seq, f.t_dev_us) == (77, 10, 77000)
        assert f.F_N == 12.5 and f.status & WD and not f.status & int(Status.RX_ERROR)
        assert w.state.setpoint_ex()[:2] == (pytest.approx(0.3), True) and w.state.setpoint_ex()[3] == 20
        # corrupt CRC → BAD_CRC echoing the last good seq; RX_ERROR latched
        bad = bytearray(encode_setpoint(11, 0.9))
        bad[-1] ^= 0xFF
        [f] = w.send(bytes(bad))
        assert isinstance(f, ErrorFrame) and f.code == ErrorCode.BAD_CRC and f.echo_seq == 10
        assert w.state.setpoint()[0] == pytest.approx(0.3)  # not applied
        [f] = w.send(encode_setpoint(12, 1.5))  # out of range → CURRENT_CLAMPED
        assert f.status & int(Status.RX_ERROR) and f.status & int(Status.CURRENT_CLAMPED)
        # a host-to-device SAMPLE is not something the device handles
        [f] = w.send(encode_sample(1, 2, 3, 0, 0, 0, 0, 0))
        assert isinstance(f, ErrorFrame) and f.code == ErrorCode.UNKNOWN_TYPE and f.echo_seq == 1
        # CLEAR_FAULTS clears RX_ERROR and (in the reply already) WATCHDOG_TRIPPED
        [f] = w.send(encode_setpoint(13, 0.2, SetpointFlag.ENABLE | SetpointFlag.CLEAR_FAULTS))
        assert not f.status & int(Status.RX_ERROR) and not f.status & WD and f.echo_seq == 13
        # two frames in one chunk, split frames across chunks
        two = encode_setpoint(14, 0.1) + encode_setpoint(15, 0.1)
        assert [f.echo_seq for f in w.send(two[:20])] == [14]
        assert [f.echo_seq for f in w.send(two[20:])] == [15]
        c = w.dev.counters()
        assert c["setpoints"] == 5 and c["crc_errors"] == 1 and c["errors_sent"] == 2
    finally:
        w.close()


def test_truth_log_cooperative_mode_writes_every_row_exactly(tmp_path):
    """Inline serving formats the truth log from the clock's idle spin (no
    writer thread): every recorded row must still reach the file, in order."""
    from hil_sim.truth import TruthLog
    from mrctl.daemon.recorder import read_run

    log = TruthLog(tmp_path / "t.csv", rate_hz=1000.0, batch_s=0.1, threaded=False)
    rows = [(k, k * 1e-3, 0.1 * k, -0.2, 1.0 / (k + 1), 0.3, 0.25, 0.0, 0.0, float("nan"), k % 4)
            for k in range(250)]
    for r in rows:
        log.record(r)
        log.work_once()  # what the idle spin does between ticks
    out = log.close()
    assert out["truth_log"]["rows_written"] == 250 and out["truth_log"]["error"] is None
    cols = read_run(tmp_path / "t.csv")
    assert list(cols["k"]) == list(range(250))
    assert [float(x) for x in cols["F_true"]] == [r[4] for r in rows]  # %r: exact


# -- device pacing: the SYNC flag -------------------------------------------------
def _replies(fd: int) -> list:
    os.set_blocking(fd, False)
    try:
        data = os.read(fd, 4096)
    except BlockingIOError:
        return []
    return FrameDecoder().feed(data)


def test_sync_setpoint_is_answered_after_the_tick_that_applies_it() -> None:
    """SYNC: no reply on arrival; the tick after it applies the setpoint and
    the reply carries that tick's sample (seq, applied current). A SYNC
    request that arrives after a tick has read its setpoint waits for the next."""
    dev, state = _device()
    dev.tick(0, 1_000_000)
    r, w = os.pipe()
    try:
        ser = SerialDevice(state, w, threading.Event(), 2.0)
        ser.handle(encode_setpoint(7, 0.25, int(SetpointFlag.ENABLE | SetpointFlag.SYNC), 50))
        assert _replies(r) == [] and state.setpoint()[0] == 0.25  # stored, not answered yet
        dev.tick(1, state.setpoint()[2])
        (f,) = _replies(r)
        assert isinstance(f, SampleFrame) and f.echo_seq == 7 and f.seq == 1
        assert f.current_A == pytest.approx(dev.bench.I_applied, rel=1e-6) and dev.bench.I_cmd == 0.25
        # without SYNC the answer is immediate, with the latest sample
        ser.handle(encode_setpoint(8, 0.3, int(SetpointFlag.ENABLE), 50))
        (f,) = _replies(r)
        assert f.echo_seq == 8 and f.seq == 1
        # a SYNC request landing between the setpoint read and the publish of
        # tick 2 is applied, and answered, at tick 3
        state.setpoint_ex()  # tick 2 reads its setpoint ...
        ser.handle(encode_setpoint(9, 0.35, int(SetpointFlag.ENABLE | SetpointFlag.SYNC), 50))
        state.publish(state.latest_sample()._replace(seq=2))
        state.run_owed()  # ... and publishes: the request is not for it
        assert _replies(r) == []
        dev.tick(3, state.setpoint()[2])
        (f,) = _replies(r)
        assert f.echo_seq == 9 and f.seq == 3 and dev.bench.I_cmd == pytest.approx(0.35, rel=1e-6)
    finally:
        os.close(r)
        os.close(w)


def test_modbus_sync_write_is_answered_by_the_clock_with_the_fresh_sample() -> None:
    """Modbus: bit 2 of the enable register is SYNC. The FC23 reply is
    deferred; the clock sends it after the tick, with that tick's registers."""
    from hil_sim.modbus_device import Deferred, ModbusDevice
    from mrctl.io.modbus import decode_tcp_response, mbap_frame, read_write_request_pdu
    from mrctl.io.registers import default_register_map

    dev, state = _device()
    dev.tick(0, 1_000_000)
    rmap = default_register_map()
    mdev = ModbusDevice(state, rmap)
    rb, wb = rmap.read_blocks[0], rmap.write_block
    data = bytearray(2 * wb.count)
    rmap.encode_write_into(data, 0, 0.45, 1 | 4, 50)
    req = mbap_frame(3, rmap.unit_id, read_write_request_pdu(rb.address, rb.count, wb.address, data))
    resp = mdev.handle_tcp_frame(req)
    assert isinstance(resp, Deferred) and state.setpoint()[0] == pytest.approx(0.45)
    sent: list[bytes] = []
    resp.owed.attach(lambda: sent.append(resp.build()))
    assert sent == []
    dev.tick(1, state.setpoint()[2])
    (adu,) = sent
    regs = decode_tcp_response(adu, 3, rmap.unit_id, 23, rb.count)
    vals = rmap.decode_read(regs)
    assert vals.seq == 1 and vals.current_applied_A == pytest.approx(dev.bench.I_applied, rel=1e-6)
    # the same write without SYNC is answered at once
    rmap.encode_write_into(data, 0, 0.45, 1, 50)
    req = mbap_frame(4, rmap.unit_id, read_write_request_pdu(rb.address, rb.count, wb.address, data))
    assert isinstance(mdev.handle_tcp_frame(req), bytes)


# -- Modbus TCP served inline from the clock thread (--serve inline) ----------------
def _fc23_request(tid: int, current_A: float, flags: int):
    from mrctl.io.modbus import mbap_frame, read_write_request_pdu
    from mrctl.io.registers import default_register_map

    rmap = default_register_map()
    rb, wb = rmap.read_blocks[0], rmap.write_block
    data = bytearray(2 * wb.count)
    rmap.encode_write_into(data, 0, current_A, flags, 50)
    return rmap, mbap_frame(tid, rmap.unit_id, read_write_request_pdu(rb.address, rb.count, wb.address, data))


def _poll_until(srv, cond, timeout_s: float = 2.0) -> None:
    t_end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < t_end, "the inline server did not get there"
        srv.poll_once()
        time.sleep(1e-4)


def _recv_adu(c: socket.socket, srv, timeout_s: float = 2.0) -> bytes:
    """Poll the server (as the clock's spin does) until a reply reaches the client."""
    c.setblocking(False)
    t_end = time.monotonic() + timeout_s
    while True:
        try:
            data = c.recv(4096)
            if data:
                return data
        except BlockingIOError:
            pass
        assert time.monotonic() < t_end, "no reply"
        srv.poll_once()
        time.sleep(1e-4)


def test_tcp_inline_sync_reply_is_sent_by_the_tick_with_its_sample() -> None:
    """Inline serving: the clock parses a SYNC write while it spins, stores the
    setpoint, sends nothing; the next tick applies it and sends the reply with
    that tick's registers. A plain write is answered at once."""
    from hil_sim.modbus_tcp import ModbusTcpInline
    from mrctl.io.modbus import decode_tcp_response

    dev, state = _device()
    dev.tick(0, 1_000_000)
    srv = ModbusTcpInline(state, "127.0.0.1", 0)
    c = socket.create_connection(("127.0.0.1", srv.port))
    try:
        rmap, req = _fc23_request(3, 0.45, 1 | 4)
        rb = rmap.read_blocks[0]
        c.sendall(req)
        _poll_until(srv, lambda: state.setpoint()[0] == pytest.approx(0.45))
        for _ in range(50):
            srv.poll_once()
        c.setblocking(False)
        with pytest.raises(BlockingIOError):  # owed to the tick, not sent on arrival
            c.recv(4096)
        dev.tick(1, state.setpoint()[2])
        vals = rmap.decode_read(decode_tcp_response(_recv_adu(c, srv), 3, rmap.unit_id, 23, rb.count))
        assert vals.seq == 1 and vals.current_applied_A == pytest.approx(dev.bench.I_applied, rel=1e-6)
        assert dev.bench.I_cmd == pytest.approx(0.45)
        _, req = _fc23_request(4, 0.2, 1)
        c.sendall(req)
        vals = rmap.decode_read(decode_tcp_response(_recv_adu(c, srv), 4, rmap.unit_id, 23, rb.count))
        assert vals.seq == 1 and state.setpoint()[0] == pytest.approx(0.2)  # at once, latest sample
    finally:
        c.close()
        srv.close()


def test_tcp_inline_reply_faults_delay_drop_and_bad_stream() -> None:
    """The inline server applies the reply faults itself: a delayed reply goes
    out no earlier than delay_s, a dropped one never; an impossible MBAP header
    from a client closes that connection only."""
    from hil_sim.faults import FaultBit, FaultSchedule, parse_fault_arg
    from hil_sim.modbus_tcp import ModbusTcpInline

    state = DeviceState()
    state.faults = FaultSchedule([parse_fault_arg("delay_replies@0+10,delay_s=0.05")[0]], 1000.0)
    srv = ModbusTcpInline(state, "127.0.0.1", 0)
    c = socket.create_connection(("127.0.0.1", srv.port))
    other = socket.create_connection(("127.0.0.1", srv.port))
    try:
        state.fault_bits = state.faults.active(5)  # what the clock does each tick
        assert state.fault_bits == int(FaultBit.DELAY_REPLIES)
        t0 = time.monotonic()
        c.sendall(_fc23_request(1, 0.1, 1)[1])
        assert _recv_adu(c, srv)[:2] == b"\x00\x01"
        assert time.monotonic() - t0 >= 0.05 and srv.dev.fault_counts["replies_delayed"] == 1
        state.fault_bits = int(FaultBit.DROP_REPLIES)
        c.sendall(_fc23_request(2, 0.1, 1)[1])
        _poll_until(srv, lambda: srv.dev.fault_counts["replies_dropped"] == 1)
        state.fault_bits = 0
        c.sendall(b"\x00\x03\x00\x07\x00\x06\x01\x03\x00\x00\x00\x01")  # protocol id 7
        _poll_until(srv, lambda: srv.dev.frames_dropped == 1)
        assert c.recv(4096) == b""  # closed by the device
        other.sendall(_fc23_request(5, 0.3, 1)[1])
        assert _recv_adu(other, srv)[:2] == b"\x00\x05"  # the other client is served on
    finally:
        c.close()
        other.close()
        srv.close()


def test_sync_owed_reply_never_leaks_to_the_next_request() -> None:
    """A SYNC write that gets no reply (an RTU broadcast) must not leave its
    owed reply behind: the next plain request from the same thread is
    answered at once, not deferred to the clock."""
    from hil_sim.modbus_device import ModbusDevice
    from mrctl.io.modbus import crc16_modbus, read_write_request_pdu
    from mrctl.io.registers import default_register_map

    state = DeviceState()
    rmap = default_register_map()
    mdev = ModbusDevice(state, rmap)
    rb, wb = rmap.read_blocks[0], rmap.write_block

    def rtu(unit: int, flags: int) -> bytes:
        data = bytearray(2 * wb.count)
        rmap.encode_write_into(data, 0, 0.3, flags, 50)
        body = bytes((unit,)) + read_write_request_pdu(rb.address, rb.count, wb.address, data)
        return body + crc16_modbus(body).to_bytes(2, "little")

    assert mdev.handle_rtu_frame(rtu(0, 1 | 4)) is None  # broadcast: applied, never answered
    assert state.setpoint()[0] == pytest.approx(0.3)
    resp = mdev.handle_rtu_frame(rtu(rmap.unit_id, 1))
    assert isinstance(resp, bytes) and resp[:2] == bytes((rmap.unit_id, 23))


def test_rtu_inline_sync_reply_is_sent_by_the_tick_and_junk_is_skipped() -> None:
    """Inline RTU on a pty: junk before a SYNC write is hunted through, the
    write is applied and its reply waits for the tick, which sends it with
    that tick's registers."""
    import tty

    from hil_sim.modbus_device import ModbusDevice
    from hil_sim.modbus_rtu import ModbusRtuInline, rtu_silence_s
    from mrctl.io.modbus import crc16_modbus, decode_rtu_response, read_write_request_pdu
    from mrctl.io.registers import default_register_map

    dev, state = _device()
    dev.tick(0, 1_000_000)
    rmap = default_register_map()
    rb, wb = rmap.read_blocks[0], rmap.write_block
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    try:
        srv = ModbusRtuInline(ModbusDevice(state, rmap), master, rtu_silence_s(921600))
        data = bytearray(2 * wb.count)
        rmap.encode_write_into(data, 0, 0.45, 1 | 4, 50)
        body = bytes((rmap.unit_id,)) + read_write_request_pdu(rb.address, rb.count, wb.address, data)
        os.write(slave, b"\x00\xff\x13" + body + crc16_modbus(body).to_bytes(2, "little"))
        _poll_until(srv, lambda: state.setpoint()[0] == pytest.approx(0.45))
        assert srv.dev.bytes_discarded == 3
        os.set_blocking(slave, False)
        for _ in range(50):
            srv.poll_once()
        with pytest.raises(BlockingIOError):  # owed to the tick
            os.read(slave, 4096)
        dev.tick(1, state.setpoint()[2])
        t_end = time.monotonic() + 2
        reply = b""
        while len(reply) < 5 + 2 * rb.count and time.monotonic() < t_end:
            try:
                reply += os.read(slave, 4096)
            except BlockingIOError:
                time.sleep(1e-4)
        vals = rmap.decode_read(decode_rtu_response(reply, rmap.unit_id, 23, rb.count))
        assert vals.seq == 1 and dev.bench.I_cmd == pytest.approx(0.45)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_sync_replies_go_through_the_reply_faults(transport: str) -> None:
    """A device-paced (SYNC) reply, sent by the clock after its tick, meets the
    same reply faults as any other: drop_replies drops it. (It once bypassed
    them, so Modbus faults did nothing under device pacing.)"""
    import tty

    from hil_sim.faults import FaultBit, FaultSchedule, parse_fault_arg
    from hil_sim.modbus_device import ModbusDevice
    from hil_sim.modbus_rtu import ModbusRtuInline, rtu_silence_s
    from hil_sim.modbus_tcp import ModbusTcpInline
    from mrctl.io.modbus import crc16_modbus

    dev, state = _device()
    dev.tick(0, 1_000_000)
    state.faults = FaultSchedule([parse_fault_arg("drop_replies@0+10")[0]], 1000.0)
    rmap, req = _fc23_request(3, 0.45, 1 | 4)
    if transport == "tcp":
        srv = ModbusTcpInline(state, "127.0.0.1", 0, rmap)
        c = socket.create_connection(("127.0.0.1", srv.port))
        send, close = c.sendall, lambda: (c.close(), srv.close())

        def received() -> bytes:
            c.setblocking(False)
            try:
                return c.recv(4096)
            except BlockingIOError:
                return b""
    else:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        srv = ModbusRtuInline(ModbusDevice(state, rmap), master, rtu_silence_s(921600))
        body = bytes((rmap.unit_id,)) + req[7:]
        req = body + crc16_modbus(body).to_bytes(2, "little")
        send, close = (lambda b: os.write(slave, b)), (lambda: (os.close(master), os.close(slave)))
        os.set_blocking(slave, False)

        def received() -> bytes:
            try:
                return os.read(slave, 4096)
            except BlockingIOError:
                return b""
    try:
        send(req)
        _poll_until(srv, lambda: state.setpoint()[0] == pytest.approx(0.45))
        state.fault_bits = state.faults.active(1)  # what the clock does each tick ...
        assert state.fault_bits == int(FaultBit.DROP_REPLIES)
        dev.faults = None  # ... here by hand, so the bench keeps these bits
        dev.tick(1, state.setpoint()[2])
        for _ in range(200):
            srv.poll_once()
        time.sleep(0.02)
        assert received() == b""
        assert srv.dev.fault_counts["replies_dropped"] == 1
    finally:
        close()


def test_sync_reply_owed_across_a_hangup_is_lost_not_raised() -> None:
    """A SYNC reply owed when the pty is hung up (the disconnect fault) is
    sent by the clock thread into a closed fd: it must be lost, as on a
    pulled cable, not raise there (that stopped the whole bench once)."""
    dev, state = _device()
    dev.tick(0, 1_000_000)
    r, w = os.pipe()
    ser = SerialDevice(state, w, threading.Event(), 2.0)
    ser.handle(encode_setpoint(7, 0.25, int(SetpointFlag.ENABLE | SetpointFlag.SYNC), 50))
    os.close(w)  # hung up before the tick
    os.close(r)
    dev.tick(1, state.setpoint()[2])  # runs the owed reply: must not raise
    assert ser.replies == 0 and ser.replies_dropped == 1
    assert state.latest_sample().seq == 1


def test_ready_file_is_written_when_serving_and_removed_at_exit(tmp_path: Path) -> None:
    """--ready-file: a stale file from an earlier bench is removed at start,
    the ready line is written once the bench serves, and removed at exit
    (README's HIL recipe waits for it)."""
    from hil_sim.testing.harness import HilSim

    ready = tmp_path / "ready"
    ready.write_text("stale\n")
    hil = HilSim("--transport", "modbus-tcp", "--bind", "127.0.0.1:0", "--duration", "30",
                 "--ready-file", str(ready), workdir=tmp_path)
    try:
        text = ready.read_text()
        assert text == hil.ready + "\n" and text.startswith("hil_sim ready transport=modbus-tcp bind=127.0.0.1:")
    finally:
        code = hil.stop()
    assert code == 0 and not ready.exists()
    assert not list(tmp_path.glob(".ready.*.tmp"))
