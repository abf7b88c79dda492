"""Modbus backend: register map, framing, fuzzing, TCP/RTU loopback, mbpoll.

Reference implementation for byte-level checks: pymodbus (its PDU classes,
framers, CRC and register converters). Loopback tests run the real
hil_sim device loops in threads (TCP on 127.0.0.1 with an ephemeral port,
RTU on a pty pair). Generous deadlines where a reply is expected (the
exchange returns as soon as it arrives), short ones only where none can
come; no latency is asserted.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import socket
import struct
import subprocess
import threading
import time
import tty
from typing import Any, Callable, Iterator

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import pymodbus  # noqa: F401 - a test dependency: missing, the test fails
import serial  # noqa: E402,F401 - a test dependency: missing, these tests fail

from pymodbus.client.mixin import ModbusClientMixin  # noqa: E402
from pymodbus.framer import FramerRTU, FramerSocket  # noqa: E402
from pymodbus.pdu import DecodePDU  # noqa: E402
from pymodbus.pdu.register_message import (  # noqa: E402
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    ReadWriteMultipleRegistersResponse,
    WriteMultipleRegistersRequest,
)

from hil_sim.modbus_device import (  # noqa: E402
    Deferred,
    ModbusDevice,
    default_register_map as device_default_map,
)
from hil_sim.modbus_rtu import ModbusRtuInline, rtu_feed, rtu_silence_s, serve_modbus_rtu  # noqa: E402
from hil_sim.modbus_tcp import serve_modbus_tcp, serve_modbus_tcp_inline  # noqa: E402
from hil_sim.modbus_wire import (  # noqa: E402
    ILLEGAL_DATA_ADDRESS,
    ILLEGAL_DATA_VALUE,
    ILLEGAL_FUNCTION,
    mbap_frame_length,
    rtu_request_length,
)
from hil_sim.state import DeviceState  # noqa: E402
from hil_sim.testing.peers import free_port  # noqa: E402
from mrctl.io.base import (  # noqa: E402
    DeviceError,
    Disconnected,
    FrameError,
    Link,
    LinkError,
    LinkTimeout,
    Sample,
    Status,
)
from mrctl.io.modbus import (  # noqa: E402
    EXCEPTION_NAMES,
    FC_READ_HOLDING,
    FC_READ_INPUT,
    FC_READ_WRITE,
    FC_WRITE_MULTIPLE,
    ModbusLink,
    crc16_modbus,
    decode_response_pdu,
    decode_rtu_response,
    decode_tcp_response,
    exception_name,
    mbap_frame,
    open_serial_port,
    read_request_pdu,
    read_write_request_pdu,
    rtu_frame,
    rtu_tick_frames,
    rtu_transaction_wire_time_s,
    write_request_pdu,
)
from mrctl.io.registers import (  # noqa: E402
    DATA_TYPES,
    DEFAULT_REGISTER_MAP,
    RegisterMap,
    default_register_map,
    validate_register_map,
)

DT = ModbusClientMixin.DATATYPE
REPLY_S = 2.0  # a reply is expected: generous, returns early
NO_REPLY_S = 0.1  # none can come: keep the test short
FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

SAMPLE = Sample(seq=70000, t_dev_s=12.5, x_m=0.0125, v_mps=-0.25, F_N=321.5, status=int(Status.OUTPUT_ENABLED), current_A=0.75)


def f32(x: float) -> float:
    return struct.unpack(">f", struct.pack(">f", x))[0]


# =============================================================================
# register map
def test_default_map_layout_and_plan() -> None:
    m = default_register_map()
    assert m == device_default_map()
    assert m.unit_id == 1
    assert [tuple(b) for b in m.read_blocks] == [("holding", 0, 13)]
    assert tuple(m.write_block) == ("holding", 16, 4)
    assert m.fc23_capable
    assert m.spans() == {"holding": (0, 20)}
    assert RegisterMap.from_mapping(m.to_mapping()) == m
    assert RegisterMap.from_mapping(None) == m
    assert RegisterMap.from_mapping({}) == m
    assert RegisterMap.from_mapping(DEFAULT_REGISTER_MAP) == m


def test_default_map_matches_docs_table() -> None:
    """docs/registers.md documents the default map: the table must agree with the code."""
    path = os.path.join(os.path.dirname(__file__), "..", "docs", "registers.md")
    text = open(path, encoding="utf-8").read()
    rows = re.findall(r"^\|\s*`(\w+)`\s*\|\s*(\d+)\s*\|\s*(\w+)\s*\|\s*(\w+)\s*\|", text, re.M)
    documented = {name: (int(addr), table, dtype) for name, addr, table, dtype in rows}
    actual = {n: (s.address, s.table, s.type) for n, s in default_register_map().specs.items()}
    assert documented == actual


def test_docs_yaml_example_is_valid() -> None:
    import yaml
    path = os.path.join(os.path.dirname(__file__), "..", "docs", "registers.md")
    block = open(path, encoding="utf-8").read().split("```yaml\n", 1)[1].split("```", 1)[0]
    m = RegisterMap.from_mapping(yaml.safe_load(block)["register_map"])
    assert m.unit_id == 17 and not m.fc23_capable
    assert [tuple(b) for b in m.read_blocks] == [("input", 0, 10)]
    assert tuple(m.write_block) == ("holding", 100, 2)
    assert m.specs["F_N"].word_order == "big" and m.specs["x_m"].word_order == "little"


@pytest.mark.parametrize("dtype", list(DATA_TYPES))
@pytest.mark.parametrize("word_order", ["big", "little"])
@pytest.mark.parametrize("scale,offset", [(1.0, 0.0), (1e-3, 0.0), (2.5e-4, -1.0)])
def test_round_trip_every_type_word_order_scale(dtype: str, word_order: str, scale: float, offset: float) -> None:
    regs = dict(DEFAULT_REGISTER_MAP["registers"])
    regs["x_m"] = {"address": 4, "type": dtype, "word_order": word_order, "scale": scale, "offset": offset}
    n = DATA_TYPES[dtype][0]
    regs["current_setpoint_A"] = {"address": 16, "type": dtype, "word_order": word_order, "scale": scale, "offset": offset}
    regs["enable"] = {"address": 16 + n, "type": "uint16"}
    regs["watchdog_ms"] = {"address": 17 + n, "type": "uint16"}
    m = RegisterMap.from_mapping({"registers": regs})
    lo, hi = m.specs["x_m"].raw_range or (-1e6, 1e6)
    for raw in sorted({lo, hi, 0, 1, (lo + hi) // 2, hi // 3}):
        phys = raw * scale + offset
        (blk,) = m.encode_read(SAMPLE._replace(x_m=phys))
        assert m.decode_read(blk).x_m == pytest.approx(phys, rel=1e-6, abs=1e-9)
        # write side, host → device
        w = m.encode_write(phys, True, 50)
        assert m.decode_write(w).current_setpoint_A == pytest.approx(phys, rel=1e-6, abs=1e-9)
    # the register words agree with pymodbus's converter for the same raw value
    raw = hi // 3 if DATA_TYPES[dtype][2] else 1.5
    (blk,) = m.encode_read(SAMPLE._replace(x_m=raw * scale + offset))
    words = list(struct.unpack(">13H", blk))[4 : 4 + DATA_TYPES[dtype][0]]
    assert words == ModbusClientMixin.convert_to_registers(raw, getattr(DT, dtype.upper()), word_order=word_order)


@given(
    dtype=st.sampled_from(list(DATA_TYPES)),
    word_order=st.sampled_from(["big", "little"]),
    data=st.data(),
)
@settings(max_examples=200, deadline=None)
def test_round_trip_raw_values_hypothesis(dtype: str, word_order: str, data: st.DataObject) -> None:
    m = RegisterMap.from_mapping(
        {"word_order": word_order, "registers": {
            "x_m": {"address": 10, "type": dtype}, "v_mps": {"address": 0, "type": "float32"},
            "current_setpoint_A": {"address": 20, "type": dtype}}}
    )
    rr = m.specs["x_m"].raw_range
    if rr is None:
        v = data.draw(st.floats(width=32, allow_nan=False, allow_infinity=False))
    else:
        v = data.draw(st.integers(*rr))
    (blk,) = m.encode_read((0, 0, v, 0.0, 0.0, 0, 0.0))
    assert m.decode_read(blk).x_m == v
    assert m.decode_write(m.encode_write(v)).current_setpoint_A == v


def test_known_bytes_big_and_little_word_order() -> None:
    big = RegisterMap.from_mapping({"registers": {
        "x_m": {"address": 0, "type": "float32"}, "v_mps": {"address": 2, "type": "int32"},
        "current_setpoint_A": {"address": 4, "type": "float32"}}})
    little = RegisterMap.from_mapping({"word_order": "little", "registers": big.to_mapping()["registers"] | {
        "x_m": {"address": 0, "type": "float32", "word_order": "little"},
        "v_mps": {"address": 2, "type": "int32", "word_order": "little"}}})
    assert big.encode_read((0, 0, 1.0, -2, 0, 0, 0))[0] == bytes.fromhex("3f800000 fffffffe")
    assert little.encode_read((0, 0, 1.0, -2, 0, 0, 0))[0] == bytes.fromhex("00003f80 fffeffff")
    assert big.encode_write(1.0) == bytes.fromhex("3f800000")


def test_counters_wrap_and_status_and_nan_on_device_side() -> None:
    m = RegisterMap.from_mapping({"registers": {
        "seq": {"address": 0, "type": "uint16"}, "t_dev": {"address": 1, "type": "uint32", "scale": 1e-6},
        "x_m": {"address": 3, "type": "int16", "scale": 1e-4}, "v_mps": {"address": 4, "type": "float32"},
        "F_N": {"address": 6, "type": "int16"}, "status": {"address": 7, "type": "int16"},
        "current_setpoint_A": {"address": 10, "type": "float32"}}})
    (blk,) = m.encode_read(Sample(70000, 5000.0, 10.0, 1e39, math.nan, 0x8008, 0.0))
    v = m.decode_read(blk)
    assert v.seq == 70000 % 65536  # counters wrap
    assert v.t_dev == round(5000.0 / 1e-6) % 2**32
    assert v.x_m == pytest.approx(32767 * 1e-4)  # measured values saturate
    assert v.v_mps == math.inf  # float32 overflow → inf
    assert v.F_N == 0.0  # NaN in an integer register → 0 (status says NO_LOAD_CELL)
    assert v.status == 0x8008  # status bits survive a signed type


def test_write_encode_rejects_non_finite_and_out_of_range() -> None:
    m = default_register_map()
    for bad in (math.nan, math.inf, -math.inf, 1e39):
        with pytest.raises(ValueError, match="current_setpoint_A"):
            m.encode_write(bad)
    m16 = RegisterMap.from_mapping({"registers": dict(DEFAULT_REGISTER_MAP["registers"]) | {
        "current_setpoint_A": {"address": 16, "type": "int16", "scale": 1e-3}, "enable": {"address": 17}, "watchdog_ms": {"address": 18}}})
    assert m16.decode_write(m16.encode_write(-1.234)).current_setpoint_A == pytest.approx(-1.234)
    with pytest.raises(ValueError, match="does not fit int16"):
        m16.encode_write(40.0)
    with pytest.raises(ValueError, match="watchdog_ms"):
        m16.encode_write(1.0, True, 70000)


def test_input_registers_mean_separate_reads() -> None:
    regs = dict(DEFAULT_REGISTER_MAP["registers"])
    regs["x_m"] = {"table": "input", "address": 100, "type": "float32"}
    regs["v_mps"] = {"table": "input", "address": 104, "type": "float32"}  # gap 102..103 read too
    m = RegisterMap.from_mapping({"registers": regs})
    assert not m.fc23_capable
    assert [tuple(b) for b in m.read_blocks] == [("holding", 0, 13), ("input", 100, 6)]
    assert rtu_tick_frames(m, False) == [(9 + 8, 8), (8, 5 + 26), (8, 5 + 12)]
    with pytest.raises(ValueError):
        rtu_tick_frames(m, True)
    with pytest.raises(ValueError, match="use_fc23=True"):
        ModbusLink("tcp", host="h", register_map=m, use_fc23=True)
    blocks = m.encode_read(SAMPLE)
    v = m.decode_read(*blocks)
    assert (v.x_m, v.v_mps, v.seq) == (f32(SAMPLE.x_m), f32(SAMPLE.v_mps), SAMPLE.seq)
    # the device serves such a map too: FC23 is refused (reads aren't one holding block)
    state = DeviceState()
    state.publish(SAMPLE)
    for transport in ("tcp", "rtu"):
        link = attach(transport, _device_respond(transport, state, register_map=m), fc23=False, register_map=m)
        s = link.exchange(0.7)
        assert (s.x_m, s.v_mps, s.seq) == (f32(SAMPLE.x_m), f32(SAMPLE.v_mps), SAMPLE.seq)
        assert state.setpoint()[:2] == (f32(0.7), True)
        assert [tx.fc for tx in link._txs] == [FC_WRITE_MULTIPLE, FC_READ_HOLDING, FC_READ_INPUT]  # noqa: SLF001


def _with(**regs: Any) -> dict[str, Any]:
    return {"registers": dict(DEFAULT_REGISTER_MAP["registers"]) | regs}


@pytest.mark.parametrize(
    "data,prefix",
    [
        (_with(x_m={"address": 4, "type": "float64"}),
         "registers.x_m.type: 'float64' not allowed (allowed: int16, uint16, int32, uint32, float32)"),
        (_with(x_m={"address": 4, "table": "coil"}), "registers.x_m.table: 'coil' not allowed"),
        (_with(current_setpoint_A={"address": 16, "table": "input"}), "registers.current_setpoint_A.table:"),
        (_with(x_m={"address": -1}), "registers.x_m.address: -1 not allowed"),
        (_with(x_m={"address": 65535, "type": "float32"}), "registers.x_m.address: 65535 + 2 registers"),
        (_with(x_m={"type": "float32"}), "registers.x_m.address: required"),
        (_with(x_m={"address": 4, "scale": 0}), "registers.x_m.scale: 0 not allowed"),
        (_with(x_m={"address": 4, "offset": math.nan}), "registers.x_m.offset: nan not allowed"),
        (_with(x_m={"address": 4, "word_order": "middle"}), "registers.x_m.word_order: 'middle' not allowed"),
        (_with(x_m={"address": 4, "units": "m"}), "registers.x_m.units: unknown key"),
        (_with(seq={"address": 0, "type": "float32"}), "registers.seq.type: 'float32' not allowed for seq"),
        (_with(status={"address": 12, "scale": 2}), "registers.status.scale: 2 not allowed for status"),
        (_with(x_m={"address": 5}), "registers.v_mps.address: registers 6..7 overlap registers.x_m (5..6, holding)"),
        (_with(enable={"address": 19}, watchdog_ms={"address": 20}), "registers.enable.address: written registers must be contiguous"),
        (_with(F_N={"address": 200}), "registers: holding read quantities span 202 registers"),
        (_with(force={"address": 30}), "registers.force: unknown quantity"),
        (_with(x_m=None), "registers.x_m: must be a mapping"),
        ({"registers": {"x_m": {"address": 0}, "v_mps": {"address": 2}}}, "registers.current_setpoint_A: required"),
        ({"unit_id": 300}, "unit_id: 300 not allowed"),
        ({"unit_id": True}, "unit_id: True not allowed"),
        ({"word_order": "big-endian"}, "word_order: 'big-endian' not allowed"),
        ({"registres": {}}, "registres: unknown key"),
        ({"registers": [1, 2]}, "registers: must be a mapping"),
    ],
)
def test_config_errors_name_their_key(data: dict[str, Any], prefix: str) -> None:
    with pytest.raises(ValueError) as ei:
        RegisterMap.from_mapping(data)
    assert str(ei.value).startswith(prefix), str(ei.value)
    rmap, errors = validate_register_map(data, "backend.register_map")
    assert rmap is None and errors[0].startswith("backend.register_map." + prefix.split(":")[0].lstrip("."))


# =============================================================================
# wire time
def test_rtu_wire_time() -> None:
    m = default_register_map()
    assert rtu_tick_frames(m, True) == [(21, 31)]
    assert rtu_tick_frames(m, False) == [(17, 8), (8, 31)]
    t = rtu_transaction_wire_time_s(m, 115200, True)
    assert t == pytest.approx((52 + 7) * 11 / 115200)  # 5.63 ms: 1 kHz impossible
    assert t > 1e-3
    assert rtu_transaction_wire_time_s(m, 921600, True) == pytest.approx(59 * 11 / 921600)  # 0.70 ms
    assert rtu_transaction_wire_time_s(m, 921600, True, bits_per_char=10) < rtu_transaction_wire_time_s(m, 921600, True)
    assert rtu_transaction_wire_time_s(m, 921600, False) > rtu_transaction_wire_time_s(m, 921600, True)
    assert rtu_transaction_wire_time_s(m, 921600, True, fixed_t35_above_19200=True) > 2 * 1.75e-3
    with pytest.raises(ValueError):
        rtu_transaction_wire_time_s(m, 0, True)


# =============================================================================
# framing against pymodbus
def test_crc_matches_pymodbus() -> None:
    for data in (b"", b"\x01\x03\x00\x00\x00\x0a", bytes(range(256))):
        c = crc16_modbus(data)
        assert FramerRTU.compute_CRC(data) == ((c & 0xFF) << 8 | c >> 8)
    assert crc16_modbus(b"123456789") == 0x4B37  # CRC-16/MODBUS check value
    assert crc16_modbus(b"56789", crc16_modbus(b"1234")) == 0x4B37


def test_exception_names_match_pymodbus() -> None:
    """Our table names every code as pymodbus's ExcCodes does (messages unchanged without it)."""
    from pymodbus.constants import ExcCodes

    assert EXCEPTION_NAMES == {int(c): c.name for c in ExcCodes}
    assert all(exception_name(int(c)) == c.name for c in ExcCodes)


