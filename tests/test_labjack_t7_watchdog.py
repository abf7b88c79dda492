"""The LabJack T7's strict watchdog, Modbus Feedback, device clock and E-stop input
(issues 32 and 34): the emulator as LabJack documents the T7, and mrctl's preset link against it."""

from __future__ import annotations

import math
import os
import socket
import struct
import threading
import time
from pathlib import Path

import pytest
import yaml

from hil_sim.state import DeviceState
from hil_sim.testing.harness import ROOT
from mrctl.cli import main as mrctl_main
from mrctl.io.base import Sample, Status

BENCH = ROOT / "config" / "hil_labjack_t7_bench.yaml"
EXPERIMENT = ROOT / "config" / "experiments" / "labjack_t7.yaml"
KEY = 0x4D524354


class _Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def _wiring(**changes):
    from hil_sim.labjack_t7 import t7_fields
    from mrctl.util.schema import validate_fields

    data = yaml.safe_load(BENCH.read_text())["labjack_t7"]
    data.update(latency_s=0.0, latency_io_extra_s=0.0)
    data.update(changes)
    node, errors = validate_fields(t7_fields(), data, "labjack_t7")
    assert errors == []
    return node


def _device(clock=None, **changes):
    from hil_sim.labjack_t7 import T7Device

    state = DeviceState()
    state.publish(Sample(0, 0.0, 0.001, math.nan, 20.0, 0, 0.1))
    return T7Device(state, _wiring(**changes), **({"clock_ns": clock} if clock else {})), state


def _w32(address: int, v: int) -> bytes:
    return struct.pack(">BHHBI", 16, address, 2, 4, v)


def _wf(address: int, v: float) -> bytes:
    return struct.pack(">BHHBf", 16, address, 2, 4, v)


def _arm(dev, strict: bool, reset: bool = False) -> None:
    for a, v in ((61604, 1), (61610, int(strict)), (61612, KEY), (61620, int(reset)), (61640, 1), (61600, 1)):
        assert dev.handle_pdu(_w32(a, v))[0] == 16, a


# -- the watchdog as datasheet 23.0 describes it, on a virtual clock -----------------------------
@pytest.mark.parametrize("strict", [True, False])
def test_a_poller_keeps_the_watchdog_alive_only_when_it_is_not_strict(strict) -> None:
    clock = _Clock()
    dev, state = _device(clock)
    _arm(dev, strict)
    assert dev.handle_pdu(_wf(1000, 2.0))[0] == 16
    for _ in range(25):  # another client reads AIN0 every 100 ms for 2.5 s
        clock.ns += 100_000_000
        dev.handle_pdu(struct.pack(">BHH", 3, 0, 2))
        dev.check()
    if strict:
        assert dev.dac_V[0] == 0.0 and len(dev.watchdog_trips) == 2  # at 1 s and again at 2 s: repeated
        assert state.setpoint()[0] == 0.0
    else:
        assert dev.dac_V[0] == 2.0 and dev.watchdog_trips == []


def test_strict_watchdog_is_cleared_by_the_key_alone_and_repeats_its_actions() -> None:
    clock = _Clock()
    dev, _state = _device(clock)
    _arm(dev, True)
    for _ in range(30):  # the key every 100 ms: no trip
        clock.ns += 100_000_000
        dev.handle_pdu(_w32(61614, KEY))
        dev.check()
    assert dev.watchdog_trips == []
    dev.handle_pdu(_w32(61614, KEY + 1))  # a wrong key clears nothing
    dev.handle_pdu(_wf(1000, 3.0))
    clock.ns += 1_000_000_000
    dev.check()
    assert dev.watchdog_trips == [clock.ns] and dev.dac_V[0] == 0.0
    dev.handle_pdu(_wf(1000, 3.0))  # another client drives DAC0 again: the next expiry zeroes it again
    clock.ns += 1_000_000_000
    dev.check()
    assert len(dev.watchdog_trips) == 2 and dev.dac_V[0] == 0.0
    assert dev.handle_pdu(struct.pack(">BHH", 3, 61614, 2)) == bytes((0x83, 0x02))  # the clear register is write-only
    assert dev.handle_pdu(_w32(61610, 0)) == bytes((0x90, 0x03))  # refused while enabled


