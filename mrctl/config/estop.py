"""``safety.estop``: the E-stop / interlock input a real link reads every tick.

What each link can read (checked against ``backend`` once the file is valid):

* ``input: device`` — the device's own E-stop input, reported in its status
  (``Status.ESTOP``, bit 7): the reference firmware's E-stop pin
  (docs/protocol.md), a Modbus device's ``status`` register (the default
  register map, hil_sim; a register map names its status register);
* ``input: DIO<n>`` (or the T7's names ``FIO<n>``, ``EIO<n>``, ``CIO<n>``,
  ``MIO<n>``) on a device preset such as the LabJack T7, with ``active``.

The in-process simulated bench has none (it is not wired to anything). The
software input never replaces the hard-wired E-stop that removes the
driver's and the shaker's power (docs/hardware.md): it makes mrctl latch,
command 0 A with the enable output low, and wait for ``mrctl arm``.
"""

from __future__ import annotations

import re
from typing import Any

from mrctl.util.schema import Node, Section, Str

__all__ = ["estop_section", "estop_checks", "parse_dio", "DIO_PREFIXES"]

#: a T-series DIO's names: DIO0-22 = FIO0-7, EIO0-7, CIO0-3, MIO0-2 (LabJack T-series datasheet 13.0 "Digital I/O")
DIO_PREFIXES: dict[str, int] = {"DIO": 0, "FIO": 0, "EIO": 8, "CIO": 16, "MIO": 20}
_DIO = re.compile(r"^(DIO|FIO|EIO|CIO|MIO)(\d{1,2})$")


def estop_section() -> Section:
    """The schema of ``safety.estop`` (absent: no software E-stop input)."""
    return Section({
        "input": Str(default=None, optional=True,
                     doc="the E-stop / interlock input read every tick: 'device' (the device reports it in its "
                         "status, bit 7: the reference firmware, a Modbus status register), or a device preset's "
                         "digital input ('DIO4', 'FIO4', 'EIO0', ...); null = none (the hard-wired E-stop only; "
                         "docs/hardware.md)"),
        "active": Str(default=None, optional=True, choices=("low", "high"),
                      doc="a digital input: the level that means stop; wire a normally-closed contact to ground "
                          "with the input's pull-up and say high: a broken wire then stops too"),
    }, doc="E-stop / interlock input: open -> 0 A, enable low, latched until mrctl arm (docs/hardware.md)")


def parse_dio(name: str) -> int | None:
    """``DIO4`` → 4, ``EIO0`` → 8, ``MIO2`` → 22; None if ``name`` is not a DIO name."""
    m = _DIO.match(name)
    if m is None:
        return None
    return DIO_PREFIXES[m.group(1)] + int(m.group(2))


def estop_checks(cfg: Node) -> list[str]:
    """``safety.estop`` against the backend (each error names its key)."""
    safety, backend = cfg.get("safety"), cfg.get("backend")
    estop = safety.get("estop") if safety is not None else None
    if estop is None or backend is None:
        return []
    inp, active = estop.get("input"), estop.get("active")
    kind = backend.get("type")
    if inp is None:
        return ["safety.estop.active: set without safety.estop.input"] if active is not None else []
    preset = backend.get("device")
    if kind == "sim":
        return ["safety.estop.input: the in-process simulated bench has no E-stop input "
                "(use hil_sim's --fault estop@AT+FOR over a real protocol; docs/hil_sim.md)"]
    if inp == "device":
        if preset is not None:
            return [f"safety.estop.input: 'device': a {_preset_name(preset)} has no E-stop of its own; "
                    "name the digital input it is wired to (e.g. DIO4)"]
        if active is not None:
            return ["safety.estop.active: the device reports its E-stop in its status (it knows the level); "
                    "remove active"]
        rmap = backend.get("register_map") if kind != "serial" else None
        if rmap is not None and not rmap.has("status"):
            return ["safety.estop.input: 'device', but backend.register_map has no status register to report it "
                    "(docs/registers.md)"]
        return []
    if parse_dio(inp) is None:
        return [f"safety.estop.input: {inp!r} not allowed (device, or a device preset's digital input such as DIO4)"]
    errors = []
    if preset is None:
        errors.append(f"safety.estop.input: {inp!r} is a device preset's digital input: needs backend.device "
                      "(e.g. labjack_t7)")
    if active is None:
        errors.append(f"safety.estop.active: required with input {inp!r} (low or high)")
    return errors


def _preset_name(preset: Any) -> str:
    return str(getattr(getattr(preset, "preset", None), "name", preset))
