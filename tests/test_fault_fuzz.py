"""Bad input fuzzing: the experiment config, hil_sim's bench/fault config, and the
device-side decoders that tests/test_protocol.py and tests/test_modbus.py do not
already fuzz.

Config (mrctl.config.validate_experiment): random mutations of the shipped,
valid experiments — wrong types, out-of-range and non-finite numbers, unknown
keys, missing keys and sections, sections replaced by scalars. Every outcome
is either a validated config whose every value conforms to the schema, or a
``ConfigError`` whose every message starts with a key path that exists in the
input or in the schema; never another exception. A sweep over every number,
flag and choice field checks that out-of-range / wrong-type values are never
accepted (a negative ``safety.I_max`` never validates) and that the error
names that very key.

Frames: the serial device's request handling (hil_sim.serial_device) on
arbitrary bytes, with and without reply faults active, and the Modbus device
with arbitrary fault bits; the serial FrameDecoder, the Modbus client
decoders and the Modbus request decoder are fuzzed in test_protocol.py /
test_modbus.py already.
"""

from __future__ import annotations

import copy
import math
import re
import socket
import threading
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mrctl.config import (
    Bool,
    ConfigError,
    Custom,
    Node,
    Num,
    Section,
    Str,
    Union,
    experiment_schema,
    load_yaml,
    validate_experiment,
)

ROOT = Path(__file__).resolve().parents[1]
EXP_DIR = ROOT / "config" / "experiments"
BASES = {name: load_yaml(EXP_DIR / name) for name in
         ("fig5.yaml", "fig5_paper.yaml", "identify.yaml", "hil_serial.yaml", "hil_modbus_tcp.yaml",
          "hil_modbus_rtu.yaml")}
SCHEMA = experiment_schema(EXP_DIR)

FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# -----------------------------------------------------------------------------
# key paths
def _custom_names(path: str) -> list[str]:
    """Known sub-keys below a Custom field (its own small schema)."""
    if path.endswith("parameters"):
        from mrctl.model.params import LuGreParams

        return ["file", *LuGreParams.all_names()]
    if path.endswith("registers"):
        from mrctl.io.registers.spec import ENTRY_KEYS as _ENTRY_KEYS, QUANTITIES, TOP_KEYS as _TOP_KEYS

        return [*_TOP_KEYS, *QUANTITIES, *_ENTRY_KEYS]
    return []


def _input_paths(obj: Any, prefix: str = "") -> list[str]:
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            p = f"{prefix}.{k}" if prefix else str(k)
            out.append(p)
            out += _input_paths(v, p)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            p = f"{prefix}[{i}]"
            out.append(p)
            out += _input_paths(v, p)
    return out


def _schema_key_paths(fields: Any = None, prefix: str = "") -> list[str]:
    out = []
    for k, spec in (fields if fields is not None else SCHEMA).items():
        p = f"{prefix}.{k}" if prefix else k
        out.append(p)
        if isinstance(spec, Section):
            out += _schema_key_paths(spec.fields, p)
        elif isinstance(spec, Union):
            out.append(f"{p}.{spec.key}")
            for v in spec.variants.values():
                out += _schema_key_paths(v, p)
        elif isinstance(spec, Custom):
            names = _custom_names(p)
            out += [f"{p}.{a}" for a in names]
            out += [f"{p}.{a}.{b}" for a in names for b in names]  # registers.registers.x_m, ...
    return out


SCHEMA_KEY_PATHS = set(_schema_key_paths())


def _path_of(msg: str) -> str:
    """The key path a message starts with (for messages about ordinary keys)."""
    head = msg.split(": ", 1)[0]
    return head.split(" (", 1)[0]


def names_a_known_path(msg: str, data: Any) -> bool:
    """True if ``msg`` starts with a key path that exists in the input or the schema."""
    if msg.startswith("config: "):
        return True
    candidates = SCHEMA_KEY_PATHS | set(_input_paths(data))
    head = msg.split(": ", 1)[0]
    if head.endswith(">") and "<" in head:  # a key that is not a name, described (never echoed): its parent's path
        parent = head[:head.index("<")].rstrip(".")
        return parent == "" or parent in candidates
    return any(msg.startswith(c + ": ") or msg.startswith(c + " (") for c in candidates)