def test_requests_match_pymodbus_framers() -> None:
    data = default_register_map().encode_write(1.5, True, 50)
    words = list(struct.unpack(">4H", data))
    cases = [
        (read_write_request_pdu(0, 13, 16, data),
         ReadWriteMultipleRegistersRequest(read_address=0, read_count=13, write_address=16, write_registers=words, dev_id=7, transaction_id=0x1234)),
        (write_request_pdu(16, data), WriteMultipleRegistersRequest(address=16, registers=words, dev_id=7, transaction_id=0x1234)),
        (read_request_pdu(FC_READ_HOLDING, 0, 13), ReadHoldingRegistersRequest(address=0, count=13, dev_id=7, transaction_id=0x1234)),
    ]
    for pdu, ref in cases:
        assert mbap_frame(0x1234, 7, pdu) == FramerSocket(DecodePDU(False)).buildFrame(ref)
        assert rtu_frame(7, pdu) == FramerRTU(DecodePDU(False)).buildFrame(ref)
        # and the device side understands what pymodbus's server decoder does
        n, req = FramerSocket(DecodePDU(True)).handleFrame(mbap_frame(0x1234, 7, pdu), 0, 0)
        assert req is not None and req.function_code == pdu[0]


def test_responses_built_by_pymodbus_decode() -> None:
    regs = list(range(100, 113))
    for cls, fc in ((ReadWriteMultipleRegistersResponse, FC_READ_WRITE), (ReadHoldingRegistersResponse, FC_READ_HOLDING)):
        r = cls(registers=regs, dev_id=1, transaction_id=9)
        data = decode_tcp_response(FramerSocket(DecodePDU(False)).buildFrame(r), 9, 1, fc, 13)
        assert list(struct.unpack(">13H", data)) == regs
        data = decode_rtu_response(FramerRTU(DecodePDU(False)).buildFrame(r), 1, fc, 13)
        assert list(struct.unpack(">13H", data)) == regs


