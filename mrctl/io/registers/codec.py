"""Register block codec: the bytes of a map's blocks ↔ values, table-driven.

One :class:`struct.Struct` per block covers every register of it (gaps as
pad bytes), so a block is one ``unpack``/``pack_into`` per tick; a small
table per map then says, for each quantity, which unpacked value it is and
what to do with it (nothing, scale, mask, join two little-order words).
For the default map every read quantity is taken as unpacked, so decoding
the sample block is ``unpack`` + one ``itemgetter``.

Why tables and not code generated per map with ``exec`` (which saves
about a microsecond per tick, bench/register_codec.py, figures in
docs/registers.md): against a 1000 µs period that does not matter, and
plain tables are easier to read, test and debug.

Host side: :meth:`RegisterCodec.decode_read` (sample blocks → ReadValues) and
:meth:`RegisterCodec.encode_write_into` (setpoint → write block); device side
(hil_sim): :meth:`RegisterCodec.encode_sample` and :meth:`RegisterCodec.decode_write`.
"""

from __future__ import annotations

import math
import struct
from operator import itemgetter
from typing import Any, Callable, NamedTuple, Sequence

__all__ = ["DATA_TYPES", "ReadValues", "WriteValues", "BlockLayout", "RegisterCodec", "raw_range"]

#: data type → (registers, struct code big-endian, integer?, signed?)
DATA_TYPES: dict[str, tuple[int, str, bool, bool]] = {
    "int16": (1, "h", True, True),
    "uint16": (1, "H", True, False),
    "int32": (2, "i", True, True),
    "uint32": (2, "I", True, False),
    "float32": (2, "f", False, True),
}
_F32_MAX = 3.4028234663852886e38
_U32 = struct.Struct(">I")
_F32 = struct.Struct(">f")
#: counters and status: raw on the host (the link unwraps), wrapped on the device
_COUNTERS = ("seq", "t_dev", "status")
#: the write quantities in the order of encode_write_into's arguments and WriteValues
_WRITES = ("current_setpoint_A", "enable", "watchdog_ms")


class ReadValues(NamedTuple):
    """Decoded read side. Counters raw (not unwrapped); absent quantities are None."""

    seq: int | None
    t_dev: int | float | None  #: raw for integer types (see RegisterMap.counter_modulus), else seconds
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


def raw_range(dtype: str) -> tuple[int, int] | None:
    """(min, max) raw value of an integer type, None for float32."""
    n, _, integer, signed = DATA_TYPES[dtype]
    if not integer:
        return None
    bits = 16 * n
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)


class BlockLayout:
    """Struct for registers [start, start+count) and where each quantity sits in it.

    ``slots[name] = (index of its first unpacked value, split)``: a 32-bit
    value in little word order is packed as two 16-bit words (``split``).
    """

    def __init__(self, specs: Sequence[Any], start: int, count: int) -> None:
        fmt = [">"]
        self.slots: dict[str, tuple[int, bool]] = {}
        pos = start
        idx = 0
        for s in sorted(specs, key=lambda s: s.address):
            if s.address > pos:
                fmt.append(f"{2 * (s.address - pos)}x")
            n, code, _, _ = DATA_TYPES[s.type]
            split = n == 2 and s.word_order == "little"
            fmt.append("HH" if split else code)
            self.slots[s.name] = (idx, split)
            idx += 2 if split else 1
            pos = s.end
        if start + count > pos:
            fmt.append(f"{2 * (start + count - pos)}x")
        self.nvalues = idx
        self.struct = struct.Struct("".join(fmt))


# --------------------------------------------------------------------------
# per-quantity conversions
def _joined(dtype: str) -> Callable[[int, int], Any]:
    """(low word, high word) → raw value of a split 32-bit register pair."""
    code = DATA_TYPES[dtype][1]
    if code == "f":
        return lambda lo, hi: _F32.unpack(_U32.pack(hi << 16 | lo))[0]
    if code == "i":
        return lambda lo, hi: (hi << 16 | lo) - ((hi & 0x8000) << 17)
    return lambda lo, hi: hi << 16 | lo


def _words(dtype: str) -> Callable[[Any], int]:
    """raw value → the unsigned 32-bit pattern of a split register pair."""
    if DATA_TYPES[dtype][1] == "f":
        return lambda raw: _U32.unpack(_F32.pack(raw))[0]
    return lambda raw: raw & 0xFFFFFFFF


def _physical(spec: Any) -> Callable[[Any], Any] | None:
    """raw → physical on the reading side; None = the raw value as it is."""
    integer, signed = DATA_TYPES[spec.type][2:]
    if spec.name in ("seq", "status") or (spec.name == "t_dev" and integer):
        if signed:
            mask = (1 << (16 * DATA_TYPES[spec.type][0])) - 1
            return lambda r: r & mask
        return None
    k, o = spec.scale, spec.offset
    if k == 1.0 and o == 0.0:
        return (lambda r: r + 0.0) if integer else None
    if o == 0.0:
        return lambda r: r * k
    return lambda r: r * k + o


