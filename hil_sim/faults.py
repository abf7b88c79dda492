"""Scheduled fault injection for the simulated bench (docs/hil_sim.md, "Faults").

A fault is a *kind*, a start time ``at_s`` and a length ``for_s`` on the
**device's own tick time base**: it is active for device ticks
``k0 = round(at_s·rate) ≤ k < k0 + max(1, round(for_s·rate))``. Because the
window is in ticks, not wall-clock time, a run is reproducible: the same
schedule hits the same device ticks whatever the host's scheduling did, and
the truth log's ``fault`` column (the bits below) says exactly which ticks
were affected.

Faults come from the bench YAML::

    faults:
      - {kind: nan, at_s: 2.0, for_s: 0.3}
      - {kind: delay_replies, at_s: 3.0, for_s: 0.3, delay_s: 0.003}

or from the command line, repeatable: ``--fault KIND@AT_S+FOR_S[,param=value]``
(``--fault drop_replies@2+0.05``, ``--fault delay_replies@3+0.3,delay_s=0.0005``).

Who applies what: the clock thread computes the active bits once per tick
(:meth:`FaultSchedule.active`) and publishes them in
:class:`~hil_sim.state.DeviceState`; *sample* faults (``stale_seq``, ``nan``,
``out_of_range``) and ``ignore_setpoints`` are applied by the clock to the
sample it publishes / the current it applies; *link* faults (the rest) are
applied by the protocol servers when they answer, from the bits of the
latest tick.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any, Iterable

__all__ = [
    "FaultBit",
    "FAULT_KINDS",
    "FaultSpec",
    "FaultSchedule",
    "LINK_FAULTS",
    "SAMPLE_FAULTS",
    "check_fault_list",
    "check_transport",
    "parse_fault_arg",
]


class FaultBit(enum.IntFlag):
    """One bit per fault kind: the truth log's ``fault`` column."""

    DROP_REPLIES = 1 << 0
    DELAY_REPLIES = 1 << 1
    CORRUPT_CRC = 1 << 2
    GARBAGE = 1 << 3
    STALE_SEQ = 1 << 4
    NAN = 1 << 5
    OUT_OF_RANGE = 1 << 6
    MODBUS_EXCEPTION = 1 << 7
    DISCONNECT = 1 << 8
    IGNORE_WRITES = 1 << 9
    IGNORE_SETPOINTS = 1 << 10
    ESTOP = 1 << 11


@dataclass(frozen=True)
class _Param:
    kind: str  # "number" | "integer" | "choice"
    default: Any  # None = required
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] = ()
    doc: str = ""


@dataclass(frozen=True)
class FaultKind:
    name: str
    bit: FaultBit
    doc: str
    params: dict[str, _Param] = field(default_factory=dict)
    transports: tuple[str, ...] = ("serial", "modbus-tcp", "modbus-rtu")


_ALL = ("serial", "modbus-tcp", "modbus-rtu")
_MODBUS = ("modbus-tcp", "modbus-rtu")