def test_response_decoder_errors() -> None:
    ok = bytes((FC_READ_WRITE, 4, 0, 1, 0, 2))
    assert decode_response_pdu(ok, FC_READ_WRITE, 2) == b"\x00\x01\x00\x02"
    with pytest.raises(DeviceError, match="ILLEGAL_FUNCTION") as ei:
        decode_response_pdu(bytes((FC_READ_WRITE | 0x80, 1)), FC_READ_WRITE, 2)
    assert ei.value.code == 1
    assert exception_name(2) == "ILLEGAL_ADDRESS" and exception_name(0x42) == "0x42"
    for bad in (b"", ok[:1], ok[:-1], bytes((FC_READ_HOLDING,)) + ok[1:], bytes((FC_READ_WRITE | 0x80, 1, 0))):
        with pytest.raises(FrameError):
            decode_response_pdu(bad, FC_READ_WRITE, 2)
    frame = rtu_frame(1, ok)
    with pytest.raises(FrameError, match="CRC"):
        decode_rtu_response(frame[:-1] + bytes((frame[-1] ^ 1,)), 1, FC_READ_WRITE, 2)
    with pytest.raises(FrameError, match="unit"):
        decode_rtu_response(rtu_frame(2, ok), 1, FC_READ_WRITE, 2)
    tcp = mbap_frame(5, 1, ok)
    for bad_frame, what in ((mbap_frame(6, 1, ok), "transaction"), (mbap_frame(5, 3, ok), "unit"),
                            (tcp[:2] + b"\x00\x01" + tcp[4:], "protocol"), (tcp + b"\x00", "length")):
        with pytest.raises(FrameError, match=what):
            decode_tcp_response(bad_frame, 5, 1, FC_READ_WRITE, 2)


