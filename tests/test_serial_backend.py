"""SerialLink against a fake device on a pty pair (and pyserial's loop://).

The fake device runs in a thread on the pty master and answers each SETPOINT
through a per-test ``respond`` function. Timeouts are generous where a reply
is expected (the exchange returns as soon as it arrives, so this costs
nothing) and short only where no valid reply can ever come. No latency is
asserted: the box is shared and noisy.
"""

from __future__ import annotations

import math
import os
import select
import socket
import threading
import time
import tty
import types
from typing import Callable, Iterator

import pytest

import serial

from mrctl.io.base import DeviceError, Disconnected, FrameError, Link, LinkTimeout, Sample, Status  # noqa: E402
from mrctl.io.protocol import (  # noqa: E402
    ErrorCode,
    FrameDecoder,
    FrameType,
    ProtocolVersionError,
    SetpointFlag,
    SetpointFrame,
    encode_error,
    encode_frame,
    encode_sample,
)
from mrctl.io.serial import SerialLink, default_reply_timeout_s  # noqa: E402

REPLY_TIMEOUT_S = 2.0  # a reply is expected: generous, returns early
NO_REPLY_TIMEOUT_S = 0.15  # no valid reply can come: keep the test short

Respond = Callable[["FakeDevice", SetpointFrame], bytes | None]


def sample_for(dev: "FakeDevice", sp: SetpointFrame, echo: int | None = None) -> bytes:
    """A plausible SAMPLE answering ``sp``: applies the setpoint if ENABLEd."""
    dev.dev_seq += 1
    applied = sp.current_A if sp.flags & SetpointFlag.ENABLE else 0.0
    status = Status.NO_LOAD_CELL | (Status.OUTPUT_ENABLED if sp.flags & SetpointFlag.ENABLE else 0)
    return encode_sample(
        dev.dev_seq,
        sp.seq if echo is None else echo,
        dev.t_us,
        0.001 * dev.dev_seq,
        -0.25,
        math.nan,
        applied,
        status,
    )


class FakeDevice(threading.Thread):
    """Device side of the protocol on a pty master fd."""

    def __init__(self, master_fd: int, respond: Respond) -> None:
        super().__init__(daemon=True)
        self.fd = master_fd
        self.respond = respond
        self.received: list[SetpointFrame] = []
        self.dev_seq = 100
        self.t_us = 0xFFFF_FFFF - 20_500  # the 32-bit µs clock wraps ~20 ticks in
        self._stop_evt = threading.Event()
        self._close_lock = threading.Lock()
        self.closed = False

    def run(self) -> None:
        dec = FrameDecoder()
        while not self._stop_evt.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], 0.02)
                if not ready:
                    continue
                data = os.read(self.fd, 4096)
            except OSError:
                return
            if not data:
                return
            for f in dec.feed(data):
                if isinstance(f, SetpointFrame):
                    self.received.append(f)
                    self.t_us = (self.t_us + 1000) & 0xFFFFFFFF
                    reply = self.respond(self, f)
                    if reply:
                        try:
                            os.write(self.fd, reply)
                        except OSError:
                            return

    def stop(self) -> None:
        self._stop_evt.set()
        self.join(timeout=5)

    def close_master(self) -> None:
        """Simulate the device vanishing (USB unplug)."""
        self.stop()
        with self._close_lock:
            if not self.closed:
                os.close(self.fd)
                self.closed = True


@pytest.fixture
def pty_device() -> Iterator[Callable[..., tuple[SerialLink, FakeDevice]]]:
    made: list[tuple[SerialLink, FakeDevice]] = []

    def make(respond: Respond, timeout_s: float = REPLY_TIMEOUT_S) -> tuple[SerialLink, FakeDevice]:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo/line editing before pyserial configures it
        link = SerialLink(os.ttyname(slave), 921600, timeout_s=timeout_s)
        link.open()
        os.close(slave)  # pyserial holds its own fd
        dev = FakeDevice(master, respond)
        dev.start()
        made.append((link, dev))
        return link, dev

    yield make
    for link, dev in made:
        link.close()
        dev.close_master()


# --- normal operation ------------------------------------------------------------
def test_exchange_round_trip(pty_device) -> None:
    link, dev = pty_device(sample_for)
    assert isinstance(link, Link)
    s = link.exchange(0.75)
    assert isinstance(s, Sample)
    assert s.seq == 101
    assert s.x_m == pytest.approx(0.101)
    assert s.v_mps == -0.25
    assert math.isnan(s.F_N)
    assert s.current_A == 0.75
    assert s.status & Status.OUTPUT_ENABLED and s.status & Status.NO_LOAD_CELL
    sp = dev.received[-1]
    assert sp.current_A == 0.75 and sp.flags & SetpointFlag.ENABLE and sp.watchdog_ms == 50