#: name → kind: the one table (validation, CLI, docs).
FAULT_KINDS: dict[str, FaultKind] = {k.name: k for k in (
    FaultKind("drop_replies", FaultBit.DROP_REPLIES,
              "requests are received and setpoints applied, but no reply is sent (replies lost on the way back)"),
    FaultKind("delay_replies", FaultBit.DELAY_REPLIES,
              "every reply is sent delay_s after its request (FIFO); setpoints are applied at once",
              {"delay_s": _Param("number", None, 0.0, 1.0, doc="reply delay (s), > 0")}),
    FaultKind("corrupt_crc", FaultBit.CORRUPT_CRC,
              "replies go out with a broken check: serial/RTU CRC flipped, Modbus TCP MBAP length set to 0"),
    FaultKind("garbage", FaultBit.GARBAGE,
              "n_bytes seeded random bytes are sent before every reply",
              {"n_bytes": _Param("integer", 16, 1, 256, doc="junk bytes per reply")}),
    FaultKind("stale_seq", FaultBit.STALE_SEQ,
              "the published sample seq is frozen at its value before the fault (data and t_dev still advance)"),
    FaultKind("nan", FaultBit.NAN,
              "the published x (or v) is NaN",
              {"field": _Param("choice", "x", choices=("x", "v"), doc="which channel is NaN")}),
    FaultKind("out_of_range", FaultBit.OUT_OF_RANGE,
              "the published x is x_m (far outside any sane range)",
              {"x_m": _Param("number", 1.0, -1e6, 1e6, doc="displacement reported (m)")}),
    FaultKind("modbus_exception", FaultBit.MODBUS_EXCEPTION,
              "every request is answered with exception 4 SLAVE_DEVICE_FAILURE; writes are not applied",
              transports=_MODBUS),
    FaultKind("disconnect", FaultBit.DISCONNECT,
              "the link goes away for for_s: TCP clients are closed and new connections refused; "
              "serial/RTU: the pty is closed (host sees EIO) and its symlink removed, then a new pty is "
              "linked at the same path"),
    FaultKind("ignore_writes", FaultBit.IGNORE_WRITES,
              "the device stops answering at all: requests are read and discarded, nothing applied "
              "(driver loss as the host sees it); the device watchdog applies 0 A"),
    FaultKind("ignore_setpoints", FaultBit.IGNORE_SETPOINTS,
              "replies as usual and the watchdog is fed, but the driver keeps the current it had when "
              "the fault began (truth I_cmd frozen)"),
    FaultKind("estop", FaultBit.ESTOP,
              "the E-stop circuit is open for for_s: the hard-wired chain removes the driver's power (0 A) "
              "and the E-stop input reads active. A device with its own E-stop input (serial, Modbus) reports "
              "ESTOP in its status and holds 0 A, latched until a CLEAR_FAULTS after the input closed; the "
              "emulated T7 shows the input on its E-stop DIO (labjack_t7.estop), the latch is mrctl's"),
)}

#: faults the protocol servers apply (the rest are applied by the clock)
LINK_FAULTS = (FaultBit.DROP_REPLIES | FaultBit.DELAY_REPLIES | FaultBit.CORRUPT_CRC | FaultBit.GARBAGE
               | FaultBit.MODBUS_EXCEPTION | FaultBit.DISCONNECT | FaultBit.IGNORE_WRITES)
#: faults that make the published sample bad
SAMPLE_FAULTS = FaultBit.STALE_SEQ | FaultBit.NAN | FaultBit.OUT_OF_RANGE

_BASE_KEYS = ("kind", "at_s", "for_s")


@dataclass(frozen=True)
class FaultSpec:
    """One scheduled fault (validated)."""

    kind: str
    at_s: float
    for_s: float
    params: tuple[tuple[str, Any], ...] = ()
    source: str = ""  #: where it came from (key path or --fault text), for messages

    @property
    def bit(self) -> int:
        return int(FAULT_KINDS[self.kind].bit)

    def param(self, name: str) -> Any:
        for k, v in self.params:
            if k == name:
                return v
        return FAULT_KINDS[self.kind].params[name].default

    def window(self, rate_hz: float) -> tuple[int, int]:
        """[k0, k1): the device ticks during which the fault is active."""
        k0 = int(round(self.at_s * rate_hz))
        return k0, k0 + max(1, int(round(self.for_s * rate_hz)))

    def as_dict(self, rate_hz: float | None = None) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind, "at_s": self.at_s, "for_s": self.for_s, "bit": self.bit}
        d.update({k: self.param(k) for k in FAULT_KINDS[self.kind].params})
        if rate_hz:
            d["k0"], d["k1"] = self.window(rate_hz)
        return d

    def text(self) -> str:
        """The CLI form (``kind@at+for[,p=v]``)."""
        extra = "".join(f",{k}={v}" for k, v in self.params)
        return f"{self.kind}@{self.at_s:g}+{self.for_s:g}{extra}"