# =============================================================================
# fuzzing: decoders only ever return a valid result or raise the typed errors
TYPED = (FrameError, DeviceError)
fcs = st.sampled_from([FC_READ_HOLDING, FC_READ_INPUT, FC_WRITE_MULTIPLE, FC_READ_WRITE])


@FUZZ
@given(frame=st.binary(max_size=300), fc=fcs, n=st.integers(1, 125), tid=st.integers(0, 0xFFFF))
def test_fuzz_tcp_response_decoder(frame: bytes, fc: int, n: int, tid: int) -> None:
    try:
        data = decode_tcp_response(frame, tid, 1, fc, n)
    except TYPED:
        return
    assert len(data) == (0 if fc == FC_WRITE_MULTIPLE else 2 * n)


@FUZZ
@given(body=st.binary(max_size=260), fc=fcs, n=st.integers(1, 125), good_crc=st.booleans())
def test_fuzz_rtu_response_decoder(body: bytes, fc: int, n: int, good_crc: bool) -> None:
    frame = body + crc16_modbus(body).to_bytes(2, "little") if good_crc else body
    try:
        data = decode_rtu_response(frame, 1, fc, n)
    except TYPED:
        return
    assert len(data) == (0 if fc == FC_WRITE_MULTIPLE else 2 * n)


@FUZZ
@given(pdu=st.one_of(
    st.binary(max_size=260),
    st.tuples(st.sampled_from([3, 4, 16, 23, 0x83, 1, 0]), st.binary(max_size=40)).map(lambda t: bytes((t[0],)) + t[1]),
))
def test_fuzz_device_request_decoder(pdu: bytes) -> None:
    state = DeviceState()
    state.publish(SAMPLE)
    for rmap in (default_register_map(), INPUT_MAP):
        _fuzz_device_once(ModbusDevice(state, rmap), state, pdu)


INPUT_MAP = RegisterMap.from_mapping({"word_order": "little", "registers": dict(DEFAULT_REGISTER_MAP["registers"]) | {
    "x_m": {"table": "input", "address": 0, "type": "int16", "scale": 1e-4},
    "v_mps": {"table": "input", "address": 2, "type": "int32", "scale": 1e-6}}})


def _fuzz_device_once(dev: ModbusDevice, state: DeviceState, pdu: bytes) -> None:
    resp = dev.handle_pdu(pdu)
    if not pdu:
        assert resp is None
        return
    assert resp is not None and resp[0] & 0x7F == pdu[0] & 0x7F
    if resp[0] & 0x80:
        assert len(resp) == 2 and resp[1] in (ILLEGAL_FUNCTION, ILLEGAL_DATA_ADDRESS, ILLEGAL_DATA_VALUE)
    elif resp[0] in (FC_READ_HOLDING, FC_READ_INPUT, FC_READ_WRITE):
        assert len(resp) == 2 + resp[1]
    sp = state.setpoint()
    assert math.isfinite(sp[0])  # never applies a non-finite setpoint
    # framed forms never raise either
    for n in range(len(pdu) + 8):
        try:
            mbap_frame_length(mbap_frame(1, 1, pdu)[:n])
        except FrameError:
            pass
    dev.handle_tcp_frame(mbap_frame(1, 1, pdu))
    dev.handle_tcp_frame(pdu)
    dev.handle_rtu_frame(rtu_frame(1, pdu))
    dev.handle_rtu_frame(pdu)
    rtu_request_length(pdu)


@FUZZ
@given(chunks=st.lists(st.one_of(
    st.binary(max_size=30),
    st.sampled_from([3, 16, 23]).map(lambda fc: rtu_frame(1, read_write_request_pdu(0, 13, 16, bytes(8)) if fc == 23
                                                          else write_request_pdu(16, bytes(8)) if fc == 16
                                                          else read_request_pdu(3, 0, 13))),
), max_size=8))
def test_fuzz_device_rtu_stream(chunks: list[bytes]) -> None:
    """The device's RTU stream parser: arbitrary chunks never raise; replies are valid frames."""
    state = DeviceState()
    state.publish(SAMPLE)
    dev = ModbusDevice(state, default_register_map())
    buf = bytearray()
    for c in chunks:
        buf += c
        for resp in rtu_feed(dev, buf):
            assert resp[0] == 1 and crc16_modbus(resp[:-2]) == int.from_bytes(resp[-2:], "little")
    if buf:
        dev.handle_rtu_frame(bytes(buf))


