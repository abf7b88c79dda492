"""RegisterMap: checked entries → the blocks of one tick and their codec.

From its entries (:mod:`mrctl.io.registers.spec`) the map computes the
*transaction plan* for one tick:

* one read block per table (the span covering every read quantity of that
  table, gaps included), holding first, and
* one write block (the write quantities, gap-free, holding).

If all read quantities are holding registers (one read block), a tick is a
single FC23 *read/write multiple registers* transaction; otherwise it is an
FC16 write plus one FC3/FC4 read per block. The bytes of the blocks are
:mod:`mrctl.io.registers.codec`'s.

Counters (``seq``, ``t_dev``) are *raw* in ``ReadValues``: the client
unwraps them (a 16-bit seq wraps every 65 s at 1 kHz) before scaling, which
is why :class:`RegisterMap` exposes their modulus.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any, Mapping

from mrctl.io.registers.codec import BlockLayout, RegisterCodec
from mrctl.io.registers.spec import (
    DEFAULT_REGISTER_MAP,
    READ_QUANTITIES,
    TABLES,
    WRITE_QUANTITIES,
    Block,
    RegisterSpec,
    check_register_map,
)

__all__ = ["RegisterMap", "default_register_map", "validate_register_map"]


def validate_register_map(data: Any, path: str = "") -> tuple["RegisterMap | None", list[str]]:
    """Check a ``register_map`` mapping; return (map or None, every error).

    Each error line starts with its key path (prefixed by ``path``), the
    shape :mod:`mrctl.config` collects. ``None``/empty → the default map.
    """
    checked, errors = check_register_map(data, path)
    if checked is None:
        return None, errors
    return RegisterMap(*checked), []


class RegisterMap:
    """Validated register map plus its block codec. Immutable.

    Build with :meth:`from_mapping` or :func:`default_register_map`.

    Hot-path methods (:class:`~mrctl.io.registers.codec.RegisterCodec`'s):

    * ``decode_read(*blocks) -> ReadValues`` — host; one bytes-like per
      :attr:`read_blocks`, exactly ``2*count`` bytes each (else ``struct.error``).
    * ``encode_write_into(buf, offset, current_A, enable=True, watchdog_ms=0.0)``
      — host; ``enable`` is a bool or the flag bits ENABLE (1) | CLEAR_FAULTS
      (2) | SYNC (4) of :class:`mrctl.io.protocol.SetpointFlag`; ``ValueError``
      if a value is non-finite or does not fit its type.
    * ``encode_sample(sample) -> tuple[bytes, ...]`` — device; ``sample`` is a
      :class:`~mrctl.io.base.Sample` (or any 7-sequence in ``ReadValues``
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
        codec = RegisterCodec(
            dict(self.specs),
            [BlockLayout([s for s in reads if s.table == b.table], b.address, b.count) for b in blocks],
            BlockLayout(writes, self.write_block.address, self.write_block.count),
        )
        self.decode_read = codec.decode_read
        self.encode_write_into = codec.encode_write_into
        self.encode_sample = codec.encode_sample
        self.decode_write = codec.decode_write

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
