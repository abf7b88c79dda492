"""Modbus register map: which quantity lives in which register, as what type.

A :class:`RegisterMap` says, for every quantity the loop exchanges with a
Modbus device, the register table (holding / input), the start address
(0-based PDU address, what goes on the wire), the data type (int16, uint16,
int32, uint32, float32), the word order of 32-bit values and the linear
scaling ``physical = raw * scale + offset``. It is built from a plain mapping
(the YAML ``register_map`` section, see docs/registers.md) by
:meth:`RegisterMap.from_mapping`, which rejects anything odd with a
:class:`ValueError` whose message starts with the key path.

From the entries the map computes the *transaction plan* for one tick:

* one read block per table (the span covering every read quantity of that
  table, gaps included, ≤ 125 registers), and
* one write block (the write quantities, gap-free, ≤ 121 registers, holding).

If all read quantities are holding registers (one read block), a tick is a
single FC23 *read/write multiple registers* transaction; otherwise it is an
FC16 write plus one FC3/FC4 read per block.

Encoding and decoding use precompiled :class:`struct.Struct` objects over
whole blocks (one ``unpack``/``pack_into`` per block per tick) inside small
functions generated per map (~1 µs per tick each way); 32-bit values in
little word order are unpacked as two 16-bit words and recombined. Nothing
here imports pymodbus or pyserial: the device simulator, the client and the
config checker all share this module.

Counters (``seq``, ``t_dev``) are *raw* in :class:`ReadValues`: the client
unwraps them (a 16-bit seq wraps every 65 s at 1 kHz) before scaling, which
is why :class:`RegisterMap` exposes their modulus.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Mapping, NamedTuple, Sequence

__all__ = [
    "DATA_TYPES",
    "TABLES",
    "WORD_ORDERS",
    "READ_QUANTITIES",
    "WRITE_QUANTITIES",
    "QUANTITIES",
    "MAX_READ_REGISTERS",
    "MAX_WRITE_REGISTERS",
    "RegisterSpec",
    "Block",
    "ReadValues",
    "WriteValues",
    "RegisterMap",
    "default_register_map",
    "DEFAULT_REGISTER_MAP",
    "validate_register_map",
]

#: data type → (registers, struct code big-endian, integer?, signed?)
DATA_TYPES: dict[str, tuple[int, str, bool, bool]] = {
    "int16": (1, "h", True, True),
    "uint16": (1, "H", True, False),
    "int32": (2, "i", True, True),
    "uint32": (2, "I", True, False),
    "float32": (2, "f", False, True),
}
TABLES = ("holding", "input")
#: big = high word first (register n holds bits 31..16, "ABCD");
#: little = low word first ("CDAB"). Bytes within a register are always big-endian.
WORD_ORDERS = ("big", "little")

#: Quantities read every tick (device → host), with their physical units.
READ_QUANTITIES: dict[str, str] = {
    "seq": "count",  # device sample counter
    "t_dev": "s",  # device time of the measurement
    "x_m": "m",
    "v_mps": "m/s",
    "F_N": "N",
    "status": "bits",  # mrctl.io.base.Status
    "current_applied_A": "A",
}
#: Quantities written every tick (host → device).
WRITE_QUANTITIES: dict[str, str] = {
    "current_setpoint_A": "A",
    "enable": "flags",  # bit 0 ENABLE, bit 1 CLEAR_FAULTS (mrctl.io.protocol.SetpointFlag)
    "watchdog_ms": "ms",
}
QUANTITIES = {**READ_QUANTITIES, **WRITE_QUANTITIES}
REQUIRED = ("x_m", "v_mps", "current_setpoint_A")
#: integer-only quantities whose raw value is the value (no scale/offset)
_UNSCALED = ("seq", "status", "enable")
_INTEGER_ONLY = ("seq", "status", "enable", "watchdog_ms")

#: Modbus limits: FC3/FC4/FC23 read ≤ 125 registers, FC23 write ≤ 121 (FC16 ≤ 123).
MAX_READ_REGISTERS = 125
MAX_WRITE_REGISTERS = 121

_ENTRY_KEYS = ("table", "address", "type", "word_order", "scale", "offset")
_TOP_KEYS = ("unit_id", "word_order", "registers")
_F32_MAX = 3.4028234663852886e38


@dataclass(frozen=True)
class RegisterSpec:
    """Where and how one quantity is stored."""

    name: str
    table: str  #: "holding" | "input"
    address: int  #: 0-based PDU address of the first register
    type: str  #: key of :data:`DATA_TYPES`
    word_order: str = "big"  #: 32-bit only: "big" (high word first) | "little"
    scale: float = 1.0  #: physical = raw * scale + offset
    offset: float = 0.0

    @property
    def count(self) -> int:
        """Registers occupied (1 or 2)."""
        return DATA_TYPES[self.type][0]

    @property
    def end(self) -> int:
        """One past the last register."""
        return self.address + self.count

    @property
    def is_integer(self) -> bool:
        return DATA_TYPES[self.type][2]

    @property
    def raw_range(self) -> tuple[int, int] | None:
        """(min, max) raw value for integer types, None for float32."""
        n, _, integer, signed = DATA_TYPES[self.type]
        if not integer:
            return None
        bits = 16 * n
        return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)

    def to_mapping(self) -> dict[str, Any]:
        d: dict[str, Any] = {"table": self.table, "address": self.address, "type": self.type}
        if self.count == 2:
            d["word_order"] = self.word_order
        if self.scale != 1.0:
            d["scale"] = self.scale
        if self.offset != 0.0:
            d["offset"] = self.offset
        return d


class Block(NamedTuple):
    """A contiguous register range moved in one request."""

    table: str
    address: int
    count: int

    @property
    def end(self) -> int:
        return self.address + self.count


class ReadValues(NamedTuple):
    """Decoded read side. Counters raw (not unwrapped); absent quantities are None."""

    seq: int | None
    t_dev: int | float | None  #: raw for integer types (see RegisterMap.t_dev_modulus), else seconds
    x_m: float
    v_mps: float
    F_N: float | None
    status: int | None
    current_applied_A: float | None


class WriteValues(NamedTuple):
    """Decoded write side (device view). Absent quantities are None."""

    current_setpoint_A: float
    enable: bool | None  #: bit 0 of the enable register
    watchdog_ms: float | None
    clear_faults: bool = False  #: bit 1 of the enable register
    sync: bool = False  #: bit 2 of the enable register: answer after the next tick (device pacing)


# --------------------------------------------------------------------------
# default map (docs/registers.md shows it as a table; keep the two in sync)
DEFAULT_REGISTER_MAP: dict[str, Any] = {
    "unit_id": 1,
    "word_order": "big",
    "registers": {
        # read block: holding 0..12 (13 registers)
        "seq": {"table": "holding", "address": 0, "type": "uint32"},
        "t_dev": {"table": "holding", "address": 2, "type": "uint32", "scale": 1e-6},
        "x_m": {"table": "holding", "address": 4, "type": "float32"},
        "v_mps": {"table": "holding", "address": 6, "type": "float32"},
        "F_N": {"table": "holding", "address": 8, "type": "float32"},
        "current_applied_A": {"table": "holding", "address": 10, "type": "float32"},
        "status": {"table": "holding", "address": 12, "type": "uint16"},
        # write block: holding 16..19 (4 registers)
        "current_setpoint_A": {"table": "holding", "address": 16, "type": "float32"},
        "enable": {"table": "holding", "address": 18, "type": "uint16"},
        "watchdog_ms": {"table": "holding", "address": 19, "type": "uint16"},
    },
}

_DEFAULT_TYPES = {
    "seq": "uint32",
    "t_dev": "uint32",
    "status": "uint16",
    "enable": "uint16",
    "watchdog_ms": "uint16",
}


# --------------------------------------------------------------------------
# validation
def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_entry(
    name: str, data: Any, path: str, default_word_order: str, errors: list[str]
) -> RegisterSpec | None:
    if not isinstance(data, Mapping):
        errors.append(f"{path}: must be a mapping (table, address, type, ...), got {type(data).__name__}")
        return None
    n0 = len(errors)
    for key in data:
        if key not in _ENTRY_KEYS:
            errors.append(f"{path}.{key}: unknown key (allowed here: {', '.join(_ENTRY_KEYS)})")
    table = data.get("table", "holding")
    if table not in TABLES:
        errors.append(f"{path}.table: {table!r} not allowed (allowed: {', '.join(TABLES)})")
    elif name in WRITE_QUANTITIES and table != "holding":
        errors.append(f"{path}.table: {table!r} not allowed for a written quantity (allowed: holding)")
    if "address" not in data:
        errors.append(f"{path}.address: required")
        address = 0
    else:
        address = data["address"]
        if not _is_int(address) or not 0 <= address <= 0xFFFF:
            errors.append(f"{path}.address: {address!r} not allowed (must be an integer 0..65535)")
            address = 0
    dtype = data.get("type", _DEFAULT_TYPES.get(name, "float32"))
    if not isinstance(dtype, str) or dtype not in DATA_TYPES:
        errors.append(f"{path}.type: {dtype!r} not allowed (allowed: {', '.join(DATA_TYPES)})")
        dtype = "uint16"
    elif name in _INTEGER_ONLY and not DATA_TYPES[dtype][2]:
        allowed = ", ".join(t for t, d in DATA_TYPES.items() if d[2])
        errors.append(f"{path}.type: {dtype!r} not allowed for {name} (allowed: {allowed})")
    elif address + DATA_TYPES[dtype][0] - 1 > 0xFFFF:
        errors.append(f"{path}.address: {address} + {DATA_TYPES[dtype][0]} registers runs past 65535")
    word_order = data.get("word_order", default_word_order)
    if word_order not in WORD_ORDERS:
        errors.append(f"{path}.word_order: {word_order!r} not allowed (allowed: {', '.join(WORD_ORDERS)})")
    scale = data.get("scale", 1.0)
    offset = data.get("offset", 0.0)
    if not _is_num(scale) or not math.isfinite(scale) or scale == 0:
        errors.append(f"{path}.scale: {scale!r} not allowed (must be a finite non-zero number)")
    elif name in _UNSCALED and scale != 1:
        errors.append(f"{path}.scale: {scale!r} not allowed for {name} (must be 1)")
    if not _is_num(offset) or not math.isfinite(offset):
        errors.append(f"{path}.offset: {offset!r} not allowed (must be a finite number)")
    elif name in _UNSCALED and offset != 0:
        errors.append(f"{path}.offset: {offset!r} not allowed for {name} (must be 0)")
    if len(errors) != n0:
        return None
    return RegisterSpec(name, table, int(address), dtype, word_order, float(scale), float(offset))


def validate_register_map(data: Any, path: str = "") -> tuple["RegisterMap | None", list[str]]:
    """Check a ``register_map`` mapping; return (map or None, every error).

    Each error line starts with its key path (prefixed by ``path``), the
    shape :mod:`mrctl.config` collects. ``None``/empty → the default map.
    """
    p = (lambda k: f"{path}.{k}" if path else k)  # noqa: E731
    errors: list[str] = []
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        return None, [f"{path or 'register_map'}: must be a mapping, got {type(data).__name__}"]
    for key in data:
        if key not in _TOP_KEYS:
            errors.append(f"{p(str(key))}: unknown key (allowed here: {', '.join(_TOP_KEYS)})")
    unit_id = data.get("unit_id", DEFAULT_REGISTER_MAP["unit_id"])
    if not _is_int(unit_id) or not 0 <= unit_id <= 255:
        errors.append(f"{p('unit_id')}: {unit_id!r} not allowed (must be an integer 0..255)")
    word_order = data.get("word_order", DEFAULT_REGISTER_MAP["word_order"])
    if word_order not in WORD_ORDERS:
        errors.append(f"{p('word_order')}: {word_order!r} not allowed (allowed: {', '.join(WORD_ORDERS)})")
        word_order = "big"
    regs = data.get("registers")
    if regs is None:
        regs = DEFAULT_REGISTER_MAP["registers"]
    if not isinstance(regs, Mapping):
        errors.append(f"{p('registers')}: must be a mapping of quantity → register, got {type(regs).__name__}")
        return None, errors
    specs: dict[str, RegisterSpec] = {}
    for name, entry in regs.items():
        epath = p(f"registers.{name}")
        if name not in QUANTITIES:
            errors.append(f"{epath}: unknown quantity (allowed here: {', '.join(QUANTITIES)})")
            continue
        spec = _check_entry(name, entry, epath, word_order, errors)
        if spec is not None:
            specs[name] = spec
    for name in REQUIRED:
        if name not in regs:
            errors.append(f"{p(f'registers.{name}')}: required")
    if errors:
        return None, errors
    # overlaps, per table
    by_table: dict[str, list[RegisterSpec]] = {}
    for s in specs.values():
        by_table.setdefault(s.table, []).append(s)
    for items in by_table.values():
        items.sort(key=lambda s: s.address)
        for a, b in zip(items, items[1:]):
            if b.address < a.end:
                errors.append(
                    f"{p(f'registers.{b.name}.address')}: registers {b.address}..{b.end - 1} overlap "
                    f"registers.{a.name} ({a.address}..{a.end - 1}, {a.table})"
                )
    if errors:
        return None, errors
    # block limits
    for table, items in by_table.items():
        reads = [s for s in items if s.name in READ_QUANTITIES]
        if reads:
            span = reads[-1].end - reads[0].address
            if span > MAX_READ_REGISTERS:
                errors.append(
                    f"{p('registers')}: {table} read quantities span {span} registers "
                    f"({reads[0].address}..{reads[-1].end - 1}); one request reads at most {MAX_READ_REGISTERS}"
                )
    writes = sorted((s for s in specs.values() if s.name in WRITE_QUANTITIES), key=lambda s: s.address)
    for a, b in zip(writes, writes[1:]):
        if b.address != a.end:
            errors.append(
                f"{p(f'registers.{b.name}.address')}: written registers must be contiguous "
                f"(gap {a.end}..{b.address - 1} after registers.{a.name}); "
                f"one request writes every register between them"
            )
    if writes and writes[-1].end - writes[0].address > MAX_WRITE_REGISTERS:
        errors.append(f"{p('registers')}: written registers exceed {MAX_WRITE_REGISTERS}")
    if errors:
        return None, errors
    return RegisterMap(specs, int(unit_id), word_order), []


# --------------------------------------------------------------------------
# codec compilation
#
# Each map compiles four small functions from generated source (like
# collections.namedtuple once did): one struct call per block and one
# expression per quantity, no per-tick loops, dicts or temporary lists.
# decode_read costs ~1 µs instead of ~3.5 µs for the equivalent generic loop
# (measured; see docs/registers.md). The generated text is kept in
# ``RegisterMap.source`` for inspection.

_U32 = struct.Struct(">I")
_F32 = struct.Struct(">f")


def _f32_from_bits(u: int) -> float:
    return _F32.unpack(_U32.pack(u))[0]


def _bits_from_f32(x: float) -> int:
    return _U32.unpack(_F32.pack(x))[0]


def _s32(u: int) -> int:
    return u - 0x100000000 if u & 0x80000000 else u


class _BlockLayout:
    """Struct format for registers [start, start+count) and where each quantity sits in it."""

    def __init__(self, specs: Sequence[RegisterSpec], start: int, count: int) -> None:
        fmt = [">"]
        self.slots: dict[str, tuple[int, bool]] = {}  # name → (index of first value, split into 2 words?)
        pos = start
        idx = 0
        for s in sorted(specs, key=lambda s: s.address):
            if s.address > pos:
                fmt.append(f"{2 * (s.address - pos)}x")
            n, code, _, _ = DATA_TYPES[s.type]
            if n == 2 and s.word_order == "little":
                fmt.append("HH")
                self.slots[s.name] = (idx, True)
                idx += 2
            else:
                fmt.append(code)
                self.slots[s.name] = (idx, False)
                idx += 1
            pos = s.end
        if start + count > pos:
            fmt.append(f"{2 * (start + count - pos)}x")
        self.nvalues = idx
        self.struct = struct.Struct("".join(fmt))


def _raw_expr(spec: RegisterSpec, v: str, slot: tuple[int, bool]) -> str:
    """Expression for the raw value of ``spec`` in unpacked tuple ``v``."""
    i, split = slot
    if not split:
        return f"{v}[{i}]"
    word = f"({v}[{i + 1}] << 16 | {v}[{i}])"  # low word first
    code = DATA_TYPES[spec.type][1]
    if code == "f":
        return f"_f32_from_bits{word}"
    if code == "i":
        return f"_s32{word}"
    return word


def _float_writer(spec: RegisterSpec):
    """physical → raw float32, ValueError if non-finite or too large (host side)."""
    scale, offset, name = spec.scale, spec.offset, spec.name
    identity = scale == 1.0 and offset == 0.0

    def conv(x: float) -> float:
        v = x if identity else (x - offset) / scale
        if -_F32_MAX <= v <= _F32_MAX:
            return v
        raise ValueError(f"{name}: {x!r} is not finite or does not fit float32")

    return conv


def _int_writer(spec: RegisterSpec):
    """physical → raw integer, ValueError if non-finite or out of the type's range (host side)."""
    scale, offset, name, typ = spec.scale, spec.offset, spec.name, spec.type
    lo, hi = spec.raw_range  # type: ignore[misc]

    def conv(x: float) -> int:
        try:
            r = round((x - offset) / scale)
        except (ValueError, OverflowError, TypeError):
            raise ValueError(f"{name}: {x!r} is not finite") from None
        if lo <= r <= hi:
            return r
        raise ValueError(f"{name}: {x!r} does not fit {typ} (raw {r}, range {lo}..{hi})")

    return conv