def test_device_rtu_stream_hunts_through_junk() -> None:
    state = DeviceState()
    state.publish(SAMPLE)
    dev = ModbusDevice(state, default_register_map())
    req = rtu_frame(1, read_request_pdu(3, 4, 2))
    buf = bytearray(b"\x00\x01\x10\xff" + req[:5])  # junk (incl. a false FC16 header), half a request
    assert rtu_feed(dev, buf) == []
    buf += req[5:] + req  # the rest, then a second request
    out = rtu_feed(dev, buf)
    assert len(out) == 2 and not buf
    assert decode_rtu_response(out[0], 1, 3, 2) == struct.pack(">f", SAMPLE.x_m)
    assert dev.bytes_discarded == 4


class FakeIO:
    """In-memory RTU line: each request is answered by ``respond(request)``."""

    def __init__(self, respond: Callable[[bytes], bytes]) -> None:
        self.respond = respond
        self.pending = b""
        self.requests: list[bytes] = []
        self.wakes: list[int] = []  # the link's sleep-until hint per read (0 = none)

    def write(self, data: bytes | bytearray, deadline: float) -> None:
        self.requests.append(bytes(data))
        self.pending += self.respond(bytes(data))

    def read(self, n: int, deadline: float, max_n: int = 0, wake_ns: int = 0) -> bytes:
        self.wakes.append(wake_ns)
        n = max(n, max_n)
        out, self.pending = self.pending[:n], self.pending[n:]
        return out

    def flush_input(self) -> int:
        n, self.pending = len(self.pending), b""
        return n

    def close(self) -> None:
        pass


class FakeSock:
    """TCP for ModbusLink over a socketpair; the 'device' answers synchronously via ``respond``."""

    def __init__(self, respond: Callable[[bytes], bytes]) -> None:
        self.respond = respond
        self.a, self.b = socket.socketpair()
        self.a.setblocking(False)

    def send(self, data: bytes | bytearray) -> int:
        r = self.respond(bytes(data))
        if r:
            self.b.sendall(r)
        return len(data)

    def recv(self, n: int) -> bytes:
        return self.a.recv(n)

    def fileno(self) -> int:
        return self.a.fileno()

    def close(self) -> None:
        self.a.close()
        self.b.close()


def attach(transport: str, respond: Callable[[bytes], bytes], fc23: bool = True, timeout_s: float = NO_REPLY_S,
           **kw: Any) -> ModbusLink:
    """A ModbusLink wired to an in-memory device (RTU) or a socketpair (TCP)."""
    link = ModbusLink(transport, host="fake", url="fake", timeout_s=timeout_s, use_fc23=fc23, **kw)
    if transport == "tcp":
        link._attach_transport(use_fc23=fc23, sock=FakeSock(respond))  # noqa: SLF001
    else:
        link._attach_transport(use_fc23=fc23, io=FakeIO(respond))  # noqa: SLF001
    return link


@FUZZ
@given(transport=st.sampled_from(["tcp", "rtu"]), fc23=st.booleans(), reply=st.binary(max_size=80),
       keep_header=st.booleans(), crc=st.booleans())
def test_fuzz_whole_exchange(transport: str, fc23: bool, reply: bytes, keep_header: bool, crc: bool) -> None:
    """Arbitrary reply bytes: exchange returns a Sample or raises a LinkError, nothing else."""

    def respond(req: bytes) -> bytes:
        if transport == "tcp":
            body = req[:2] + reply[2:] if keep_header else reply
            return body
        body = req[:2] + reply if keep_header else reply
        return body + crc16_modbus(body).to_bytes(2, "little") if crc else body

    link = attach(transport, respond, fc23, timeout_s=0.002)
    try:
        s = link.exchange(0.5)
    except LinkError:
        return
    finally:
        if transport == "tcp":
            link._io.close()  # noqa: SLF001 - the socketpair
    assert isinstance(s, Sample) and math.isfinite(s.x_m) and math.isfinite(s.v_mps)


def _device_respond(transport: str, state: DeviceState, **kw: Any) -> Callable[[bytes], bytes]:
    """The device's answer at once; a SYNC reply as if its tick came at once."""
    dev = ModbusDevice(state, **kw)
    handle = dev.handle_tcp_frame if transport == "tcp" else dev.handle_rtu_frame

    def respond(req: bytes) -> bytes:
        r = handle(req)
        return r.build() if isinstance(r, Deferred) else r or b""

    return respond


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_in_memory_exchange_unwraps_counters_and_nan_force(transport: str) -> None:
    state = DeviceState()
    m = RegisterMap.from_mapping(_with(seq={"address": 0, "type": "uint16"}))
    link = attach(transport, _device_respond(transport, state, register_map=m), register_map=m)
    t0 = 2**32 - 2  # µs: the uint32 device clock wraps after the first sample
    for k, seq in enumerate((65534, 65535, 0, 1)):
        state.publish(SAMPLE._replace(seq=seq, t_dev_s=((t0 + 1000 * k) % 2**32) * 1e-6,
                                      status=int(Status.NO_LOAD_CELL), F_N=0.0))
        s = link.exchange(0.25)
        assert s.seq == 65534 + k  # extended beyond 16 bits: the safety layer sees no wrap
        assert s.t_dev_s == pytest.approx((t0 + 1000 * k) * 1e-6)
        assert math.isnan(s.F_N)  # NO_LOAD_CELL → NaN whatever the register says
    assert state.setpoint()[:2] == (0.25, True)
    assert link.device_clock_resets == 0


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_in_memory_error_mapping(transport: str) -> None:
    state = DeviceState()
    state.publish(SAMPLE)
    good = _device_respond(transport, state)
    # exception response
    link = attach(transport, _device_respond(transport, state, fc23=False))
    with pytest.raises(DeviceError, match="ILLEGAL_FUNCTION") as ei:
        link.exchange(0.1)
    assert ei.value.code == ILLEGAL_FUNCTION and link.device_errors == 1
    # silence
    link = attach(transport, lambda req: b"")
    with pytest.raises(LinkTimeout):
        link.exchange(0.1)
    assert link.timeouts == 1
    # non-finite x: a healthy link carrying bad data; the sample is returned
    # (NaN) for the safety supervisor to judge, and counted
    state.publish(SAMPLE._replace(x_m=math.nan))
    link = attach(transport, good)
    assert math.isnan(link.exchange(0.1).x_m)
    assert link.invalid_values == 1 and link.frame_errors == 0
    state.publish(SAMPLE)
    assert link.exchange(0.1).x_m == f32(SAMPLE.x_m)
    if transport == "rtu":
        # junk before the reply is skipped; a corrupt CRC is a FrameError
        link = attach(transport, lambda req: b"\x00\xff\x01" + good(req))
        assert link.exchange(0.1).v_mps == f32(SAMPLE.v_mps)
        assert link.bytes_discarded == 3
        link = attach(transport, lambda req: good(req)[:-1] + bytes((good(req)[-1] ^ 0xFF,)))
        with pytest.raises(FrameError, match="CRC"):
            link.exchange(0.1)
        assert link.crc_errors == 1
        link = attach(transport, lambda req: good(req)[:10])
        with pytest.raises(FrameError, match="truncated"):
            link.exchange(0.1)
    else:
        # an old reply is skipped; a reply with another MBAP protocol id is a FrameError
        old: list[bytes] = []

        def late(req: bytes) -> bytes:
            r = good(req)
            out = (old.pop() if old else b"") + r
            old.append(b"\x7f\x7f" + r[2:])  # a stale reply precedes the next one
            return out

        link = attach(transport, late)
        link.exchange(0.1)
        link.exchange(0.1)
        assert link.stale_replies == 1
        link = attach(transport, lambda req: req[:2] + b"\x00\x01" + good(req)[4:])
        with pytest.raises(FrameError, match="MBAP"):
            link.exchange(0.1)
    with pytest.raises(ValueError):
        link.exchange(math.nan)


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_watchdog_and_clear_faults_reach_the_bench(transport: str) -> None:
    state = DeviceState()
    state.publish(SAMPLE)
    link = attach(transport, _device_respond(transport, state), watchdog_ms=20)
    link.exchange(0.3)
    assert state.setpoint_ex()[3:] == (20, 0)  # watchdog 20 ms, no clear request
    assert link.request_clear_faults()
    link.exchange(0.3)
    assert state.setpoint_ex()[0:2] == (f32(0.3), True) and state.setpoint_ex()[4] == 1
    link.exchange(0.3)
    assert state.setpoint_ex()[4] == 1  # once
    link.enabled = False
    link.request_clear_faults()
    link.exchange(0.3)
    assert state.setpoint_ex()[1] is False and state.setpoint_ex()[4] == 2
    m = RegisterMap.from_mapping({"registers": {k: v for k, v in DEFAULT_REGISTER_MAP["registers"].items()
                                                if k not in ("enable", "watchdog_ms")}})
    assert not ModbusLink("tcp", host="x", register_map=m).request_clear_faults()