def host_writer(spec: Any) -> Callable[[float], Any]:
    """physical → raw for the host's write: ValueError if not finite or out of range."""
    k, o, name, typ = spec.scale, spec.offset, spec.name, spec.type
    rr = raw_range(typ)
    if rr is None:
        identity = k == 1.0 and o == 0.0

        def conv_f(x: float) -> float:
            v = x if identity else (x - o) / k
            if -_F32_MAX <= v <= _F32_MAX:
                return v
            raise ValueError(f"{name}: {x!r} is not finite or does not fit float32")

        return conv_f
    lo, hi = rr

    def conv_i(x: float) -> int:
        try:
            r = round((x - o) / k)
        except (ValueError, OverflowError, TypeError):
            raise ValueError(f"{name}: {x!r} is not finite") from None
        if lo <= r <= hi:
            return r
        raise ValueError(f"{name}: {x!r} does not fit {typ} (raw {r}, range {lo}..{hi})")

    return conv_i


def device_writer(spec: Any) -> Callable[[Any], Any]:
    """physical → raw for the device's sample: counters and status wrap,
    integers saturate (NaN → 0), float32 overflows to ±inf. Never raises on numbers."""
    k, o = spec.scale, spec.offset
    rr = raw_range(spec.type)
    if rr is None:
        identity = k == 1.0 and o == 0.0

        def conv_f(x: float) -> float:
            v = x if identity else (x - o) / k
            if -_F32_MAX <= v <= _F32_MAX or v != v:
                return v
            return math.copysign(math.inf, v)

        return conv_f
    lo, hi = rr
    mod = hi - lo + 1
    if spec.name in _COUNTERS:

        def conv_wrap(x: float) -> int:
            try:
                r = round((x - o) / k) % mod
            except (ValueError, OverflowError):
                return 0
            return r - mod if r > hi else r

        return conv_wrap

    def conv_sat(x: float) -> int:
        try:
            r = round((x - o) / k)
        except (ValueError, OverflowError):
            return 0 if x != x else (hi if x > 0 else lo)
        return lo if r < lo else hi if r > hi else r

    return conv_sat