def test_reset_on_timeout_restarts_the_device_and_a_pulled_up_enable_line_fires_the_monostable() -> None:
    clock = _Clock()
    dev, state = _device(clock, enable={"dio": 0, "hold_s": 0.04, "pull_down": 0})
    _arm(dev, True, reset=True)
    dev.handle_pdu(_wf(40000, 1.0))
    dev.handle_pdu(struct.pack(">BHHBH", 16, 2000, 1, 2, 0))  # enable output low
    dev.handle_pdu(_wf(1000, 2.0))
    flash = dev.io.flash_writes
    clock.ns += 1_000_000_000
    dev.check()
    assert dev.generation == 1 and dev.dac_V[0] == 0.0 and dev.io.ain_range[0] == 0.0
    assert dev.io.dio_dir == [0] * 23 and dev.io.flash["enable"] == 1 and dev.io.flash_writes == flash
    assert dev.enable_rises == [clock.ns]  # the pull-up came back: a rising edge, the driver enabled
    assert state.setpoint()[1] is True


def test_dio_reads_make_inputs_writes_make_outputs_and_the_estop_reads_its_level() -> None:
    dev, state = _device(estop={"dio": 4, "active": "low"})
    rd = lambda a, n=1: dev.handle_pdu(struct.pack(">BHH", 3, a, n))  # noqa: E731
    assert rd(2004) == bytes((3, 2, 0, 1))  # closed contact: high
    state.estop_input = True
    assert rd(2004) == bytes((3, 2, 0, 0))
    assert rd(2005) == bytes((3, 2, 0, 1))  # an unwired input: the pull-up
    dev.handle_pdu(struct.pack(">BHHBH", 16, 2005, 1, 2, 0))
    assert struct.unpack(">I", rd(2850, 2)[2:])[0] == 1 << 5  # DIO5 an output now, DIO4 an input
    assert struct.unpack(">I", rd(2800, 2)[2:])[0] >> 4 & 3 == 0


# -- on the wire: MBFB by hand, two connections, the link -------------------------------------------
@pytest.fixture
def served():
    """An emulated T7 served on loopback from a thread (the device's timers run there too)."""
    from hil_sim.modbus_tcp import ModbusTcpInline

    made = []

    def start(clock=None, **changes):
        dev, state = _device(clock, **changes)
        srv = ModbusTcpInline(state, "127.0.0.1", 0, device=dev, max_clients=dev.max_connections)
        stop = threading.Event()

        def run() -> None:
            while not stop.is_set():
                srv.poll_once()
                dev.check()
                time.sleep(5e-5)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        made.append((stop, t, srv))
        return dev, state, srv.port

    yield start
    for stop, t, srv in made:
        stop.set()
        t.join(2)
        srv.close()


def _ask(sock: socket.socket, adu: bytes) -> bytes:
    sock.settimeout(5.0)
    sock.sendall(adu)
    data = b""
    while len(data) < 6 or len(data) < 6 + (data[4] << 8 | data[5]):
        chunk = sock.recv(512)
        assert chunk, "closed"
        data += chunk
    return data


def test_a_raw_mbfb_frame_built_by_hand_is_answered_and_a_third_client_is_refused(served) -> None:
    dev, state, port = served()
    # the documented layout, byte by byte: write DAC0 (1000) 1.25 V, then read AIN0 (address 0, 2 registers)
    pdu = bytes([0x4C, 0x01, 0x03, 0xE8, 0x02]) + bytes.fromhex("3fa00000") + bytes([0x00, 0x00, 0x00, 0x02])
    adu = bytes([0x12, 0x34, 0x00, 0x00, 0x00, len(pdu) + 1, 0x01]) + pdu
    with socket.create_connection(("127.0.0.1", port)) as a, socket.create_connection(("127.0.0.1", port)) as b:
        r = _ask(a, adu)
        assert r[:8] == bytes([0x12, 0x34, 0, 0, 0, 6, 0x01, 0x4C]) and len(r) == 12
        assert struct.unpack(">f", r[8:])[0] == pytest.approx(0.001 / 0.0025 + 2.47, abs=5 * 20 / 65536)  # noise
        assert dev.dac_V[0] == 1.25 and state.setpoint()[0] == pytest.approx(0.5)
        bad = bytes([0x4C, 0x02, 0, 0, 2])  # frame type 2: no such frame
        assert _ask(b, bytes([0, 1, 0, 0, 0, len(bad) + 1, 1]) + bad)[7:] == bytes([0xCC, 0x03])
        with socket.create_connection(("127.0.0.1", port)) as c:
            c.settimeout(2.0)
            assert c.recv(16) == b""  # the third connection is closed at once