def test_rtu_late_reply_is_flushed_not_taken() -> None:
    """RTU has no transaction id: a reply arriving after its deadline must not be
    taken as the next request's (which would shift every later exchange by one)."""
    state = DeviceState()
    good = _device_respond("rtu", state)
    late: list[bytes] = []
    link = attach("rtu", lambda req: late.append(good(req)) or b"")
    state.publish(SAMPLE._replace(seq=1))
    with pytest.raises(LinkTimeout):
        link.exchange(0.1)
    io = link._io  # noqa: SLF001
    io.pending += late.pop()  # the old answer shows up between ticks
    io.respond = good
    state.publish(SAMPLE._replace(seq=2))
    assert link.exchange(0.1).seq == 2
    assert link.bytes_discarded == 31


# =============================================================================
# loopback: real device loops in threads
@pytest.fixture(params=["thread", "inline"])
def tcp_device(request) -> Iterator[Callable[..., tuple[DeviceState, int]]]:
    """A Modbus TCP device on loopback, served both ways hil_sim can:
    a thread per connection, or polled from the clock thread (inline)."""
    stops: list[tuple[threading.Event, threading.Thread]] = []
    serve = serve_modbus_tcp if request.param == "thread" else serve_modbus_tcp_inline

    def start(**kw: Any) -> tuple[DeviceState, int]:
        state = DeviceState()
        state.publish(SAMPLE)
        stop = threading.Event()
        got: list[str] = []
        th = threading.Thread(target=serve, args=(state, "127.0.0.1", 0, kw.pop("register_map", None), stop, got.append),
                              kwargs=kw, daemon=True)
        th.start()
        t_end = time.monotonic() + 5
        while not got and time.monotonic() < t_end:
            time.sleep(0.005)
        assert got and got[0].startswith("modbus-tcp 127.0.0.1:")
        stops.append((stop, th))
        return state, int(got[0].rsplit(":", 1)[1])

    yield start
    for stop, th in stops:
        stop.set()
        th.join(5)


def check_sample(s: Sample, ref: Sample = SAMPLE) -> None:
    assert s.seq == ref.seq
    assert s.t_dev_s == pytest.approx(ref.t_dev_s, abs=1e-6)
    assert (s.x_m, s.v_mps, s.F_N, s.current_A) == (f32(ref.x_m), f32(ref.v_mps), f32(ref.F_N), f32(ref.current_A))
    assert s.status == ref.status


@pytest.mark.parametrize("use_fc23", [None, True, False])
def test_tcp_loopback(tcp_device, use_fc23: bool | None) -> None:
    state, port = tcp_device()
    link = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S, use_fc23=use_fc23)
    assert isinstance(link, Link)
    with link:
        assert link.use_fc23 is (use_fc23 is not False)
        assert state.setpoint()[:2] == (0.0, False)  # nothing enabled before the first exchange (probe: 0 A, off)
        for k in range(20):
            ref = SAMPLE._replace(seq=SAMPLE.seq + k, t_dev_s=SAMPLE.t_dev_s + 1e-3 * k)
            state.publish(ref)
            check_sample(link.exchange(0.1 * k), ref)
            assert state.setpoint()[:2] == (pytest.approx(0.1 * k), True)
        link.enabled = False
        link.exchange(1.0)
        assert state.setpoint()[:2] == (1.0, False)
        assert link.exchanges == 21 and link.timeouts == 0
        assert "modbus-tcp 127.0.0.1" in link.describe()
    assert state.setpoint()[:2] == (0.0, False)  # close() wrote 0 A, disabled
    link.close()  # idempotent
    with pytest.raises(Disconnected):
        link.exchange(0.0)


def test_tcp_device_without_fc23_falls_back(tcp_device) -> None:
    state, port = tcp_device(fc23=False)
    with ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S) as link:
        assert link.use_fc23 is False and link.fc23_fallbacks == 1
        check_sample(link.exchange(0.5))
        assert state.setpoint()[:2] == (0.5, True)
        assert "FC16+FC3/4" in link.describe()
    forced = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S, use_fc23=True)
    forced.open()
    try:
        with pytest.raises(DeviceError, match="ILLEGAL_FUNCTION") as ei:
            forced.exchange(0.5)
        assert ei.value.code == ILLEGAL_FUNCTION
    finally:
        forced.close()


def test_tcp_illegal_address_and_unit(tcp_device) -> None:
    state, port = tcp_device()
    # the client's map puts x_m where the device has nothing → ILLEGAL_ADDRESS (at the probe)
    far = RegisterMap.from_mapping(_with(F_N={"address": 40}))
    link = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S, register_map=far)
    with pytest.raises(DeviceError, match="ILLEGAL_ADDRESS"):
        link.open()
    assert not link.is_open
    link = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S, unit_id=9, use_fc23=True)
    with link:
        with pytest.raises(DeviceError) as ei:
            link.exchange(0.0)
        assert ei.value.code == 0x0B