# --------------------------------------------------------------------------
class RegisterCodec:
    """The four block conversions of one register map.

    ``specs``: name → spec (``name, address, type, word_order, scale,
    offset, end``); ``read_layouts``: one :class:`BlockLayout` per read block,
    in the order the blocks are passed; ``write_layout``: the write block.
    """

    def __init__(self, specs: dict[str, Any], read_layouts: Sequence[BlockLayout], write_layout: BlockLayout) -> None:
        # host read: unpack every block, concatenate, pick ReadValues' order, fix up some
        self._unpackers = tuple(lay.struct.unpack for lay in read_layouts)
        where: dict[str, tuple[int, bool]] = {}  # name → (index in the concatenated values, split)
        off = 0
        for lay in read_layouts:
            where.update({n: (off + i, sp) for n, (i, sp) in lay.slots.items()})
            off += lay.nvalues
        fixes: list[tuple[int, Callable[[tuple], Any]]] = []
        for k, name in enumerate(ReadValues._fields):
            if name not in specs:
                fixes.append((k, lambda v: None))
            elif where[name][1] or _physical(specs[name]) is not None:
                fixes.append((k, _read_fix(specs[name], *where[name])))
        self._pick = itemgetter(*(where[n][0] if n in specs else 0 for n in ReadValues._fields))
        self._fixes = tuple(fixes)
        # host write: (argument index, slot, split words or None, converter); args = (current, enable, watchdog)
        self._wlayout = write_layout
        wplan = []
        for a, n in enumerate(_WRITES):
            if n in specs:
                i, sp = write_layout.slots[n]
                conv = (lambda e: e & 7) if n == "enable" else host_writer(specs[n])  # enable: bool or flag bits
                wplan.append((a, i, _words(specs[n].type) if sp else None, conv))
        self._wplan = tuple(wplan)
        # device write side: per read block (pack, values, fast tier or None, slow plan); see encode_sample
        self._splan = tuple(
            (lay.struct.pack, lay.nvalues, _fast_tier(specs, lay), tuple(
                (ReadValues._fields.index(n), i, _words(specs[n].type) if sp else None, device_writer(specs[n]))
                for n, (i, sp) in lay.slots.items()))
            for lay in read_layouts
        )
        # device read side: per write quantity (slot, join or None, scale, offset), None if absent
        self._wdec = tuple(
            None if n not in specs else (
                write_layout.slots[n][0], _joined(specs[n].type) if write_layout.slots[n][1] else None,
                None if n == "enable" else specs[n].scale, specs[n].offset)
            for n in _WRITES
        )

    # -- host ------------------------------------------------------------------
    def decode_read(self, *blocks: bytes | bytearray | memoryview) -> ReadValues:
        """One bytes-like per read block, exactly ``2*count`` bytes each (else ``struct.error``)."""
        unpackers = self._unpackers
        if len(blocks) == 1 == len(unpackers):
            v = unpackers[0](blocks[0])
        elif len(blocks) == len(unpackers):
            v = ()
            for unpack, b in zip(unpackers, blocks, strict=True):
                v += unpack(b)
        else:
            raise TypeError(f"decode_read takes {len(unpackers)} blocks, got {len(blocks)}")
        if not self._fixes:
            return tuple.__new__(ReadValues, self._pick(v))
        out = list(self._pick(v))
        for k, fix in self._fixes:
            out[k] = fix(v)
        return tuple.__new__(ReadValues, out)

    def encode_write_into(self, buf: bytearray, offset: int, current_A: float, enable: bool | int = True,
                          watchdog_ms: float = 0.0) -> None:
        """The write block into ``buf`` at ``offset``. ``enable``: a bool or the
        flag bits ENABLE (1) | CLEAR_FAULTS (2) | SYNC (4). ValueError if a
        value is non-finite or does not fit its type."""
        lay = self._wlayout
        args = (current_A, enable, watchdog_ms)
        vals: list[Any] = [0] * lay.nvalues
        for a, i, words, conv in self._wplan:
            raw = conv(args[a])
            if words is None:
                vals[i] = raw
            else:
                r = words(raw)
                vals[i] = r & 0xFFFF
                vals[i + 1] = r >> 16
        lay.struct.pack_into(buf, offset, *vals)

    # -- device ----------------------------------------------------------------
    def encode_sample(self, s: Sequence[Any]) -> tuple[bytes, ...]:
        """Bytes of every read block from a Sample (or any 7-sequence in ReadValues order).

        Two tiers per block: the fast one takes the values as they are
        (float32 and unsigned counters) or through a plain conversion and
        packs them; if that raises (overflow, NaN or a float in an integer
        register, a counter out of range), every value goes through its
        device converter (wrap, saturate, ±inf), which never raises."""
        out = []
        for pack, n, fast, plan in self._splan:
            if fast is not None:
                pick, fixes = fast
                try:
                    vals = list(pick(s))
                    for j, fix in fixes:
                        vals[j] = fix(vals[j])
                    out.append(pack(*vals))
                    continue
                except _PACK_ERRORS:
                    pass
            vals = [0] * n
            for k, i, words, conv in plan:
                raw = conv(s[k])
                if words is None:
                    vals[i] = raw
                else:
                    r = words(raw)
                    vals[i] = r & 0xFFFF
                    vals[i + 1] = r >> 16
            out.append(pack(*vals))
        return tuple(out)

    def decode_write(self, data: bytes | bytearray | memoryview) -> WriteValues:
        """The write block as the device reads it."""
        w = self._wlayout.struct.unpack(data)
        vals: list[Any] = []
        for f in self._wdec:
            if f is None:
                vals.append(None)
                continue
            i, join, k, o = f
            raw = w[i] if join is None else join(w[i], w[i + 1])
            vals.append(raw if k is None else raw * k + o)
        cur, en, wd = vals
        if en is None:
            return WriteValues(cur, None, wd)
        return WriteValues(cur, (en & 1) != 0, wd, (en & 2) != 0, (en & 4) != 0)


_PACK_ERRORS = (OverflowError, TypeError, ValueError, struct.error)


def _fast_tier(specs: dict[str, Any], lay: BlockLayout) -> tuple[Callable[[Any], Any], tuple] | None:
    """The fast tier of encode_sample for one block: (pick the values in slot
    order, ((slot, conversion), ...)), or None if a value is split in words."""
    if any(sp for _, sp in lay.slots.values()):
        return None
    order = sorted(lay.slots, key=lambda n: lay.slots[n][0])
    ks = [ReadValues._fields.index(n) for n in order]
    pick = itemgetter(*ks) if len(ks) > 1 else (lambda s, k=ks[0]: (s[k],))
    fixes = []
    for j, n in enumerate(order):
        sp = specs[n]
        k, o = sp.scale, sp.offset
        identity = k == 1.0 and o == 0.0
        if not sp.is_integer:
            if not identity:
                fixes.append((j, lambda x, k=k, o=o: (x - o) / k))
        elif n in _COUNTERS and not DATA_TYPES[sp.type][3]:
            if not identity:
                mask = (1 << (16 * DATA_TYPES[sp.type][0])) - 1
                fixes.append((j, lambda x, k=k, o=o, mask=mask: round((x - o) / k) & mask))
        else:
            fixes.append((j, device_writer(sp)))
    return pick, tuple(fixes)


def _read_fix(s: Any, i: int, split: bool) -> Callable[[tuple], Any]:
    """values → the physical value of quantity ``s`` at value index ``i``."""
    phys = _physical(s) or (lambda r: r)
    if split:
        join = _joined(s.type)
        return lambda v: phys(join(v[i], v[i + 1]))
    return lambda v: phys(v[i])