def test_many_exchanges_seq_and_device_time_unwrap(pty_device) -> None:
    link, dev = pty_device(sample_for)
    samples = [link.exchange(0.01 * k) for k in range(50)]
    assert [s.seq for s in samples] == list(range(101, 151))
    # device time wraps at 2**32 µs during the run; t_dev_s stays monotonic
    dt = [b.t_dev_s - a.t_dev_s for a, b in zip(samples, samples[1:])]
    assert all(d == pytest.approx(1e-3) for d in dt)
    host_seqs = [f.seq for f in dev.received]
    assert host_seqs == sorted(host_seqs) and len(set(host_seqs)) == 50
    c = link.counters()
    assert c["exchanges"] == 50 and c["timeouts"] == 0 and c["stale_replies"] == 0
    assert c["crc_errors"] == 0 and c["bytes_discarded"] == 0


def test_disable_flag_and_safe_close(pty_device) -> None:
    link, dev = pty_device(sample_for)
    link.enabled = False
    s = link.exchange(1.0)
    assert s.current_A == 0.0 and not s.status & Status.OUTPUT_ENABLED
    link.enabled = True
    link.exchange(0.5)
    link.close()
    link.close()  # idempotent
    assert not link.is_open
    # close() sent a disabled 0 A setpoint
    for _ in range(250):
        if len(dev.received) >= 3:
            break
        time.sleep(0.02)
    last = dev.received[-1]
    assert last.current_A == 0.0 and not last.flags & SetpointFlag.ENABLE
    with pytest.raises(Disconnected):
        link.exchange(0.1)


def test_non_finite_setpoint_rejected(pty_device) -> None:
    link, _ = pty_device(sample_for)
    with pytest.raises(ValueError):
        link.exchange(math.nan)


# --- failures ------------------------------------------------------------------------
def test_no_reply_is_link_timeout(pty_device) -> None:
    link, dev = pty_device(lambda d, sp: None, timeout_s=NO_REPLY_TIMEOUT_S)
    with pytest.raises(LinkTimeout):
        link.exchange(0.2)
    assert link.timeouts == 1 and link.frame_errors == 0
    assert len(dev.received) == 1


def test_garbage_then_valid_reply_succeeds(pty_device) -> None:
    garbage = b"\x00\xff\x13\x11\x0d\x0a\x5a\xa5\xa5\x5a\x01\x81"  # XON/XOFF, CR/LF, false preamble
    link, _ = pty_device(lambda d, sp: garbage + sample_for(d, sp))
    s = link.exchange(0.3)
    assert s.current_A == pytest.approx(0.3)
    assert link.bytes_discarded == len(garbage)
    s2 = link.exchange(0.4)  # still in sync afterwards
    assert s2.current_A == pytest.approx(0.4)


def test_corrupt_crc_only_is_frame_error(pty_device) -> None:
    def corrupt(d: FakeDevice, sp: SetpointFrame) -> bytes:
        b = bytearray(sample_for(d, sp))
        b[20] ^= 0x40
        return bytes(b)

    link, _ = pty_device(corrupt, timeout_s=NO_REPLY_TIMEOUT_S)
    with pytest.raises(FrameError):
        link.exchange(0.2)
    assert link.crc_errors == 1 and link.frame_errors == 1 and link.timeouts == 0


def test_stale_reply_is_discarded(pty_device) -> None:
    def stale_then_good(d: FakeDevice, sp: SetpointFrame) -> bytes:
        return sample_for(d, sp, echo=(sp.seq - 1) & 0xFFFFFFFF) + sample_for(d, sp)

    link, _ = pty_device(stale_then_good)
    s = link.exchange(0.6)
    assert s.current_A == pytest.approx(0.6)
    assert link.stale_replies == 1


def test_only_stale_reply_times_out(pty_device) -> None:
    link, _ = pty_device(lambda d, sp: sample_for(d, sp, echo=sp.seq + 7), timeout_s=NO_REPLY_TIMEOUT_S)
    with pytest.raises(LinkTimeout):
        link.exchange(0.6)
    assert link.stale_replies == 1


def test_late_reply_is_stale_on_next_tick(pty_device) -> None:
    """A reply that misses its tick must not be returned for the next one."""
    gate = threading.Event()

    def slow_first(d: FakeDevice, sp: SetpointFrame) -> bytes:
        if len(d.received) == 1:
            gate.wait(5)  # hold the first reply until the host timed out
        return sample_for(d, sp)

    link, _ = pty_device(slow_first, timeout_s=NO_REPLY_TIMEOUT_S)
    with pytest.raises(LinkTimeout):
        link.exchange(0.1)
    gate.set()
    link.timeout_s = REPLY_TIMEOUT_S
    s = link.exchange(0.9)
    assert s.current_A == pytest.approx(0.9)
    assert link.stale_replies == 1