def _link(port: int, tmp_path: Path, safety: dict | None = None, **backend):
    from mrctl.config import load_experiment
    from mrctl.io import link_class_for

    data = yaml.safe_load(EXPERIMENT.read_text())
    data["backend"].update(port=port, **backend)
    data["safety"].update(safety or {})
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    cfg = load_experiment(p)
    return link_class_for(cfg.backend).from_config(cfg.backend), p


def test_the_link_sends_one_mbfb_request_per_tick_stamped_by_core_timer(served, tmp_path) -> None:
    dev, state, port = served()
    link, _ = _link(port, tmp_path)
    link.open()
    try:
        assert link.protocol == "mbfb" and link.core_timer and "one MBFB request per tick" in link.describe()
        before = dict(dev.fc_counts)
        samples = []
        for k in range(20):
            state.publish(Sample(k, k * 1e-3, 0.001, math.nan, 20.0, 0, 0.1))
            samples.append(link.exchange(0.2))
            time.sleep(0.002)
        assert {fc: n - before.get(fc, 0) for fc, n in dev.fc_counts.items()} == {3: 0, 16: 0, 76: 20}
        t = [s.t_dev_s for s in samples]
        assert all(b > a for a, b in zip(t, t[1:])) and len({s.seq for s in samples}) == 20
        state.publish(Sample(99, 0.1, 0.001, math.nan, 20.0, 0, 0.1))
        s1, s2 = link.exchange(0.2), link.exchange(0.2)
        assert s1.seq == s2.seq  # no new conversion: the device time does not advance (stale to the supervisor)
        assert dev.dac_V[0] == pytest.approx(0.5)  # 0.2 A x 2.5 V/A
    finally:
        link.close()
    assert dev.dac_V[0] == 0.0


def test_host_time_stamps_still_tell_a_stale_sample_by_core_timer(served, tmp_path) -> None:
    """backend.time_stamps: host: each sample is stamped by the host's clock when its reply
    arrives; CORE_TIMER is still read in the same request and is the sample's seq, so a reply
    without a new conversion is still stale to the supervisor."""
    dev, state, port = served()
    link, _ = _link(port, tmp_path, time_stamps="host")
    link.open()
    try:
        assert link.core_timer and "host clock (CORE_TIMER for staleness)" in link.describe()
        seqs = []
        for k in range(5):
            state.publish(Sample(k, k * 1e-3, 0.001, math.nan, 20.0, 0, 0.1))
            before = time.monotonic()
            s = link.exchange(0.2)
            assert before <= s.t_dev_s <= time.monotonic()  # the host's clock, read at the reply
            seqs.append(s.seq)
            time.sleep(0.002)
        assert len(set(seqs)) == 5
        s1, s2 = link.exchange(0.2), link.exchange(0.2)
        assert s1.seq == s2.seq and s2.t_dev_s > s1.t_dev_s  # stale by the device's timer, not by the stamps
    finally:
        link.close()


