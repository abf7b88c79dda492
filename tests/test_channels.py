"""Extra channels on the serial wire (docs/protocol.md §2.5) and over hil_sim's quarter car."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

from mrctl.io.base import FrameError
from mrctl.io.protocol import (
    ChannelListFrame,
    ChannelQueryFrame,
    FrameDecoder,
    FrameType,
    SampleFrame,
    SetpointFlag,
    decode_frame,
    encode,
    encode_channel_list,
    encode_channel_query,
    encode_frame,
    encode_sample,
)

ROOT = Path(__file__).resolve().parents[1]


def test_sample_x_round_trip_and_layout():
    ch = (0.25, -1.5, 3.0)
    raw = encode_sample(7, 8, 9, 0.01, 0.1, 20.0, 0.3, 0x08, ch)
    assert len(raw) == 37 + 4 * 3 and raw[3] == FrameType.SAMPLE_X and raw[4] == 26 + 12
    assert raw[35:47] == struct.pack("<3f", *ch)  # the channels follow the SAMPLE payload
    f = decode_frame(raw)
    assert isinstance(f, SampleFrame) and f.channels == ch and f.echo_seq == 8 and f.status == 0x08
    assert encode(f) == raw
    plain = encode_sample(7, 8, 9, 0.01, 0.1, 20.0, 0.3, 0x08)
    assert len(plain) == 37 and decode_frame(plain).channels == ()  # a SAMPLE is unchanged
    with pytest.raises(ValueError):
        encode_sample(1, 1, 1, 0, 0, 0, 0, 0, tuple(range(10)))


def test_channel_query_and_list_round_trip():
    q = encode_channel_query(41)
    assert len(q) == 11 and decode_frame(q) == ChannelQueryFrame(41)
    names = ("v_sprung", "a_sprung", "tyre_defl")
    raw = encode_channel_list(5, 41, names)
    f = decode_frame(raw)
    assert f == ChannelListFrame(5, 41, names) and encode(f) == raw
    assert raw[13:] [:-2] == b"v_sprung,a_sprung,tyre_defl"


def test_bad_sample_x_lengths_are_frame_errors():
    with pytest.raises(FrameError):
        decode_frame(encode_frame(FrameType.SAMPLE_X, 1, b"\x00" * 27))  # not 26 + 4n
    with pytest.raises(FrameError):
        decode_frame(encode_frame(FrameType.CHANNEL_QUERY, 1, b"\x00"))


def test_decoder_finds_sample_x_among_noise_and_splits():
    frames = encode_sample(1, 2, 3, 0.0, 0.0, 1.0, 0.0, 0, (1.0, 2.0)) + b"\x00\xa5\x5a" + \
        encode_channel_list(2, 3, ("x",)) + encode_sample(3, 4, 5, 0.0, 0.0, 1.0, 0.0, 0)
    dec = FrameDecoder()
    out = []
    for i in range(0, len(frames), 7):
        out += dec.feed(frames[i:i + 7])
    assert [type(f).__name__ for f in out] == ["SampleFrame", "ChannelListFrame", "SampleFrame"]
    assert out[0].channels == (1.0, 2.0) and out[2].channels == ()


def test_serial_link_asks_for_channels_and_fills_them_in_place():
    """SerialLink against a scripted device on loop:// : CHANNEL_QUERY →
    CHANNEL_LIST, then every SETPOINT carries CHANNELS and each SAMPLE_X
    updates the same dict."""
    from mrctl.io.serial import SerialLink

    class Device:
        def __init__(self):
            self.dec = FrameDecoder()
            self.flags = []

        def answer(self, data: bytes) -> bytes:
            out = b""
            for f in self.dec.feed(data):
                if isinstance(f, ChannelQueryFrame):
                    out += encode_channel_list(0, f.seq, ("v_sprung", "tyre_defl"))
                elif hasattr(f, "flags"):
                    self.flags.append(f.flags)
                    ch = (0.1 * f.seq, -0.001) if f.flags & SetpointFlag.CHANNELS else ()
                    out += encode_sample(f.seq, f.seq, 1000 * f.seq, 0.0, 0.0, 1.0, f.current_A, 0, ch)
            return out

    dev = Device()

    class Port:
        def __init__(self):
            self.rx = bytearray()

        def write(self, data):
            self.rx += dev.answer(bytes(data))
            return len(data)

        def read(self, n):
            out, self.rx[:] = bytes(self.rx[:n]), self.rx[n:]
            return out

        def flush(self):
            pass

        def close(self):
            pass

    link = SerialLink("loop://", 921600, safe_on_close=False)
    link._port = Port()
    link.exchange(0.1)
    assert link.channels == {} and not dev.flags[-1] & SetpointFlag.CHANNELS
    assert link.request_channels() == ("v_sprung", "tyre_defl")
    ch = link.channels
    assert math.isnan(ch["v_sprung"])
    s = link.exchange(0.2)
    assert dev.flags[-1] & SetpointFlag.CHANNELS and s.current_A == pytest.approx(0.2)
    assert link.channels is ch and ch["v_sprung"] == pytest.approx(0.1 * link._seq) and ch["tyre_defl"] == pytest.approx(-0.001)


@pytest.mark.hil
def test_skyhook_over_serial_reads_the_quarter_cars_channels(tmp_path):
    """hil_sim's quarter car over the serial protocol: the on-off skyhook gets
    v_sprung in SAMPLE_X frames (with NaN it would never switch on)."""
    from hil_util import HilSim, bench_at_test_rate, experiment_at_test_rate, run_hil

    from mrctl.daemon.recorder import read_run, read_sidecar

    def start(d):
        return HilSim("--config", bench_at_test_rate(ROOT / "config" / "hil_quarter_car.yaml", d),
                      "--transport", "serial", "--link", str(d / "tty"), "--truth", str(d / "truth.csv"),
                      "--duration", "30")

    d, cfg, res, code = run_hil(tmp_path, start, lambda d, hil: experiment_at_test_rate(
        ROOT / "config" / "experiments" / "hil_quarter_car.yaml", d, **{"/tmp/mrctl-sim-tty": str(d / "tty")}),
        duration_s=3.0)
    assert code == 0
    run = read_run(d / "run.csv")
    on = np.mean(run["I"] > 0.5)
    assert 0.15 < on < 0.85, on  # switching on and off with the sign of v_sprung·v
    assert read_sidecar(d / "run.csv")["summary"]["exit_current_A"] == 0.0
    assert read_run(d / "truth.csv")["I_cmd"][-1] == 0.0


@pytest.mark.hil
def test_a_law_needing_channels_is_refused_by_a_device_without_them(tmp_path):
    from hil_util import HilSim, bench_at_test_rate, experiment_at_test_rate, run_daemon

    hil = HilSim("--config", bench_at_test_rate(ROOT / "config" / "hil_fig5_bench.yaml", tmp_path),
                 "--transport", "serial", "--link", str(tmp_path / "tty"), "--duration", "30")
    cfg = experiment_at_test_rate(ROOT / "config" / "experiments" / "hil_quarter_car.yaml", tmp_path,
                                  **{"/tmp/mrctl-sim-tty": str(tmp_path / "tty")})
    try:
        res = run_daemon(cfg, tmp_path / "run.csv", duration_s=2.0)
    finally:
        hil.stop()
    assert res.returncode == 2, res.stderr  # a refused start (exit 3) fails here too
    assert "inverse: the law 'skyhook_onoff' needs channel(s) v_sprung; serial" in res.stderr
    assert "provides none" in res.stderr