def test_device_nak_is_device_error(pty_device) -> None:
    link, _ = pty_device(lambda d, sp: encode_error(1, sp.seq, ErrorCode.UNKNOWN_TYPE))
    with pytest.raises(DeviceError) as ei:
        link.exchange(0.2)
    assert ei.value.code == ErrorCode.UNKNOWN_TYPE
    assert link.device_errors == 1


def test_bad_crc_nak_names_previous_request(pty_device) -> None:
    link, _ = pty_device(lambda d, sp: encode_error(1, (sp.seq - 1) & 0xFFFFFFFF, ErrorCode.BAD_CRC))
    with pytest.raises(DeviceError) as ei:
        link.exchange(0.2)
    assert ei.value.code == ErrorCode.BAD_CRC


def test_stale_nak_is_discarded(pty_device) -> None:
    def stale_nak_then_good(d: FakeDevice, sp: SetpointFrame) -> bytes:
        return encode_error(1, (sp.seq - 1) & 0xFFFFFFFF, ErrorCode.UNKNOWN_TYPE) + sample_for(d, sp)

    link, _ = pty_device(stale_nak_then_good)
    assert link.exchange(0.2).current_A == pytest.approx(0.2)
    assert link.stale_replies == 1 and link.device_errors == 0


def test_version_mismatch_reported_with_both_versions(pty_device) -> None:
    link, _ = pty_device(lambda d, sp: encode_error(1, sp.seq, ErrorCode.BAD_VERSION, 3))
    with pytest.raises(ProtocolVersionError, match="v1.*v3"):
        link.exchange(0.2)
    # a device that answers in its own (future) version
    link2, _ = pty_device(lambda d, sp: encode_frame(FrameType.SAMPLE, 1, bytes(40), version=2))
    with pytest.raises(ProtocolVersionError) as ei:
        link2.exchange(0.2)
    assert (ei.value.expected, ei.value.received) == (1, 2)


def test_port_vanishing_is_disconnected(pty_device) -> None:
    link, dev = pty_device(sample_for)
    link.exchange(0.1)
    dev.close_master()
    with pytest.raises(Disconnected):
        link.exchange(0.1)
    assert not link.is_open and link.disconnects == 1
    with pytest.raises(Disconnected):  # stays disconnected until reopened
        link.exchange(0.1)
    link.close()  # still fine


def test_device_vanishing_mid_exchange_is_disconnected(pty_device) -> None:
    def unplug(d: FakeDevice, sp: SetpointFrame) -> None:
        threading.Thread(target=d.close_master).start()  # can't join ourselves

    link, _ = pty_device(unplug)
    with pytest.raises(Disconnected):
        link.exchange(0.1)


def test_open_missing_port_is_disconnected() -> None:
    link = SerialLink("/dev/does-not-exist-mrctl", timeout_s=0.1)
    with pytest.raises(Disconnected):
        link.open()
    link.close()


# --- other pyserial URLs ---------------------------------------------------------------
def test_loop_url_sees_only_its_own_setpoint() -> None:
    """loop:// echoes the request back: counted as an echo, never taken as a reply."""
    link = SerialLink("loop://", timeout_s=NO_REPLY_TIMEOUT_S)
    with link:
        with pytest.raises(LinkTimeout):
            link.exchange(0.5)
        assert link.echoes == 1 and link.stale_replies == 0
    assert not link.is_open


def test_socket_url_against_tcp_fake_device() -> None:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]

    def serve() -> None:
        conn, _ = srv.accept()
        dec = FrameDecoder()
        dev = types.SimpleNamespace(dev_seq=0, t_us=0)  # what sample_for uses
        with conn:
            while True:
                data = conn.recv(4096)
                if not data:
                    return
                for f in dec.feed(data):
                    if isinstance(f, SetpointFrame) and f.flags & SetpointFlag.ENABLE:
                        conn.sendall(sample_for(dev, f))

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        with SerialLink(f"socket://127.0.0.1:{port}", timeout_s=REPLY_TIMEOUT_S) as link:
            assert [link.exchange(0.1 * k).current_A for k in range(1, 4)] == pytest.approx([0.1, 0.2, 0.3])
    finally:
        t.join(timeout=5)
        srv.close()


def test_default_timeout_and_describe() -> None:
    assert default_reply_timeout_s(921600) == pytest.approx(585.9375e-6 + 250e-6)
    assert default_reply_timeout_s(10_000_000) == pytest.approx(0.5e-3)
    link = SerialLink("loop://", 2_000_000)
    d = link.describe()
    assert "loop://" in d and "2000000" in d and "54 B" in d
    assert link.poll_s <= link.timeout_s