# -----------------------------------------------------------------------------
# "nothing invalid is accepted": a validated config conforms to the schema
def _conforms(spec: Any, value: Any, path: str) -> list[str]:
    bad: list[str] = []
    if isinstance(spec, Num):
        if value is None:
            return [] if spec.optional else [f"{path}: None"]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return [f"{path}: {value!r}"]
        if spec.integer and not float(value).is_integer():
            bad.append(f"{path}: not integer {value!r}")
        if spec.min is not None and (value <= spec.min if spec.min_exclusive else value < spec.min):
            bad.append(f"{path}: {value!r} < min")
        if spec.max is not None and value > spec.max:
            bad.append(f"{path}: {value!r} > max")
        return bad
    if isinstance(spec, Str):
        if value is None:
            return [] if spec.optional else [f"{path}: None"]
        if not isinstance(value, str) or (spec.choices and value not in spec.choices):
            return [f"{path}: {value!r}"]
        return []
    if isinstance(spec, Bool):
        return [] if isinstance(value, bool) else [f"{path}: {value!r}"]
    if isinstance(spec, Section):
        if not isinstance(value, Node):
            return [f"{path}: not a section"]
        for k, s in spec.fields.items():
            bad += _conforms(s, value.get(k), f"{path}.{k}" if path else k)
        return bad
    if isinstance(spec, Union):
        if value is None and spec.optional:  # an optional section left out (demand, for a direct current law)
            return []
        if not isinstance(value, Node) or value.get(spec.key) not in spec.variants:
            return [f"{path}: bad union"]
        for k, s in spec.variants[value.get(spec.key)].items():
            bad += _conforms(s, value.get(k), f"{path}.{k}")
        return bad
    return []  # Custom: its own checks (tested with their modules)


def check_accepted(node: Node) -> None:
    bad = []
    for k, spec in SCHEMA.items():
        bad += _conforms(spec, node.get(k), k)
    s = node.safety
    assert math.isfinite(s.I_max) and s.I_max > 0.0
    inv = node.inverse
    if inv.law == "constant":
        assert inv.current_A <= s.I_max
    if inv.law == "schedule":
        assert all(0.0 <= c <= s.I_max for c in inv.currents_A)
    for r in ("x_range_m", "v_range_mps", "F_range_N"):
        rng = s.get(r)
        assert rng is None or (math.isfinite(rng[0]) and math.isfinite(rng[1]) and rng[0] <= rng[1])
    assert not bad, bad


def check(data: Any) -> ConfigError | None:
    """Validate; assert the outcome is one of the two allowed ones."""
    try:
        node = validate_experiment(data, EXP_DIR, "fuzz")
    except ConfigError as exc:
        assert exc.errors, "a ConfigError without messages"
        for msg in exc.errors:
            assert names_a_known_path(msg, data), f"error does not start with a known key path: {msg!r}"
        return exc
    check_accepted(node)
    return None


# -----------------------------------------------------------------------------
# mutations
NASTY = st.one_of(
    st.none(), st.booleans(),
    st.integers(min_value=-10**12, max_value=10**12),
    st.sampled_from([0, -1, 1, 2, 10**9, 0.5, -0.5, 1e-12, 1e300, -1e300]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["", "abc", "1e-3", "table1", "auto", "sim", "serial", "sine", "smooth", "-1", "nan"]),
    st.lists(st.one_of(st.integers(-5, 5), st.floats(allow_nan=True), st.text(max_size=3)), max_size=3),
    st.dictionaries(st.one_of(st.text(max_size=6), st.sampled_from(["type", "law", "file", "x_m", "1"])),
                    st.integers(-3, 3), max_size=2),
)


def _paths(obj: Any, prefix: tuple = ()) -> list[tuple]:
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append(prefix + (k,))
            out += _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append(prefix + (i,))
            out += _paths(v, prefix + (i,))
    return out