def test_core_timer_going_back_is_counted_and_the_count_outlives_a_reopen(served, tmp_path) -> None:
    """The emulated T7's CORE_TIMER restarts from 0 under a live connection (what a restart the
    network survived would look like): one device_clock_reset, in counters(), still there after
    the link is closed and opened again (the unwrapper is forgotten at open, not replaced)."""
    dev, state, port = served()
    link, _ = _link(port, tmp_path)

    def tick(k: int) -> Sample:  # a new conversion of the bench (CORE_TIMER stamps its time), then a tick
        state.publish(Sample(k, k * 1e-3, 0.001, math.nan, 20.0, 0, 0.1))
        return link.exchange(0.1)

    link.open()
    try:
        t = [tick(k).t_dev_s for k in range(3)]
        assert t[0] < t[1] < t[2] and link.counters()["device_clock_resets"] == 0
        with dev._lock:
            dev.io.boot_ns = dev.clock_ns()  # CORE_TIMER from 0 again
        assert tick(3).t_dev_s < t[2] and link.counters()["device_clock_resets"] == 1
    finally:
        link.close()
    link.open()
    try:
        tick(4)
        assert link.counters()["device_clock_resets"] == 1
    finally:
        link.close()


def test_a_t7_without_mbfb_gets_fc3_fc16_and_an_old_firmware_is_refused(served, tmp_path) -> None:
    from mrctl.errors import LinkFailure
    from mrctl.io.devices.link import DeviceSetupError

    _dev, _state, port = served(mbfb=0)
    link, _ = _link(port, tmp_path)
    link.open()
    try:
        assert link.protocol == "plain" and "no MBFB" in link.describe()
        assert math.isfinite(link.exchange(0.1).x_m)
    finally:
        link.close()
    _dev, _state, port = served(firmware=1.0010)
    link, _ = _link(port, tmp_path)
    with pytest.raises(DeviceSetupError, match=r"firmware 1\.0010 is too old: mrctl needs 1\.0016") as e:
        link.open()
    assert isinstance(e.value, LinkFailure) and e.value.exit_code == 3


def test_a_preset_without_modbus_mbfb_gets_fc3_fc16_without_trying_mbfb(served, tmp_path) -> None:
    """The MBFB function code is the preset's (modbus.mbfb): without it, no MBFB request is sent."""
    import dataclasses

    from mrctl.io.devices import Preset
    from mrctl.io.devices.link import PresetLink

    dev, _state, port = served()
    link, _ = _link(port, tmp_path)
    p = link.setup.preset
    data = {**p.data, "modbus": {k: v for k, v in p.data["modbus"].items() if k != "mbfb"}}
    setup = dataclasses.replace(link.setup, preset=Preset(p.name, p.description, p.source, data))
    with pytest.raises(ValueError, match="has no Modbus Feedback"):
        PresetLink(setup, host="127.0.0.1", port=port, protocol="mbfb")
    link = PresetLink(setup, host="127.0.0.1", port=port)
    link.open()
    try:
        assert link.protocol == "plain" and math.isfinite(link.exchange(0.1).x_m)
        assert 76 not in dev.fc_counts
    finally:
        link.close()


def test_the_link_sees_the_watchdog_act_and_the_estop_input(served, tmp_path) -> None:
    clock = _Clock()  # the emulator's watchdog runs on it
    dev, state, port = served(clock, estop={"dio": 4, "active": "low"})
    link, _ = _link(port, tmp_path, safety={"estop": {"input": "FIO4", "active": "low"}})
    link.open()
    try:
        assert not link.exchange(0.3).status & (Status.ESTOP | Status.WATCHDOG_TRIPPED)
        state.estop_input = True
        assert link.exchange(0.3).status & Status.ESTOP
        state.estop_input = False
        assert not link.exchange(0.3).status & Status.ESTOP
        clock.ns += 1_300_000_000  # 1.3 s without a request: the strict watchdog (1 s) puts DAC0 at 0 V
        deadline = time.monotonic() + 10.0  # until the serving thread has run the timer
        while not dev.watchdog_trips and time.monotonic() < deadline:
            time.sleep(0.01)
        assert dev.watchdog_trips == [clock.ns]
        assert link.exchange(0.3).status & Status.WATCHDOG_TRIPPED
        assert not link.exchange(0.3).status & Status.WATCHDOG_TRIPPED
    finally:
        link.close()


