"""Device presets: DAQs a lab can buy, driven over their vendor's own register map.

A preset is data, one YAML file per device beside this module (``labjack_t7.yaml``:
addresses, types and ranges from the vendor's published map, with the source
named in the file). The user's ``backend.channels`` says which analog input
carries which sensor and the volts per unit of each; :func:`resolve_device`
checks both together (every error with its key path) and turns them into a
:class:`DeviceSetup`: each channel's calibration (:class:`ChannelSpec`: physical
= (volts - offset_V) * per_V on an input, volts = current * V_per_A + offset_V
on the DAC) and the set-up the link does at open (input range, resolution,
negative channel and settling per used input, the device watchdog, the enable
output, the E-stop input), each read back.

The link that does the set-up and the tick is :class:`mrctl.io.devices.link.PresetLink`
(generic: what differs between devices is in the YAML); the backend table
(:func:`mrctl.io.link_class_for`) chooses it for a ``backend.device``. docs/hardware.md.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

__all__ = ["CHANNEL_ROLES", "ChannelSpec", "DeviceSetup", "Preset", "load_preset", "preset_names", "resolve_device"]

PRESETS_DIR = Path(__file__).resolve().parent

#: channel role → (register-map quantity, kind "ain"|"dac", the per-volt key, its unit)
CHANNEL_ROLES: dict[str, tuple[str, str, str, str]] = {
    "x": ("x_m", "ain", "m_per_V", "m"),
    "v": ("v_mps", "ain", "mps_per_V", "m/s"),
    "F": ("F_N", "ain", "N_per_V", "N"),
    "current_monitor": ("current_applied_A", "ain", "A_per_V", "A"),
    "current": ("current_setpoint_A", "dac", "V_per_A", "V/A"),
}
REQUIRED_ROLES = ("x", "current")


@dataclass(frozen=True)
class Preset:
    """One device's register facts (the YAML file, checked on load)."""

    name: str
    description: str
    source: str
    data: Mapping[str, Any]

    @property
    def port(self) -> int:
        return int(self.data["modbus"]["port"])

    @property
    def unit_id(self) -> int:
        return int(self.data["modbus"]["unit_id"])

    @property
    def fc23(self) -> bool:
        return bool(self.data["modbus"]["fc23"])

    def io(self, kind: str) -> Mapping[str, Any]:
        """The ``ain`` / ``dac`` / ``dio`` block."""
        return self.data[kind]

    def address(self, kind: str, n: int) -> int:
        """Register address of channel ``n`` of ``kind`` (ain, dac, dio)."""
        b = self.data[kind]
        return int(b["address"]) + int(b["stride"]) * n

    @property
    def watchdog(self) -> Mapping[str, Any] | None:
        return self.data.get("watchdog")


def preset_names() -> tuple[str, ...]:
    """Every preset shipped (the YAML files beside this module)."""
    return tuple(sorted(p.stem for p in PRESETS_DIR.glob("*.yaml")))


@functools.cache
def load_preset(name: str) -> Preset:
    """The preset ``name``; KeyError naming the known ones."""
    if name not in preset_names():
        raise KeyError(f"unknown device {name!r} (known: {', '.join(preset_names())})")
    data = yaml.safe_load((PRESETS_DIR / f"{name}.yaml").read_text(encoding="utf-8"))
    return Preset(str(data["name"]), str(data["description"]), str(data["source"]), data)


@dataclass(frozen=True)
class ChannelSpec:
    """One wired channel: ``n`` on the device's ``kind`` (ain/dac); physical
    = (volts - offset_V) * per_V for inputs, volts = physical * per_V +
    offset_V for the DAC (``per_V`` is V/A there)."""

    role: str
    kind: str
    n: int
    per_V: float
    offset_V: float
    #: differential input: the AIN read as the negative side (None: single-ended)
    negative: int | None = None