def _schema_paths() -> list[tuple]:
    out: list[tuple] = []
    for k, spec in SCHEMA.items():
        out.append((k,))
        if isinstance(spec, Section):
            for f, sub in spec.fields.items():
                out.append((k, f))
                if isinstance(sub, Section):
                    out += [(k, f, g) for g in sub.fields]
        elif isinstance(spec, Union):
            out.append((k, spec.key))
            for v in spec.variants.values():
                out += [(k, f) for f in v]
    return out


SCHEMA_PATHS = _schema_paths()


def _apply(data: dict, path: tuple, action: str, value: Any) -> None:
    node: Any = data
    for p in path[:-1]:
        if isinstance(node, dict):
            if p not in node or not isinstance(node[p], (dict, list)):
                node[p] = {}
            node = node[p]
        elif isinstance(node, list) and isinstance(p, int) and p < len(node):
            node = node[p]
        else:
            return
    last = path[-1]
    if isinstance(node, dict):
        if action == "delete":
            node.pop(last, None)
        elif action == "unknown":
            node[f"{last}_typo"] = value
        else:
            node[last] = value
    elif isinstance(node, list) and isinstance(last, int) and last < len(node):
        if action == "delete":
            del node[last]
        else:
            node[last] = value


@st.composite
def mutated(draw) -> dict:
    name = draw(st.sampled_from(sorted(BASES)))
    data = copy.deepcopy(BASES[name])
    for _ in range(draw(st.integers(1, 3))):
        pool = _paths(data) + SCHEMA_PATHS
        path = draw(st.sampled_from(pool))
        action = draw(st.sampled_from(["set", "set", "set", "delete", "unknown"]))
        value = draw(NASTY)
        _apply(data, path, action, value)
    return data


@pytest.mark.parametrize("value", [[], {"a": 1}])
def test_unhashable_union_discriminator_is_a_config_error(value: Any) -> None:
    data = copy.deepcopy(BASES["fig5.yaml"])
    data["backend"] = {"type": value}
    exc = check(data)
    assert exc is not None and any(m.startswith("backend.type: ") for m in exc.errors)


@FUZZ
@given(mutated())
def test_fuzz_config_mutations_give_config_errors_with_key_paths(data: dict) -> None:
    check(data)


@FUZZ
@given(st.one_of(NASTY, st.dictionaries(st.sampled_from([*SCHEMA, "bogus"]), NASTY, max_size=6)))
def test_fuzz_config_from_nothing(data: Any) -> None:
    check(data)


def test_shipped_bases_are_valid() -> None:
    for name, data in BASES.items():
        assert check(data) is None, name


# -----------------------------------------------------------------------------
# the sweep: every number / flag / choice field gets values it must refuse
def _field_cases() -> list[tuple[str, tuple, Any]]:
    """(base, path, bad value) for every leaf field reachable from some base."""
    cases = []
    for name, base in sorted(BASES.items()):
        for key, spec in SCHEMA.items():
            groups: list[tuple[tuple, dict]] = []
            if isinstance(spec, Section):
                groups.append(((key,), spec.fields))
                for f, sub in spec.fields.items():
                    if isinstance(sub, Section):
                        groups.append(((key, f), sub.fields))
            elif isinstance(spec, Union):
                variant = (base.get(key) or {}).get(spec.key, spec.default)
                if variant in spec.variants:
                    groups.append(((key,), spec.variants[variant]))
            else:
                groups.append(((), {key: spec}))
            for prefix, fields in groups:
                for f, s in fields.items():
                    path = prefix + (f,)
                    for bad in _bad_values(s):
                        cases.append((name, path, bad))
    # one case per (path, value): the first base that has the field's section
    seen, out = set(), []
    for name, path, bad in cases:
        key = (path, repr(bad))
        if key not in seen:
            seen.add(key)
            out.append((name, path, bad))
    return out


def _bad_values(spec: Any) -> list[Any]:
    if isinstance(spec, Num):
        vals: list[Any] = ["1", True, [1], math.nan, math.inf]
        if not spec.optional:
            vals.append(None)
        if spec.min is not None:
            vals.append(spec.min if spec.min_exclusive else spec.min - 1)
            vals.append(-1e9)
        if spec.max is not None:
            vals.append(spec.max * 2 + 1)
        if spec.integer:
            vals.append(1.5)
        return vals
    if isinstance(spec, Bool):
        return ["yes", 1, None, [True]]
    if isinstance(spec, Str):
        vals = [1, [], {}]
        if spec.choices:
            vals.append("no-such-choice")
        if not spec.optional:
            vals.append(None)
        return vals
    return []