def test_tcp_two_clients_at_once(tcp_device) -> None:
    state, port = tcp_device()
    a = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S, use_fc23=True)
    b = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S, use_fc23=False)
    with a, b:
        for _ in range(10):
            check_sample(a.exchange(0.2))
            check_sample(b.exchange(0.3))


def test_tcp_late_reply_is_discarded() -> None:
    """A reply arriving after the deadline is skipped by transaction id next tick."""
    state = DeviceState()
    state.publish(SAMPLE)
    dev = ModbusDevice(state)
    ls = socket.create_server(("127.0.0.1", 0))
    delays = [0.3, 0.0, 0.0]

    def serve() -> None:
        c, _ = ls.accept()
        with c:
            for d in delays:
                req = c.recv(4096)
                time.sleep(d)
                c.sendall(dev.handle_tcp_frame(req) or b"")

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    link = ModbusLink("tcp", host="127.0.0.1", port=ls.getsockname()[1], timeout_s=NO_REPLY_S, use_fc23=True)
    with link:
        with pytest.raises(LinkTimeout):
            link.exchange(0.1)
        link.timeout_s = REPLY_S
        check_sample(link.exchange(0.2))
        assert link.stale_replies == 1
    th.join(5)
    ls.close()


@pytest.mark.parametrize("serve", [serve_modbus_tcp, serve_modbus_tcp_inline], ids=["thread", "inline"])
def test_tcp_disconnect(serve: Callable[..., None]) -> None:
    """Server stopped → Disconnected (the device closes its connections); reopen → Disconnected (refused)."""
    state = DeviceState()
    state.publish(SAMPLE)
    stop = threading.Event()
    got: list[str] = []
    th = threading.Thread(target=serve, args=(state, "127.0.0.1", 0, None, stop, got.append), daemon=True)
    th.start()
    while not got:
        time.sleep(0.005)
    port = int(got[0].rsplit(":", 1)[1])
    link = ModbusLink("tcp", host="127.0.0.1", port=port, timeout_s=REPLY_S)
    link.open()
    link.exchange(0.1)
    stop.set()
    th.join(5)
    with pytest.raises(Disconnected):
        link.exchange(0.1)
    assert link.disconnects == 1 and not link.is_open
    with pytest.raises(Disconnected, match="cannot connect"):
        link.open()
    link.close()


def _serve_rtu_inline(state: DeviceState, path: str, baud: int, register_map: RegisterMap | None,
                      stop: threading.Event, ready: Callable[[str], None], fc23: bool = True) -> None:
    """hil_sim's ``--serve inline`` RTU server, polled as its clock's spin does."""
    port = open_serial_port(path, baudrate=baud, timeout=0)
    try:
        srv = ModbusRtuInline(ModbusDevice(state, register_map, fc23=fc23), port.fileno(), rtu_silence_s(baud))
        ready(f"modbus-rtu {path}")
        while not stop.is_set():
            srv.poll_once()
            time.sleep(1e-4)
    finally:
        port.close()


@pytest.fixture(params=["thread", "inline"])
def rtu_device(request) -> Iterator[Callable[..., tuple[DeviceState, int, int]]]:
    """A Modbus RTU device on a pty, served both ways hil_sim can."""
    cleanup: list[Callable[[], None]] = []
    serve = serve_modbus_rtu if request.param == "thread" else _serve_rtu_inline

    def start(**kw: Any) -> tuple[DeviceState, int, int]:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        state = DeviceState()
        state.publish(SAMPLE)
        stop = threading.Event()
        got: list[str] = []
        th = threading.Thread(target=serve, args=(state, os.ttyname(slave), 921600, None, stop, got.append),
                              kwargs=kw, daemon=True)
        th.start()
        t_end = time.monotonic() + 5
        while not got:
            assert th.is_alive() and time.monotonic() < t_end, "the RTU device did not start"
            time.sleep(0.005)

        def clean() -> None:
            stop.set()
            th.join(5)
            for fd in (master, slave):
                try:
                    os.close(fd)
                except OSError:
                    pass

        cleanup.append(clean)
        return state, master, slave

    yield start
    for c in cleanup:
        c()


@pytest.mark.parametrize("use_fc23", [None, False])
def test_rtu_loopback_on_pty(rtu_device, use_fc23: bool | None) -> None:
    state, master, _ = rtu_device()
    link = ModbusLink("rtu", url=master, timeout_s=REPLY_S, use_fc23=use_fc23)
    with link:
        assert link.use_fc23 is (use_fc23 is None)
        for k in range(20):
            ref = SAMPLE._replace(seq=SAMPLE.seq + k)
            state.publish(ref)
            check_sample(link.exchange(0.05 * k), ref)
            assert state.setpoint()[:2] == (pytest.approx(0.05 * k), True)
        assert "modbus-rtu" in link.describe() and "µs on the wire" in link.describe()
    assert state.setpoint()[:2] == (0.0, False)


def test_rtu_fallback_timeout_and_gone(rtu_device) -> None:
    state, master, slave = rtu_device(fc23=False)
    link = ModbusLink("rtu", url=master, timeout_s=REPLY_S)
    link.open()
    assert link.use_fc23 is False and link.fc23_fallbacks == 1
    check_sample(link.exchange(0.3))
    # a unit nobody answers → LinkTimeout (RTU devices stay silent)
    other = ModbusLink("rtu", url=master, timeout_s=NO_REPLY_S, unit_id=7, use_fc23=False)
    other._attach_transport(use_fc23=False, io=link._io)  # noqa: SLF001 - share the open pty
    with pytest.raises(LinkTimeout):
        other.exchange(0.0)
    check_sample(link.exchange(0.3))  # the real unit still answers
    link.close()
    assert state.setpoint()[:2] == (0.0, False)