def test_a_reply_lost_at_a_current_change_is_neither_a_watchdog_trip_nor_a_driver_fault(served, tmp_path) -> None:
    """A tick whose reply came too late had its DAC write applied: the next sample reads it back.
    That is no mismatch (before, a step up read as another writer, DRIVER_FAULT, and a step down
    to 0 A as the watchdog's trip, which latches a run); a write by another client still is."""
    from mrctl.io.base import LinkTimeout

    dev, _state, port = served()
    link, _ = _link(port, tmp_path)
    link.open()
    bad = Status.WATCHDOG_TRIPPED | Status.DRIVER_FAULT
    try:
        for _ in range(3):
            assert not link.exchange(0.0).status & bad
        for I in (0.5, 0.0):  # a step up, then back to 0 A (the watchdog's own volts)
            link.timeout_s = 1e-5  # the request goes out, its reply (1.2 ms later) is not waited for
            with pytest.raises(LinkTimeout):
                link.exchange(I)
            deadline = time.monotonic() + 10.0
            while dev.dac_V[0] != pytest.approx(I * 2.5) and time.monotonic() < deadline:
                time.sleep(0.005)
            assert dev.dac_V[0] == pytest.approx(I * 2.5)  # the write was applied
            link.timeout_s = 0.05
            assert not link.exchange(I).status & bad
        assert link.dac_mismatches == 0 and link.watchdog_trips == 0
        with socket.create_connection(("127.0.0.1", port)) as other:  # another writer: DAC0 = 1 V
            pdu = struct.pack(">BHHB", 16, 1000, 2, 4) + struct.pack(">f", 1.0)
            assert _ask(other, struct.pack(">HHHB", 7, 0, len(pdu) + 1, 1) + pdu)[7] == 16
        assert link.exchange(0.0).status & Status.DRIVER_FAULT and link.dac_mismatches == 1
    finally:
        link.close()


class _Wire:
    """A TcpIO stand-in: the requests written, the replies given one segment per recv, what drain drops."""

    def __init__(self, *segments: bytes, queued: int = 0) -> None:
        self.segments, self.queued, self.sent = list(segments), queued, []

    def write(self, data, deadline) -> None:
        self.sent.append(bytes(data))

    def recv(self, deadline, wake_ns=0) -> bytes:
        return self.segments.pop(0) if self.segments else b""

    def drain(self) -> int:
        n, self.queued = self.queued, 0
        return n

    def close(self) -> None:
        pass


def _reply(tid: int, pdu: bytes, pid: int = 0, unit: int = 1) -> bytes:
    return struct.pack(">HHHB", tid, pid, len(pdu) + 1, unit) + pdu


def test_the_preset_links_replies_are_checked_whole_on_either_path() -> None:
    """The PresetLink's wire: a reply alone in its segment (the quick path) and one among others
    (the MBAP framing ModbusTcpLink uses) are checked alike: a protocol id other than 0 flushes the
    stream and counts the bytes dropped; a late reply is skipped and counted; FC3's byte count
    and FC16's echo must match."""
    from mrctl.io.base import FrameError
    from mrctl.io.devices import resolve_device
    from mrctl.io.devices.link import PresetLink

    setup, errors = resolve_device("labjack_t7", {"x": {"ain": 0, "m_per_V": 0.0025},
                                                  "current": {"dac": 0, "V_per_A": 2.5}}, {})
    assert errors == []
    link = PresetLink(setup, host="127.0.0.1")
    f7 = struct.pack(">f", 7.0)
    link._io = _Wire(_reply(1, bytes((3, 4)) + f7))  # the quick path
    assert link.read_value(60000, "float32") == 7.0
    link._io = _Wire(_reply(1, bytes((3, 4)) + f7) + _reply(2, bytes((3, 4)) + f7))  # a late one first
    assert link.read_value(60000, "float32") == 7.0 and link.stale_replies == 1
    bad_pid = _reply(3, bytes((3, 4)) + f7, pid=1)
    for segments in ((bad_pid,), (bad_pid[:5], bad_pid[5:])):  # alone, or through the framing
        link._io = _Wire(*segments, queued=5)
        before = link.bytes_discarded
        with pytest.raises(FrameError, match="bad MBAP header; stream flushed"):
            link.read_value(60000, "float32")
        assert link.bytes_discarded - before == len(bad_pid) + 5 and not link._rx
        assert link.counters()["bytes_discarded"] == link.bytes_discarded
    for split in (None, 3):  # byte count 2 in a reply of the right length: alone, or through the framing
        bad_count = _reply(link._tid + 1, bytes((3, 2)) + f7[:2] + bytes(2))
        link._io = _Wire(*((bad_count,) if split is None else (bad_count[:split], bad_count[split:])))
        with pytest.raises(FrameError, match="byte count"):
            link.read_value(60000, "float32")
    echo = _reply(link._tid + 1, struct.pack(">BHH", 16, 1002, 2))  # FC16 echoing another address
    link._io = _Wire(echo)
    with pytest.raises(FrameError, match="echoed address"):
        link.write_value(1000, "float32", 1.0)
    link._io = None