FIELD_CASES = _field_cases()


def test_sweep_covers_the_schema() -> None:
    paths = {".".join(map(str, p)) for _, p, _ in FIELD_CASES}
    for must in ("version", "rate_hz", "safety.I_max", "safety.hold_ticks", "safety.auto_resume",
                 "safety.link_loss_s", "backend.timeout_s", "backend.port", "backend.parity", "loop.wait",
                 "record.buffer_ticks", "plant.sensors.seed", "inverse.eps_N_per_A", "excitation.amplitude_m"):
        assert must in paths, must
    assert len(FIELD_CASES) > 300


def test_sweep_every_field_refuses_bad_values_naming_the_key() -> None:
    failures = []
    for name, path, bad in FIELD_CASES:
        data = copy.deepcopy(BASES[name])
        _apply(data, path, "set", bad)
        exc = check(data)
        dotted = ".".join(map(str, path))
        if exc is None:
            failures.append(f"{name}: {dotted} = {bad!r} was accepted")
        elif not any(_path_of(m) == dotted for m in exc.errors):
            failures.append(f"{name}: {dotted} = {bad!r}: no error names it: {exc.errors}")
    assert not failures, "\n".join(failures[:20])


@pytest.mark.parametrize("value", [-0.6, 0.0, -1e-9, math.nan, -math.inf, "0.6", None, 2.5])
def test_a_bad_current_limit_never_validates(value: Any) -> None:
    for name, base in BASES.items():
        data = copy.deepcopy(base)
        data["safety"]["I_max"] = value
        exc = check(data)
        assert exc is not None and any(m.startswith("safety.I_max: ") for m in exc.errors), (name, value)


# -----------------------------------------------------------------------------
# hil_sim: the bench config's faults and the --fault syntax
@FUZZ
@given(st.one_of(NASTY, st.lists(st.one_of(
    NASTY,
    st.fixed_dictionaries({}, optional={
        "kind": st.one_of(st.sampled_from(["nan", "drop_replies", "delay_replies", "garbage", "out_of_range",
                                           "bogus"]), NASTY),
        "at_s": NASTY, "for_s": NASTY, "delay_s": NASTY, "n_bytes": NASTY, "field": NASTY, "x_m": NASTY,
        "extra": NASTY}),
), max_size=4)))
def test_fuzz_bench_faults_validate_with_key_paths(faults: Any) -> None:
    from hil_sim.config import ConfigError as BenchConfigError
    from hil_sim.config import validate_bench

    data = {"version": 1, "excitation": {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0},
            "faults": faults}
    try:
        cfg = validate_bench(data, Path("."), "fuzz")
    except BenchConfigError as exc:
        for msg in exc.errors:
            assert re.match(r"faults(\[\d+\](\.(kind|at_s|for_s|delay_s|n_bytes|field|x_m|extra))?)?: ", msg), msg
        return
    for f in cfg.faults:
        assert f.at_s >= 0 and f.for_s > 0 and math.isfinite(f.at_s) and math.isfinite(f.for_s)
        k0, k1 = f.window(1000.0)
        assert k1 > k0 >= 0


@FUZZ
@given(st.one_of(st.text(max_size=60),
                 st.builds(lambda k, a, b, p: f"{k}@{a}+{b}{p}",
                           st.sampled_from(["nan", "delay_replies", "garbage", "x"]),
                           st.one_of(st.floats(allow_nan=True), st.text(max_size=4)),
                           st.one_of(st.floats(allow_nan=True), st.text(max_size=4)),
                           st.text(max_size=12))))
def test_fuzz_fault_argument_never_raises(text: str) -> None:
    from hil_sim.faults import parse_fault_arg

    spec, errors = parse_fault_arg(text, 3)
    if spec is None:
        assert errors and all(e.startswith("--fault[3]") for e in errors), errors
    else:
        assert not errors and spec.for_s > 0 and math.isfinite(spec.at_s)