@dataclass(frozen=True)
class DeviceSetup:
    """A preset with a lab's wiring: everything the link needs."""

    preset: Preset
    channels: Mapping[str, ChannelSpec]
    ain_range_V: float
    ain_resolution_index: int
    watchdog_s: int
    enable_dio: int | None
    enable_toggle_s: float
    extra: Mapping[str, Any] = field(default_factory=dict)
    #: AIN settling time set on every input used (µs; 0 = the device's automatic)
    ain_settling_us: float = 0.0
    #: the E-stop input (safety.estop): its DIO and whether high is the active (stop) level
    estop_dio: int | None = None
    estop_active_high: bool = False
    #: the device's clock stamps the samples the observer sees (backend.time_stamps: device), when it has one;
    #: False: the host's clock at the reply (the device's clock still tells a stale sample)
    device_time_stamps: bool = True

    @property
    def ains(self) -> tuple[int, ...]:
        """The analog inputs in use (each gets its range and resolution set at open)."""
        return tuple(sorted(c.n for c in self.channels.values() if c.kind == "ain"))

    @property
    def ain_block(self) -> tuple[int, int]:
        """The inputs as the tick reads them, one block from the lowest in use to the highest:
        (the first, how many; the device converts every input in between too)."""
        ains = self.ains
        return ains[0], ains[-1] - ains[0] + 1

    @property
    def dac(self) -> ChannelSpec:
        return self.channels["current"]

    def dac_volts(self, current_A: float) -> float:
        """Volts on the DAC for ``current_A`` (A)."""
        c = self.dac
        return current_A * c.per_V + c.offset_V

    def to_dict(self) -> dict[str, Any]:
        """What the run log's sidecar records: the device, its wiring and set-up."""
        return {"device": self.preset.name, "source": self.preset.source,
                "channels": {r: {c.kind: c.n, CHANNEL_ROLES[r][2]: c.per_V, "offset_V": c.offset_V}
                             for r, c in self.channels.items()},
                "ain_range_V": self.ain_range_V, "ain_resolution_index": self.ain_resolution_index,
                "device_watchdog_s": self.watchdog_s, "enable_dio": self.enable_dio,
                "enable_toggle_s": self.enable_toggle_s, "ain_settling_us": self.ain_settling_us,
                "negative_ain": {r: c.negative for r, c in self.channels.items() if c.negative is not None},
                "estop_dio": self.estop_dio, "estop_active": None if self.estop_dio is None
                else ("high" if self.estop_active_high else "low"),
                "time_stamps": "device" if self.device_time_stamps else "host"}

    def describe(self) -> str:
        wired = ", ".join(f"{r}={c.kind.upper()}{c.n}" + (f"-AIN{c.negative}" if c.negative is not None else "")
                          for r, c in self.channels.items())
        en = f", enable DIO{self.enable_dio} toggled every {self.enable_toggle_s * 1e3:g} ms" \
            if self.enable_dio is not None else ""
        es = f", E-stop DIO{self.estop_dio} active {'high' if self.estop_active_high else 'low'}" \
            if self.estop_dio is not None else ""
        return (f"{self.preset.name} ({wired}; AIN range +/-{self.ain_range_V:g} V, resolution index "
                f"{self.ain_resolution_index}; device watchdog {self.watchdog_s} s, strict{en}{es})")