@pytest.mark.parametrize("change, message", [
    ({"safety": {"estop": {"input": "DIO0", "active": "low"}}, "backend": {"enable_dio": 0}},
     "safety.estop.input: 'DIO0' is DIO0, the enable output (backend.enable_dio)"),
    ({"safety": {"estop": {"input": "MIO3", "active": "low"}}},
     "safety.estop.input: 'MIO3' not allowed: a labjack_t7 has DIO0-DIO22"),
    ({"backend": {"channels": {"x": {"ain": 1, "m_per_V": 0.0025, "negative_ain": 2},
                               "current": {"dac": 0, "V_per_A": 2.5}}}},
     "backend.channels.x.negative_ain: 2 not allowed"),
    ({"backend": {"ain_settling_us": 60000}}, "backend.ain_settling_us: 60000.0 not allowed (0 = automatic, up to 50000 µs)"),
])
def test_check_refuses_what_a_t7_cannot_do(tmp_path, capsys, change, message) -> None:
    data = yaml.safe_load(EXPERIMENT.read_text())
    for section, values in change.items():
        data[section].update(values)
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    assert mrctl_main(["check", str(p)]) == 2
    err = capsys.readouterr().err
    assert message in err, err


def test_check_prints_the_rate_the_datasheet_model_gives(tmp_path, capsys) -> None:
    assert mrctl_main(["check", str(EXPERIMENT)]) == 0
    out = capsys.readouterr().out
    assert "one MBFB request per tick" in out and "1.22 ms by the model per tick fits 500 Hz" in out, out
    data = yaml.safe_load(EXPERIMENT.read_text())
    data["backend"]["channels"]["F"]["ain"] = 7  # AIN0-AIN7 read as one block
    data["backend"]["ain_resolution_index"] = 8
    p = tmp_path / "exp8.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    assert mrctl_main(["check", str(p)]) == 0  # reduce_rate: a warning, the rate it will run at
    err = capsys.readouterr().err
    assert "9.90 ms by the model per tick does not fit 500 Hz" in err and "highest standard rate that fits is " \
        "50 Hz" in err and "a lower ain_resolution_index" in err, err


def test_device_disarm_turns_the_watchdog_off_and_takes_the_device_lock(served, tmp_path, monkeypatch, capsys) -> None:
    from mrctl.daemon import ownership

    monkeypatch.setenv("MRCTL_LOCK_DIR", str(tmp_path / "locks"))
    dev, _state, port = served()
    link, exp = _link(port, tmp_path)
    link.open()  # armed, as mrctl run leaves it
    link.close()
    assert dev.io.flash["enable"] == 1
    held = ownership.acquire(link.device_key(), "a running mrctl")
    try:
        assert mrctl_main(["device", "disarm", str(exp)]) == 3
        err = capsys.readouterr().err
        assert "modbus-tcp 127.0.0.1:" in err and str(os.getpid()) in err, err
        assert dev.io.flash["enable"] == 1
    finally:
        held.release()
    assert mrctl_main(["device", "disarm", str(exp)]) == 0
    assert "watchdog disarmed" in capsys.readouterr().out
    assert dev.io.flash["enable"] == 0
    writes = dev.io.flash_writes
    assert mrctl_main(["device", "disarm", str(exp)]) == 0  # already off: nothing written
    assert "was not armed" in capsys.readouterr().out and dev.io.flash_writes == writes