def _device_converter(spec: RegisterSpec):
    """physical → raw for the device side: counters/status wrap, integers saturate, float32 overflows to ±inf."""
    scale, offset = spec.scale, spec.offset
    rr = spec.raw_range
    if rr is None:
        identity = scale == 1.0 and offset == 0.0

        def conv_f(x: float) -> float:
            v = x if identity else (x - offset) / scale
            if -_F32_MAX <= v <= _F32_MAX or v != v:
                return v
            return math.copysign(math.inf, v)

        return conv_f
    lo, hi = rr
    mod = hi - lo + 1
    if spec.name in ("seq", "t_dev", "status"):

        def conv_wrap(x: float) -> int:
            try:
                r = round((x - offset) / scale) % mod
            except (ValueError, OverflowError):
                return 0
            return r - mod if r > hi else r

        return conv_wrap

    def conv_sat(x: float) -> int:
        try:
            r = round((x - offset) / scale)
        except (ValueError, OverflowError):
            return 0 if x != x else (hi if x > 0 else lo)
        return lo if r < lo else hi if r > hi else r

    return conv_sat


def _compile(rmap: "RegisterMap") -> tuple[dict[str, Any], str]:
    """Generate and compile the map's codec functions."""
    ns: dict[str, Any] = {
        "_f32_from_bits": _f32_from_bits,
        "_bits_from_f32": _bits_from_f32,
        "_s32": _s32,
        "_RV": ReadValues,
        "_WV": WriteValues,
        "_round": round,
        "_struct_error": struct.error,
    }
    lines: list[str] = []
    specs = rmap.specs
    # -- host: decode_read(b0[, b1]) -> ReadValues ------------------------------
    args = [f"b{i}" for i in range(len(rmap.read_blocks))]
    lines.append(f"def decode_read({', '.join(args)}):")
    for i, lay in enumerate(rmap._read_layouts):
        ns[f"_unpack{i}"] = lay.struct.unpack
        lines.append(f"    v{i} = _unpack{i}(b{i})")
    exprs = []
    for name in READ_QUANTITIES:
        s = specs.get(name)
        if s is None:
            exprs.append("None")
            continue
        bi = next(i for i, lay in enumerate(rmap._read_layouts) if name in lay.slots)
        e = _raw_expr(s, f"v{bi}", rmap._read_layouts[bi].slots[name])
        signed = DATA_TYPES[s.type][3]
        if name in ("seq", "status") or (name == "t_dev" and s.is_integer):
            if signed:
                e = f"({e} & {(1 << (16 * s.count)) - 1})"
        elif s.scale == 1.0 and s.offset == 0.0:
            e = e if not s.is_integer else f"({e} + 0.0)"
        else:
            ns[f"_ks_{name}"] = s.scale
            ns[f"_ko_{name}"] = s.offset
            e = f"({e} * _ks_{name} + _ko_{name})" if s.offset != 0.0 else f"({e} * _ks_{name})"
        exprs.append(e)
    lines.append(f"    return _RV({', '.join(exprs)})")
    lines.append("")
    # -- host: encode_write_into(buf, offset, current_A, enable, watchdog_ms) ---
    wl = rmap._write_layout
    lines.append("def encode_write_into(buf, offset, current_A, enable=True, watchdog_ms=0.0):")
    vals = ["0"] * wl.nvalues
    for name, arg in (("current_setpoint_A", "current_A"), ("enable", "enable"), ("watchdog_ms", "watchdog_ms")):
        s = specs.get(name)
        if s is None:
            continue
        i, split = wl.slots[name]
        if name == "enable":
            raw = "(enable & 7)"  # bool, or SetpointFlag bits ENABLE | CLEAR_FAULTS | SYNC
        else:
            ns[f"_w_{name}"] = _int_writer(s) if s.is_integer else _float_writer(s)
            raw = f"_w_{name}({arg})"
        if split:
            lines.append(f"    r_{name} = {raw if s.is_integer else f'_bits_from_f32({raw})'} & 0xFFFFFFFF")
            vals[i] = f"r_{name} & 0xFFFF"
            vals[i + 1] = f"r_{name} >> 16"
        else:
            vals[i] = raw
    ns["_pack_into_w"] = wl.struct.pack_into
    lines.append(f"    _pack_into_w(buf, offset, {', '.join(vals)})")
    lines.append("")
    # -- device: encode_read(values in ReadValues/Sample order) -> tuple of block bytes
    # Two versions: encode_read_slow converts every field through its device
    # converter (wrap / saturate / inf); encode_read inlines the common cases
    # (float32 as is, unsigned counters masked) and falls back to the slow one
    # when a value needs care (pack overflow, NaN in an integer, a float seq).
    for fast in (False, True):
        lines.append("def encode_read(s):" if fast else "def encode_read_slow(s):")
        body: list[str] = []
        outs = []
        for bi, lay in enumerate(rmap._read_layouts):
            vals = ["0"] * lay.nvalues
            for name, (i, split) in lay.slots.items():
                sp = specs[name]
                ns[f"_d_{name}"] = _device_converter(sp)
                k = list(READ_QUANTITIES).index(name)
                raw = f"_d_{name}(s[{k}])"
                identity = sp.scale == 1.0 and sp.offset == 0.0
                if fast:
                    signed = DATA_TYPES[sp.type][3]
                    mask = (1 << (16 * sp.count)) - 1
                    if not sp.is_integer:
                        ns[f"_ks_{name}"] = sp.scale
                        ns[f"_ko_{name}"] = sp.offset
                        raw = f"s[{k}]" if identity else f"((s[{k}] - _ko_{name}) / _ks_{name})"
                    elif name in ("seq", "t_dev", "status") and not signed:
                        ns[f"_ks_{name}"] = sp.scale
                        ns[f"_ko_{name}"] = sp.offset
                        raw = f"(s[{k}] & {mask})" if identity else f"(_round((s[{k}] - _ko_{name}) / _ks_{name}) & {mask})"
                if split:
                    body.append(f"        r_{name} = {raw if sp.is_integer else f'_bits_from_f32({raw})'} & 0xFFFFFFFF")
                    vals[i] = f"r_{name} & 0xFFFF"
                    vals[i + 1] = f"r_{name} >> 16"
                else:
                    vals[i] = raw
            ns[f"_pack{bi}"] = lay.struct.pack
            outs.append(f"_pack{bi}({', '.join(vals)})")
        if fast:
            lines.append("    try:")
            lines.extend(body)
            lines.append(f"        return ({', '.join(outs)},)")
            lines.append("    except (OverflowError, TypeError, ValueError, _struct_error):")
            lines.append("        return encode_read_slow(s)")
        else:
            lines.extend(b[4:] for b in body)
            lines.append(f"    return ({', '.join(outs)},)")
        lines.append("")
    # -- device: decode_write(data) -> WriteValues ------------------------------
    lines.append("def decode_write(data):")
    ns["_unpack_w"] = wl.struct.unpack
    lines.append("    w = _unpack_w(data)")
    exprs = []
    clear = "False"
    sync = "False"
    for name in WRITE_QUANTITIES:
        s = specs.get(name)
        if s is None:
            exprs.append("None")
            continue
        e = _raw_expr(s, "w", wl.slots[name])
        if name == "enable":
            clear = f"(({e} & 2) != 0)"
            sync = f"(({e} & 4) != 0)"
            e = f"(({e} & 1) != 0)"
        else:
            ns[f"_ks_{name}"] = s.scale
            ns[f"_ko_{name}"] = s.offset
            e = f"({e} * _ks_{name} + _ko_{name})"
        exprs.append(e)
    lines.append(f"    return _WV({', '.join(exprs)}, {clear}, {sync})")
    src = "\n".join(lines) + "\n"
    exec(compile(src, f"<RegisterMap codec unit {rmap.unit_id}>", "exec"), ns)  # noqa: S102 - our own generated text
    return ns, src