def _number(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(float(v))


def _channel(preset: Preset, role: str, data: Any, path: str, errors: list[str]) -> ChannelSpec | None:
    quantity, kind, per_key, unit = CHANNEL_ROLES[role]
    if not isinstance(data, Mapping):
        errors.append(f"{path}: must be a mapping ({kind}, {per_key}, offset_V), got {type(data).__name__}")
        return None
    ok = True
    allowed = (kind, per_key, "offset_V") + (("negative_ain",) if kind == "ain" else ())
    for key in data:
        if key not in allowed:
            errors.append(f"{path}.{key}: unknown key (allowed here: {', '.join(allowed)})")
            ok = False
    io = preset.io(kind)
    count = int(io["count"])
    n = data.get(kind)
    if n is None:
        errors.append(f"{path}.{kind}: missing required key (the {io['name']} number, 0-{count - 1})")
        ok = False
    elif isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < count:
        errors.append(f"{path}.{kind}: {n!r} not allowed: a {preset.name} has {io['name']}0-{io['name']}{count - 1}")
        ok = False
    per = data.get(per_key)
    if per is None:
        errors.append(f"{path}.{per_key}: missing required key ({unit} per volt)" if kind == "ain"
                      else f"{path}.{per_key}: missing required key (driver input volts per ampere)")
        ok = False
    elif not _number(per) or per == 0:
        errors.append(f"{path}.{per_key}: {per!r} not allowed (must be a finite non-zero number)")
        ok = False
    off = data.get("offset_V", 0.0)
    if not _number(off):
        errors.append(f"{path}.offset_V: {off!r} not allowed (must be a finite number of volts)")
        ok = False
    elif kind == "dac" and not float(io["min_V"]) <= off <= float(io["max_V"]):
        errors.append(f"{path}.offset_V: {off!r} V (the DAC at 0 A) is outside {io['name']}'s "
                      f"{io['min_V']:g}-{io['max_V']:g} V")
        ok = False
    neg = data.get("negative_ain")
    if neg is not None and ok:
        # AIN#_NEGATIVE_CH (ljm_constants): "positive must be even channel from 0-12 and negative must be positive+1"
        if isinstance(neg, bool) or not isinstance(neg, int) or n % 2 or neg != n + 1 or n > 12:
            errors.append(f"{path}.negative_ain: {neg!r} not allowed: a {preset.name}'s differential pairs are "
                          f"an even AIN0-AIN12 with the next one (AIN{n} pairs with "
                          + (f"AIN{n + 1})" if n % 2 == 0 and n <= 12 else "none: it is odd)"))
            ok = False
    if not ok:
        return None
    return ChannelSpec(role, kind, int(n), float(per), float(off), None if neg is None else int(neg))


def resolve_device(name: Any, channels: Any, options: Mapping[str, Any], path: str = "backend",
                   I_max_A: float | None = None) -> tuple[DeviceSetup | None, list[str]]:
    """Check ``backend.channels`` and the device options against the preset
    ``name``; return (set-up or None, every error with its key path).

    ``options``: ``ain_range_V``, ``ain_resolution_index``, ``device_watchdog_s``,
    ``enable_dio``, ``enable_toggle_s``, ``ain_settling_us``, ``time_stamps`` (None = the preset's default),
    ``estop_dio``/``estop_input``/``estop_active`` (safety.estop on a DIO, or None).
    ``I_max_A`` (safety.I_max): the DAC must reach it within its range."""
    try:
        preset = load_preset(str(name))
    except KeyError as e:
        return None, [f"{path}.device: {e.args[0]}"]
    errors: list[str] = []
    cpath = f"{path}.channels"
    if channels is None:
        return None, [f"{cpath}: required with device {preset.name} (at least x and current; docs/hardware.md)"]
    if not isinstance(channels, Mapping):
        return None, [f"{cpath}: must be a mapping of role -> channel, got {type(channels).__name__}"]
    specs: dict[str, ChannelSpec] = {}
    for role, data in channels.items():
        if role not in CHANNEL_ROLES:
            errors.append(f"{cpath}.{role}: unknown channel (allowed here: {', '.join(CHANNEL_ROLES)})")
            continue
        spec = _channel(preset, role, data, f"{cpath}.{role}", errors)
        if spec is not None:
            specs[role] = spec
    errors += [f"{cpath}.{r}: required" for r in REQUIRED_ROLES if r not in channels]
    used: dict[tuple[str, int], str] = {}
    for role, s in specs.items():
        other = used.setdefault((s.kind, s.n), role)
        if other != role:
            errors.append(f"{cpath}.{role}.{s.kind}: {s.kind.upper()}{s.n} is already {cpath}.{other}")
    for role, s in specs.items():
        if s.negative is not None and ("ain", s.negative) in used:
            errors.append(f"{cpath}.{role}.negative_ain: AIN{s.negative} is already "
                          f"{cpath}.{used[('ain', s.negative)]}")
    dac = specs.get("current")
    io = preset.io("dac")
    if dac is not None and I_max_A is not None:
        v = I_max_A * dac.per_V + dac.offset_V
        if not float(io["min_V"]) <= v <= float(io["max_V"]):
            errors.append(f"{cpath}.current.V_per_A: safety.I_max {I_max_A:g} A needs {v:g} V on "
                          f"{io['name']}{dac.n}; a {preset.name}'s DAC gives {io['min_V']:g}-{io['max_V']:g} V")
    ain = preset.io("ain")
    rng = options.get("ain_range_V")
    rng = float(ain["ranges_V"][0]) if rng is None else rng
    if not _number(rng) or float(rng) not in [float(r) for r in ain["ranges_V"]]:
        errors.append(f"{path}.ain_range_V: {rng!r} not allowed (a {preset.name} has +/- "
                      f"{', '.join(f'{r:g}' for r in ain['ranges_V'])} V)")
    lo, hi = ain["resolution_indices"]
    res = options.get("ain_resolution_index")
    res = lo if res is None else res
    if isinstance(res, bool) or not isinstance(res, int) or not lo <= res <= hi:
        errors.append(f"{path}.ain_resolution_index: {res!r} not allowed (a {preset.name} takes {lo}-{hi})")
    wd = preset.watchdog
    wd_s = options.get("device_watchdog_s")
    wd_s = 1 if wd_s is None else wd_s
    if wd is not None:
        wlo, whi = wd["timeout_s_range"]
        if not _number(wd_s) or not float(wd_s).is_integer() or not wlo <= wd_s <= whi:
            errors.append(f"{path}.device_watchdog_s: {wd_s!r} not allowed (a {preset.name}'s watchdog counts "
                          f"whole seconds, {wlo} or more; faster protection: enable_dio, docs/hardware.md)")
    dio = options.get("enable_dio")
    dcount = int(preset.io("dio")["count"])
    if dio is not None and (isinstance(dio, bool) or not isinstance(dio, int) or not 0 <= dio < dcount):
        errors.append(f"{path}.enable_dio: {dio!r} not allowed: a {preset.name} has DIO0-DIO{dcount - 1}")
    tog = options.get("enable_toggle_s")
    tog = 0.002 if tog is None else tog
    if not _number(tog) or not 0 < tog <= 1.0:
        errors.append(f"{path}.enable_toggle_s: {tog!r} not allowed (seconds, > 0 and <= 1)")
    settle = options.get("ain_settling_us")
    settle = 0.0 if settle is None else settle
    max_us = float(ain.get("settling_register", {}).get("max_us", 0))
    if not _number(settle) or not 0 <= settle <= max_us:
        errors.append(f"{path}.ain_settling_us: {settle!r} not allowed (0 = automatic, up to {max_us:g} µs)")
    estop_dio, estop_high = _estop(preset, options, dio, dcount, errors)
    if errors:
        return None, errors
    return DeviceSetup(preset, specs, float(rng), int(res), int(wd_s),
                       None if dio is None else int(dio), float(tog), ain_settling_us=float(settle),
                       estop_dio=estop_dio, estop_active_high=estop_high,
                       device_time_stamps=options.get("time_stamps") != "host"), []


def _estop(preset: Preset, options: Mapping[str, Any], enable_dio: Any, dcount: int,
           errors: list[str]) -> tuple[int | None, bool]:
    """``safety.estop`` on this preset (``estop_dio``: the DIO number its name parsed to): a DIO it
    has, not the enable output (read as an input at every open and every tick: reading ``DIO#``
    makes the line an input, docs/hardware.md)."""
    n, inp, active = options.get("estop_dio"), options.get("estop_input"), options.get("estop_active")
    if n is None:
        return None, False  # none, or not a DIO (the generic checks say so: mrctl/config/estop.py)
    if not 0 <= n < dcount:
        errors.append(f"safety.estop.input: {inp!r} not allowed: a {preset.name} has DIO0-DIO{dcount - 1} "
                      "(FIO0-7 = DIO0-7, EIO0-7 = DIO8-15, CIO0-3 = DIO16-19, MIO0-2 = DIO20-22)")
        return None, False
    if enable_dio is not None and n == enable_dio:
        errors.append(f"safety.estop.input: {inp!r} is DIO{n}, the enable output (backend.enable_dio): "
                      "the E-stop needs an input of its own")
        return None, False
    return n, active == "high"