# -----------------------------------------------------------------------------
# frames: the serial device's request side, with and without reply faults
class _Dev:
    def __init__(self, fault_bits: int) -> None:
        from hil_sim.faults import FaultSchedule, parse_fault_arg
        from hil_sim.serial_device import SerialDevice
        from hil_sim.state import DeviceState
        from mrctl.io.base import Sample

        self.host, dev = socket.socketpair()
        dev.setblocking(False)
        self.host.setblocking(False)
        self._dev = dev
        self.state = DeviceState()
        self.state.publish(Sample(9, 0.009, 0.001, -0.02, math.nan, 8, 0.25))
        self.state.faults = FaultSchedule([parse_fault_arg("garbage@0+1,n_bytes=7")[0]], 1000.0)
        self.state.fault_bits = fault_bits
        self.dev = SerialDevice(self.state, dev.fileno(), threading.Event(), 1.0)

    def output(self) -> bytes:
        out = b""
        while True:
            try:
                chunk = self.host.recv(65536)
            except BlockingIOError:
                return out
            if not chunk:
                return out
            out += chunk

    def close(self) -> None:
        self.host.close()
        self._dev.close()


@FUZZ
@given(chunks=st.lists(st.one_of(
    st.binary(max_size=60),
    st.builds(lambda seq, cur, fl, wd: __import__("mrctl.io.protocol", fromlist=["x"]).encode_setpoint(
        seq, cur, fl, wd), st.integers(0, 2**32 - 1), st.floats(width=32, allow_nan=True),
        st.integers(0, 255), st.integers(0, 255)),
), max_size=8), faults=st.sampled_from([0, 4, 8, 1, 4 | 8]))
def test_fuzz_serial_device_requests(chunks: list[bytes], faults: int) -> None:
    """Arbitrary bytes at the serial device: it never raises, never applies a
    non-finite current, and (without reply faults) every byte it sends back is
    a valid frame."""
    from mrctl.io.protocol import FrameDecoder, SampleFrame, ErrorFrame

    d = _Dev(faults)
    try:
        for c in chunks:
            d.dev.handle(c)
        out = d.output()
        I, _, _ = d.state.setpoint()
        assert isinstance(I, float)
        dec = FrameDecoder()
        frames = dec.feed(out)
        assert all(isinstance(f, (SampleFrame, ErrorFrame)) for f in frames)
        if faults == 0:
            assert dec.crc_errors == 0 and dec.bytes_discarded == 0
    finally:
        d.close()


@FUZZ
@given(frame=st.binary(max_size=80), bits=st.integers(0, (1 << 11) - 1), tcp=st.booleans())
def test_fuzz_modbus_device_with_any_fault_bits(frame: bytes, bits: int, tcp: bool) -> None:
    """The Modbus device under any combination of fault bits: never raises, and
    fault_reply returns bytes (or None) and a finite non-negative delay."""
    from hil_sim.faults import FaultSchedule, parse_fault_arg
    from hil_sim.modbus_device import ModbusDevice, default_register_map
    from hil_sim.state import DeviceState
    from mrctl.io.base import Sample
    from mrctl.io.modbus import mbap_frame, rtu_frame

    state = DeviceState()
    state.publish(Sample(9, 0.009, 0.001, -0.02, 1.0, 8, 0.25))
    state.faults = FaultSchedule([parse_fault_arg("delay_replies@0+1,delay_s=0.002")[0]], 1000.0)
    state.faults.active(0)  # the delay spec is the active one (its delay_s)
    state.fault_bits = bits
    dev = ModbusDevice(state, default_register_map())
    for f in (frame, mbap_frame(1, 1, frame) if frame else b"", rtu_frame(1, frame) if frame else b""):
        resp = dev.handle_tcp_frame(f) if tcp else dev.handle_rtu_frame(f)
        if resp is not None:
            out, delay = dev.fault_reply(resp, tcp)
            assert out is None or isinstance(out, bytes)
            assert math.isfinite(delay) and delay >= 0.0
    assert math.isfinite(state.setpoint()[0])