class RegisterMap:
    """Validated register map plus its compiled block codecs. Immutable.

    Build with :meth:`from_mapping` or :func:`default_register_map`.

    Hot-path methods (compiled per map, see :func:`_compile`):

    * ``decode_read(*blocks) -> ReadValues`` — host; one bytes-like per
      :attr:`read_blocks`, exactly ``2*count`` bytes each (else ``struct.error``).
    * ``encode_write_into(buf, offset, current_A, enable=True, watchdog_ms=0.0)``
      — host; ``enable`` is a bool or the flag bits ENABLE (1) | CLEAR_FAULTS
      (2) of :class:`mrctl.io.protocol.SetpointFlag`; ``ValueError`` if a
      value is non-finite or does not fit its type.
    * ``encode_sample(sample) -> tuple[bytes, ...]`` — device; ``sample`` is a
      :class:`~mrctl.io.base.Sample` (or any 7-sequence in :class:`ReadValues`
      order). Counters and status wrap, integers saturate, float32 overflows
      to ±inf, NaN in an integer register becomes 0.
    * ``decode_write(data) -> WriteValues`` — device.
    """

    def __init__(self, specs: Mapping[str, RegisterSpec], unit_id: int = 1, word_order: str = "big") -> None:
        # Trusted constructor: validate_register_map checks first.
        self.specs: Mapping[str, RegisterSpec] = MappingProxyType(dict(specs))
        self.unit_id = int(unit_id)
        self.word_order = word_order
        reads = [s for s in self.specs.values() if s.name in READ_QUANTITIES]
        writes = sorted((s for s in self.specs.values() if s.name in WRITE_QUANTITIES), key=lambda s: s.address)
        blocks: list[Block] = []
        for table in TABLES:  # holding first: deterministic order
            items = [s for s in reads if s.table == table]
            if items:
                a = min(s.address for s in items)
                blocks.append(Block(table, a, max(s.end for s in items) - a))
        #: one read block per table used by read quantities (holding first)
        self.read_blocks: tuple[Block, ...] = tuple(blocks)
        #: the write block (holding, gap-free)
        self.write_block = Block("holding", writes[0].address, writes[-1].end - writes[0].address)
        #: True when a tick can be one FC23 (all reads in one holding block)
        self.fc23_capable = len(blocks) == 1 and blocks[0].table == "holding"
        self._read_layouts = [
            _BlockLayout([s for s in reads if s.table == b.table], b.address, b.count) for b in blocks
        ]
        self._write_layout = _BlockLayout(writes, self.write_block.address, self.write_block.count)
        ns, self.source = _compile(self)
        self.decode_read = ns["decode_read"]
        self.encode_write_into = ns["encode_write_into"]
        self.encode_sample = ns["encode_read"]
        self.decode_write = ns["decode_write"]

    # -- construction ------------------------------------------------------
    @classmethod
    def from_mapping(cls, data: Mapping[str, Any] | None) -> "RegisterMap":
        """Validate ``data`` (the YAML ``register_map`` section).

        Raises ValueError listing every problem ("; "-joined); the message
        starts with the first problem's key path, e.g. ``registers.x_m.type:
        'float64' not allowed (allowed: int16, uint16, int32, uint32, float32)``.
        """
        rmap, errors = validate_register_map(data)
        if errors:
            raise ValueError("; ".join(errors))
        assert rmap is not None
        return rmap

    def to_mapping(self) -> dict[str, Any]:
        """Plain mapping that :meth:`from_mapping` turns back into an equal map."""
        return {
            "unit_id": self.unit_id,
            "word_order": self.word_order,
            "registers": {n: s.to_mapping() for n, s in self.specs.items()},
        }

    def with_unit_id(self, unit_id: int) -> "RegisterMap":
        """Same registers, another unit id."""
        if isinstance(unit_id, bool) or not isinstance(unit_id, int) or not 0 <= unit_id <= 255:
            raise ValueError(f"unit_id must be an integer 0..255, got {unit_id!r}")
        return RegisterMap(self.specs, unit_id, self.word_order)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RegisterMap) and dict(self.specs) == dict(other.specs) and self.unit_id == other.unit_id

    __hash__ = None  # type: ignore[assignment]  # mutable-looking; compare, don't hash

    def __repr__(self) -> str:
        return f"RegisterMap({self.describe()})"

    # -- introspection -------------------------------------------------------
    def has(self, name: str) -> bool:
        return name in self.specs

    def counter_modulus(self, name: str) -> int | None:
        """2**bits for an integer ``seq``/``t_dev`` (the client unwraps it), else None."""
        s = self.specs.get(name)
        if s is None or not s.is_integer:
            return None
        return 1 << (16 * s.count)

    def t_dev_seconds(self, raw: int | float) -> float:
        """Scale a raw (possibly unwrapped) ``t_dev`` to seconds."""
        s = self.specs["t_dev"]
        return raw * s.scale + s.offset

    def describe(self) -> str:
        r = ", ".join(f"{b.table} {b.address}+{b.count}" for b in self.read_blocks)
        return (
            f"unit {self.unit_id}, read {r}, write holding "
            f"{self.write_block.address}+{self.write_block.count}"
            f"{', FC23-capable' if self.fc23_capable else ''}"
        )

    def spans(self) -> dict[str, tuple[int, int]]:
        """Addressable span [start, end) per table: every mapped register, gaps included."""
        out: dict[str, tuple[int, int]] = {}
        for s in self.specs.values():
            a, e = out.get(s.table, (s.address, s.end))
            out[s.table] = (min(a, s.address), max(e, s.end))
        return out

    def registers(self) -> list[RegisterSpec]:
        """Specs sorted by (table, address): the order of docs/registers.md."""
        return sorted(self.specs.values(), key=lambda s: (TABLES.index(s.table), s.address))

    # -- conveniences (not the hot path) ----------------------------------------
    def encode_write(self, current_A: float, enable: bool = True, watchdog_ms: float = 0.0) -> bytes:
        """Write block bytes (allocating form of ``encode_write_into``)."""
        buf = bytearray(2 * self.write_block.count)
        self.encode_write_into(buf, 0, current_A, enable, watchdog_ms)
        return bytes(buf)

    def encode_read(self, values: Any) -> tuple[bytes, ...]:
        """Device side: bytes of every read block; ``values`` = Sample, 7-sequence or mapping."""
        if isinstance(values, Mapping):
            values = tuple(values.get(n) for n in READ_QUANTITIES)
        return self.encode_sample(tuple(0 if v is None else v for v in values))


_DEFAULT_MAP: RegisterMap | None = None


def default_register_map() -> RegisterMap:
    """The map in docs/registers.md (hil_sim serves it; real devices may differ).

    Built once and shared: a RegisterMap is immutable.
    """
    global _DEFAULT_MAP
    if _DEFAULT_MAP is None:
        _DEFAULT_MAP = RegisterMap.from_mapping(DEFAULT_REGISTER_MAP)
    return _DEFAULT_MAP