@contextlib.contextmanager
def rtu_device_on_master_fd() -> Iterator[tuple[DeviceState, str]]:
    """An RTU device serving a pty master fd; yields (state, the tty path a client opens)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    state = DeviceState()
    state.publish(SAMPLE)
    stop = threading.Event()
    th = threading.Thread(target=serve_modbus_rtu, args=(state, master, 921600, None, stop), daemon=True)
    th.start()
    try:
        yield state, os.ttyname(slave)
    finally:
        stop.set()
        th.join(5)
        os.close(master)
        os.close(slave)


def test_rtu_client_on_pty_path() -> None:
    """The client can open a tty path too (pyserial), the device an fd."""
    with rtu_device_on_master_fd() as (state, path):
        with ModbusLink("rtu", url=path, timeout_s=REPLY_S) as link:
            check_sample(link.exchange(0.4))
            assert state.setpoint()[:2] == (f32(0.4), True)


def test_rtu_gone_is_disconnected() -> None:
    master, slave = os.openpty()
    tty.setraw(master)
    link = ModbusLink("rtu", url=master, timeout_s=NO_REPLY_S, use_fc23=True)
    link.open()
    os.close(slave)  # nobody holds the device side any more: reads on the master fail (EIO)
    with pytest.raises(Disconnected):
        link.exchange(0.0)
    assert link.disconnects == 1
    os.close(master)


def test_open_failures_are_disconnected() -> None:
    with pytest.raises(Disconnected):
        ModbusLink("tcp", host="127.0.0.1", port=free_port()).open()  # nothing listens there
    with pytest.raises(Disconnected):
        ModbusLink("rtu", url="/dev/nonexistent-tty").open()
    with pytest.raises(ValueError):
        ModbusLink("rtu", url="/dev/x", unit_id=0)
    with pytest.raises(ValueError):
        ModbusLink("udp", host="x")


def test_pymodbus_client_reads_device(tcp_device) -> None:
    """A third-party client (pymodbus sync) agrees with docs/registers.md."""
    from pymodbus.client import ModbusTcpClient

    state, port = tcp_device()
    c = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    assert c.connect()
    try:
        r = c.read_holding_registers(0, count=13, device_id=1)
        assert not r.isError()
        conv = ModbusTcpClient.convert_from_registers
        assert conv(r.registers[0:2], DT.UINT32) == SAMPLE.seq
        assert conv(r.registers[2:4], DT.UINT32) == round(SAMPLE.t_dev_s * 1e6)
        assert conv(r.registers[4:6], DT.FLOAT32) == f32(SAMPLE.x_m)
        assert conv(r.registers[8:10], DT.FLOAT32) == f32(SAMPLE.F_N)
        assert r.registers[12] == SAMPLE.status
        w = c.readwrite_registers(read_address=4, read_count=2, write_address=16,
                                  values=ModbusTcpClient.convert_to_registers(0.9, DT.FLOAT32) + [1, 50], device_id=1)
        assert conv(w.registers, DT.FLOAT32) == f32(SAMPLE.x_m)
        assert state.setpoint()[:2] == (f32(0.9), True)
        assert c.read_holding_registers(30, count=2, device_id=1).exception_code == ILLEGAL_DATA_ADDRESS
        assert c.read_input_registers(0, count=2, device_id=1).exception_code == ILLEGAL_DATA_ADDRESS
    finally:
        c.close()


# =============================================================================
# mbpoll (the lead's CI installs it: apt-get install -y mbpoll)
MBPOLL = shutil.which("mbpoll")


def _mbpoll(port: int, *args: str) -> dict[int, str]:
    r = subprocess.run(["mbpoll", "-m", "tcp", "-a", "1", "-0", "-1", "-o", "2", "-p", str(port), *args],
                       capture_output=True, text=True, timeout=20)
    assert r.returncode == 0, r.stdout + r.stderr
    return {int(a): v for a, v in re.findall(r"^\[(\d+)\]:\s+(\S+)", r.stdout, re.M)}


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll not installed (apt-get install -y mbpoll)")
def test_mbpoll_reads_documented_registers(tcp_device) -> None:
    state, port = tcp_device()
    # commands as in docs/registers.md (mbpoll -0: PDU addresses; -B: big word order)
    floats = _mbpoll(port, "-t", "4:float", "-B", "-r", "4", "-c", "4", "127.0.0.1")
    assert {k: float(v) for k, v in floats.items()} == pytest.approx(
        {4: SAMPLE.x_m, 6: SAMPLE.v_mps, 8: SAMPLE.F_N, 10: SAMPLE.current_A}, rel=1e-6)
    ints = _mbpoll(port, "-t", "4:int", "-B", "-r", "0", "-c", "2", "127.0.0.1")
    assert {k: int(v) for k, v in ints.items()} == {0: SAMPLE.seq, 2: round(SAMPLE.t_dev_s * 1e6)}
    assert int(_mbpoll(port, "-t", "4", "-r", "12", "-c", "1", "127.0.0.1")[12]) == SAMPLE.status
    # a write: current setpoint float at 16 (enable register 18 stays 0 → disabled)
    r = subprocess.run(["mbpoll", "-m", "tcp", "-a", "1", "-0", "-p", str(port), "-t", "4:float", "-B", "-r", "16",
                        "127.0.0.1", "--", "1.5"], capture_output=True, text=True, timeout=20)
    assert r.returncode == 0, r.stdout + r.stderr
    assert state.setpoint()[:2] == (1.5, False)


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll not installed (apt-get install -y mbpoll)")
def test_mbpoll_rtu_on_pty() -> None:
    with rtu_device_on_master_fd() as (_state, path):
        r = subprocess.run(["mbpoll", "-m", "rtu", "-a", "1", "-0", "-1", "-o", "2", "-b", "921600", "-P", "even",
                            "-t", "4:float", "-B", "-r", "4", "-c", "2", path],
                           capture_output=True, text=True, timeout=20)
        assert r.returncode == 0, r.stdout + r.stderr
        got = {int(a): float(v) for a, v in re.findall(r"^\[(\d+)\]:\s+(\S+)", r.stdout, re.M)}
        assert got == pytest.approx({4: SAMPLE.x_m, 6: SAMPLE.v_mps}, rel=1e-6)


def test_device_paced_exchange_sleeps_until_shortly_before_the_next_tick() -> None:
    """Device pacing: after the first reply, each exchange's wait starts with a
    sleep until one period after the last reply, less the spin margin (a
    sleeping thread wakes late on a VM, so it polls only for that margin);
    host pacing never sleeps in the link."""
    state = DeviceState()
    state.publish(SAMPLE)
    link = attach("rtu", _device_respond("rtu", state))
    io = link._io  # noqa: SLF001
    link.exchange(0.1)
    link.set_device_paced(True, 1e-3, 3e-4)
    link.exchange(0.1)  # no reply time yet: nothing to sleep for
    t_reply = link._t_reply_ns  # noqa: SLF001
    assert t_reply > 0
    link.exchange(0.1)
    assert io.wakes == [0, 0, t_reply + 1_000_000 - 300_000]
    assert state.setpoint()[0] == pytest.approx(0.1)
    link.set_device_paced(False, 1e-3)
    link.exchange(0.2)
    assert io.wakes[-1] == 0 and link._t_reply_ns == 0  # noqa: SLF001