# --------------------------------------------------------------------------
# validation (YAML and CLI share it; every error starts with its key path)
def _num(value: Any, path: str, lo: float | None, hi: float | None, *, integer: bool = False,
         lo_exclusive: bool = False) -> tuple[Any, list[str]]:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None, [f"{path}: must be a number, got {value!r}"]
    if not math.isfinite(float(value)):
        return None, [f"{path}: must be finite, got {value!r}"]
    if integer and not float(value).is_integer():
        return None, [f"{path}: must be a whole number, got {value!r}"]
    v = int(value) if integer else float(value)
    if lo is not None and (v <= lo if lo_exclusive else v < lo):
        return None, [f"{path}: {value!r} out of range (must be {'>' if lo_exclusive else '>='} {lo:g})"]
    if hi is not None and v > hi:
        return None, [f"{path}: {value!r} out of range (must be <= {hi:g})"]
    return v, []


def _check_one(item: Any, path: str) -> tuple[FaultSpec | None, list[str]]:
    if not isinstance(item, dict):
        return None, [f"{path}: must be a mapping {{kind, at_s, for_s, ...}}, got {item!r}"]
    errors: list[str] = []
    kind = item.get("kind")
    if "kind" not in item:
        return None, [f"{path}.kind: missing required key (one of {', '.join(FAULT_KINDS)})"]
    if not isinstance(kind, str) or kind not in FAULT_KINDS:
        return None, [f"{path}.kind: {kind!r} not allowed (allowed: {', '.join(FAULT_KINDS)})"]
    fk = FAULT_KINDS[kind]
    for key in item:
        if key not in _BASE_KEYS and key not in fk.params:
            allowed = ", ".join((*_BASE_KEYS, *fk.params))
            errors.append(f"{path}.{key}: unknown key for kind {kind} (allowed here: {allowed})")
    vals: dict[str, float] = {}
    for key, lo, excl in (("at_s", 0.0, False), ("for_s", 0.0, True)):
        if key not in item:
            errors.append(f"{path}.{key}: missing required key")
            continue
        v, errs = _num(item[key], f"{path}.{key}", lo, 7 * 86400.0, lo_exclusive=excl)
        errors += errs
        if v is not None:
            vals[key] = v
    params: list[tuple[str, Any]] = []
    for name, p in fk.params.items():
        ppath = f"{path}.{name}"
        if name not in item:
            if p.default is None:
                errors.append(f"{ppath}: missing required key ({p.doc})")
            continue
        value = item[name]
        if p.kind == "choice":
            if value not in p.choices:
                errors.append(f"{ppath}: {value!r} not allowed (allowed: {', '.join(p.choices)})")
                continue
            v: Any = value
        else:
            v, errs = _num(value, ppath, p.lo, p.hi, integer=p.kind == "integer",
                           lo_exclusive=(name == "delay_s"))
            if errs:
                errors += errs
                continue
        params.append((name, v))
    if errors:
        return None, errors
    return FaultSpec(kind, vals["at_s"], vals["for_s"], tuple(params), path), []


def check_fault_list(value: Any, path: str) -> tuple[list[FaultSpec] | None, list[str]]:
    """Schema check for the bench YAML's ``faults`` key (a ``mrctl.config.Custom``)."""
    if value is None:
        return [], []
    if not isinstance(value, list):
        return None, [f"{path}: must be a list of {{kind, at_s, for_s, ...}} mappings, got {value!r}"]
    out: list[FaultSpec] = []
    errors: list[str] = []
    for i, item in enumerate(value):
        spec, errs = _check_one(item, f"{path}[{i}]")
        errors += errs
        if spec is not None:
            out.append(spec)
    return (out if not errors else None), errors


