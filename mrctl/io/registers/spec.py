"""Register map entries: the quantities, where each may live, and the checks.

A ``register_map`` (the YAML section, docs/registers.md) says, for every
quantity the loop exchanges with a Modbus device, the register table
(holding / input), the start address (0-based PDU address, what goes on
the wire), the data type (int16, uint16, int32, uint32, float32), the word
order of 32-bit values and the linear scaling ``physical = raw * scale +
offset``. :func:`check_register_map` validates one on the schema engine's
terms (:mod:`mrctl.util.schema`: a field table per entry, unknown keys,
defaults, every error collected with its key path), then checks what spans
entries: overlaps, the read span per table (≤ 125 registers, gaps read too)
and the write block (contiguous, ≤ 121 registers, holding).

:class:`~mrctl.io.registers.map.RegisterMap` turns the checked entries into
blocks and a codec. Nothing here imports pymodbus or pyserial: the device
simulator, the client and the config checker share it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise
from typing import Any, Callable, Mapping, NamedTuple

from mrctl.io.registers.codec import DATA_TYPES, ReadValues, raw_range
from mrctl.util.schema import Custom, Str, validate_fields

__all__ = [
    "TABLES",
    "WORD_ORDERS",
    "READ_QUANTITIES",
    "WRITE_QUANTITIES",
    "QUANTITIES",
    "REQUIRED",
    "MAX_READ_REGISTERS",
    "MAX_WRITE_REGISTERS",
    "RegisterSpec",
    "Block",
    "DEFAULT_REGISTER_MAP",
    "ENTRY_KEYS",
    "TOP_KEYS",
    "check_register_map",
]

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
assert tuple(READ_QUANTITIES) == ReadValues._fields
#: Quantities written every tick (host → device).
WRITE_QUANTITIES: dict[str, str] = {
    "current_setpoint_A": "A",
    "enable": "flags",  # bit 0 ENABLE, bit 1 CLEAR_FAULTS, bit 2 SYNC (mrctl.io.protocol.SetpointFlag)
    "watchdog_ms": "ms",
}
QUANTITIES = {**READ_QUANTITIES, **WRITE_QUANTITIES}
#: v_mps may be absent: the link then reports NaN and sensing.velocity must be observer
REQUIRED = ("x_m", "current_setpoint_A")

#: Modbus limits: FC3/FC4/FC23 read ≤ 125 registers, FC23 write ≤ 121 (FC16 ≤ 123).
MAX_READ_REGISTERS = 125
MAX_WRITE_REGISTERS = 121


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
        return raw_range(self.type)

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


# --------------------------------------------------------------------------
# default map (docs/registers.md shows it as a table; a test keeps the two in sync)
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


# --------------------------------------------------------------------------
# validation, on the schema engine's terms: a field table per entry and one
# for the top level; what spans fields (overlaps, blocks) is checked after.
#: default types of counters and flags (others: float32)
_DEFAULT_TYPES = {"seq": "uint32", "t_dev": "uint32", "status": "uint16", "enable": "uint16", "watchdog_ms": "uint16"}
_UNSCALED = ("seq", "status", "enable")  #: the raw value is the value: scale 1, offset 0
_INTEGER_ONLY = ("seq", "status", "enable", "watchdog_ms")
_MISSING = object()
Check = Callable[[Any, str], tuple[Any, list[str]]]


def _number(what: str, ok: Callable[[Any], bool], only: Any = None, name: str = "") -> Check:
    """A number satisfying ``ok`` (and equal to ``only`` if given: the quantity forces it)."""

    def check(v: Any, path: str) -> tuple[Any, list[str]]:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not ok(v):
            return None, [f"{path}: {v!r} not allowed (must be {what})"]
        if only is not None and v != only:
            return None, [f"{path}: {v!r} not allowed for {name} (must be {only})"]
        return v, []

    return check


def _integer(lo: int, hi: int, required: bool = False) -> Check:
    number = _number(f"an integer {lo}..{hi}", lambda v: isinstance(v, int) and lo <= v <= hi)
    return lambda v, path: (None, [f"{path}: required"]) if required and v is _MISSING else number(v, path)


def _choice(choices: tuple[str, ...], allowed: tuple[str, ...], why: str) -> Check:
    """One of ``choices``, and of those only ``allowed`` for ``why`` (this quantity)."""

    def check(v: Any, path: str) -> tuple[Any, list[str]]:
        if v not in choices:
            return None, [f"{path}: {v!r} not allowed (allowed: {', '.join(choices)})"]
        if v not in allowed:
            return None, [f"{path}: {v!r} not allowed for {why} (allowed: {', '.join(allowed)})"]
        return v, []

    return check


def _entry_fields(name: str, word_order: str) -> dict[str, Any]:
    """The keys of one ``registers.<name>`` entry (``word_order``: the map's default)."""
    types = tuple(DATA_TYPES)
    if name in _INTEGER_ONLY:
        int_types = tuple(t for t in types if DATA_TYPES[t][2])
        dtype: Any = Custom(_choice(types, int_types, name), default=_DEFAULT_TYPES[name])
    else:
        dtype = Str(default=_DEFAULT_TYPES.get(name, "float32"), choices=types)
    if name in WRITE_QUANTITIES:
        table: Any = Custom(_choice(TABLES, ("holding",), "a written quantity"), default="holding")
    else:
        table = Str(default="holding", choices=TABLES)
    unscaled = name in _UNSCALED
    finite = math.isfinite
    return {
        "table": table,
        "address": Custom(_integer(0, 0xFFFF, required=True), default=_MISSING),
        "type": dtype,
        "word_order": Str(default=word_order, choices=WORD_ORDERS),
        "scale": Custom(_number("a finite non-zero number", lambda v: finite(v) and v != 0,
                                1 if unscaled else None, name), default=1.0),
        "offset": Custom(_number("a finite number", finite, 0 if unscaled else None, name), default=0.0),
    }


ENTRY_KEYS = tuple(_entry_fields("x_m", "big"))
TOP_FIELDS: dict[str, Any] = {
    "unit_id": Custom(_integer(0, 255), default=DEFAULT_REGISTER_MAP["unit_id"]),
    "word_order": Str(default=DEFAULT_REGISTER_MAP["word_order"], choices=WORD_ORDERS),
    "registers": Custom(lambda v, path: (v, []), default=None),
}
TOP_KEYS = tuple(TOP_FIELDS)


def _entry(name: str, data: Any, path: str, word_order: str, errors: list[str]) -> RegisterSpec | None:
    if not isinstance(data, Mapping):
        errors.append(f"{path}: must be a mapping ({', '.join(ENTRY_KEYS[:3])}, ...), got {type(data).__name__}")
        return None
    node, errs = validate_fields(_entry_fields(name, word_order), dict(data), path)
    if not errs and node.address + DATA_TYPES[node.type][0] - 1 > 0xFFFF:
        errs.append(f"{path}.address: {node.address} + {DATA_TYPES[node.type][0]} registers runs past 65535")
    errors += errs
    if errs:
        return None
    return RegisterSpec(name, node.table, node.address, node.type, node.word_order, float(node.scale),
                        float(node.offset))


def _layout_errors(specs: dict[str, RegisterSpec], p: Callable[[str], str]) -> list[str]:
    """Overlaps per table; then the block limits: reads per table, the contiguous write block."""
    by_table: dict[str, list[RegisterSpec]] = {}
    for s in sorted(specs.values(), key=lambda s: s.address):
        by_table.setdefault(s.table, []).append(s)
    errors = [
        f"{p(f'registers.{b.name}.address')}: registers {b.address}..{b.end - 1} overlap "
        f"registers.{a.name} ({a.address}..{a.end - 1}, {a.table})"
        for items in by_table.values() for a, b in pairwise(items) if b.address < a.end
    ]
    if errors:
        return errors
    for table, items in by_table.items():
        reads = [s for s in items if s.name in READ_QUANTITIES]
        if reads and reads[-1].end - reads[0].address > MAX_READ_REGISTERS:
            errors.append(
                f"{p('registers')}: {table} read quantities span {reads[-1].end - reads[0].address} registers "
                f"({reads[0].address}..{reads[-1].end - 1}); one request reads at most {MAX_READ_REGISTERS}"
            )
    writes = [s for s in sorted(specs.values(), key=lambda s: s.address) if s.name in WRITE_QUANTITIES]
    for a, b in pairwise(writes):
        if b.address != a.end:
            errors.append(
                f"{p(f'registers.{b.name}.address')}: written registers must be contiguous "
                f"(gap {a.end}..{b.address - 1} after registers.{a.name}); "
                f"one request writes every register between them"
            )
    if writes and writes[-1].end - writes[0].address > MAX_WRITE_REGISTERS:
        errors.append(f"{p('registers')}: written registers exceed {MAX_WRITE_REGISTERS}")
    return errors


def check_register_map(data: Any, path: str = "") -> tuple[tuple[dict[str, RegisterSpec], int, str] | None, list[str]]:
    """Check a ``register_map`` mapping; return ((specs, unit_id, word_order)
    or None, every error). Each error line starts with its key path
    (prefixed by ``path``). ``None``/empty → the default map's entries."""
    p = (lambda k: f"{path}.{k}" if path else k)  # noqa: E731
    if data is not None and not isinstance(data, Mapping):
        return None, [f"{path or 'register_map'}: must be a mapping, got {type(data).__name__}"]
    top, errors = validate_fields(TOP_FIELDS, dict(data or {}), path)
    regs = top.registers if top.registers is not None else DEFAULT_REGISTER_MAP["registers"]
    if not isinstance(regs, Mapping):
        errors.append(f"{p('registers')}: must be a mapping of quantity → register, got {type(regs).__name__}")
        return None, errors
    specs: dict[str, RegisterSpec] = {}
    for name, entry in regs.items():
        if name not in QUANTITIES:
            errors.append(f"{p(f'registers.{name}')}: unknown quantity (allowed here: {', '.join(QUANTITIES)})")
            continue
        spec = _entry(name, entry, p(f"registers.{name}"), top.word_order or "big", errors)
        if spec is not None:
            specs[name] = spec
    errors += [f"{p(f'registers.{name}')}: required" for name in REQUIRED if name not in regs]
    if not errors:
        errors = _layout_errors(specs, p)
    if errors:
        return None, errors
    return (specs, int(top.unit_id), top.word_order), []