def parse_fault_arg(text: str, index: int = 0) -> tuple[FaultSpec | None, list[str]]:
    """``KIND@AT_S+FOR_S[,param=value...]`` → spec; errors start with ``--fault[index]``."""
    path = f"--fault[{index}]"
    head, *extra = text.strip().split(",")
    kind, at_sep, when = head.partition("@")
    at_txt, plus, for_txt = when.partition("+")
    if not at_sep or not plus or not kind:
        return None, [f"{path}: {text!r}: expected KIND@AT_S+FOR_S[,param=value...] "
                      f"(e.g. drop_replies@2.0+0.05)"]
    item: dict[str, Any] = {"kind": kind.strip()}
    errors: list[str] = []
    for key, txt in (("at_s", at_txt), ("for_s", for_txt)):
        try:
            item[key] = float(txt)
        except ValueError:
            errors.append(f"{path}.{key}: {txt!r} is not a number (in {text!r})")
    for e in extra:
        k, eq, v = e.partition("=")
        if not eq or not k.strip():
            errors.append(f"{path}: {e!r}: expected param=value (in {text!r})")
            continue
        k = k.strip()
        v = v.strip()
        try:
            item[k] = float(v) if k != "field" else v
        except ValueError:
            item[k] = v  # the check names the key and the bad value
    if errors:
        return None, errors
    spec, errs = _check_one(item, path)
    if spec is not None:
        spec = FaultSpec(spec.kind, spec.at_s, spec.for_s, spec.params, f"--fault {text}")
    return spec, errs


def check_transport(specs: Iterable[FaultSpec], transport: str) -> list[str]:
    """Faults a transport cannot do (e.g. modbus_exception on serial), by their key path."""
    errors = []
    for s in specs:
        fk = FAULT_KINDS[s.kind]
        if transport not in fk.transports:
            errors.append(f"{s.source or s.kind}.kind: {s.kind} needs --transport "
                          f"{' or '.join(fk.transports)} (this run: {transport})")
    return errors


# --------------------------------------------------------------------------
class FaultSchedule:
    """The active fault bits per device tick, and the parameters of the active faults."""

    def __init__(self, specs: Iterable[FaultSpec], rate_hz: float) -> None:
        self.specs = list(specs)
        self.rate_hz = float(rate_hz)
        self.windows = [(s.window(self.rate_hz), s) for s in self.specs]
        #: first tick after which nothing is ever active again
        self.k_end = max((w[1] for w, _ in self.windows), default=0)
        self.bits = 0
        #: bit → the spec that set it (first active one of that kind)
        self.active_specs: dict[int, FaultSpec] = {}

    def __bool__(self) -> bool:
        return bool(self.specs)

    def active(self, k: int) -> int:
        """Bits active at device tick k; updates :attr:`active_specs` on a change."""
        if k >= self.k_end and not self.bits:
            return 0
        bits = 0
        specs: dict[int, FaultSpec] = {}
        for (k0, k1), s in self.windows:
            if k0 <= k < k1:
                b = s.bit
                if not bits & b:
                    specs[b] = s
                bits |= b
        if bits != self.bits:
            self.bits = bits
            self.active_specs = specs
        return bits

    def param(self, bit: int, name: str) -> Any:
        s = self.active_specs.get(int(bit))
        if s is None:
            return FAULT_KINDS[_NAME_OF[int(bit)]].params[name].default
        return s.param(name)

    def describe(self) -> list[dict[str, Any]]:
        return [s.as_dict(self.rate_hz) for s in self.specs]


_NAME_OF = {int(k.bit): k.name for k in FAULT_KINDS.values()}


def bit_names(bits: int) -> str:
    """``"nan|stale_seq"`` for a fault column value (``"-"`` for 0)."""
    names = [name for name, k in FAULT_KINDS.items() if bits & int(k.bit)]
    return "|".join(names) if names else "-"


def fault_markdown() -> str:
    """The fault table for docs/hil_sim.md."""
    lines = ["| kind | bit | params | what the device does | transports |", "|---|---|---|---|---|"]
    for k in FAULT_KINDS.values():
        params = ", ".join(
            f"`{n}`" + (f" (default {p.default})" if p.default is not None else " (required)")
            for n, p in k.params.items()) or "-"
        lines.append(f"| `{k.name}` | {int(k.bit)} | {params} | {k.doc} | {', '.join(k.transports)} |")
    return "\n".join(lines)
