"""Experiment YAML → validated, typed config; every error names its key path.

Why a small declarative schema instead of a library: the runtime dependency
set is fixed (numpy, pyyaml, pyserial, pymodbus), and what we need is narrow:
unknown keys rejected, numbers range-checked, unions chosen by a ``type`` or
``law`` key, defaults filled, and *all* errors collected so ``mrctl check``
lists every one at once. The schema below is also the reference for
``docs/config.md``.

YAML traps handled here: duplicate keys are an error (PyYAML silently keeps
the last), and ``1e-3`` is read as a number (YAML 1.1 makes it a string).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import yaml

from mrctl.model.params import LuGreParams, params_from_mapping

CONFIG_VERSION = 1
SPIN_WAIT_DOC = ("wait for each reply by polling, busy for one round trip (device pacing: for the last "
                 "loop.spin_margin_s of it), instead of sleeping in select(): a sleeping thread can wake "
                 "up to ~1.5 ms late on a VM")
_REQUIRED = object()


class ConfigError(Exception):
    """One or more problems in a config; ``errors`` holds one line per problem."""

    def __init__(self, errors: list[str], source: str | None = None) -> None:
        self.errors = list(errors)
        self.source = source
        head = f"{source}: " if source else ""
        super().__init__(head + ("; ".join(self.errors) if len(self.errors) == 1 else f"{len(self.errors)} errors:\n  " + "\n  ".join(self.errors)))


# --------------------------------------------------------------------------
# YAML loading
class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys and reads 1e-3 as a float."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: dict[Any, yaml.Node] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (first at line {seen[key].start_mark.line + 1})", key_node.start_mark
            )
        seen[key] = key_node
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:\d[\d_]*)?(?:\.\d*)?[eE][-+]?\d+$"),
    list("-+0123456789."),
)


def load_yaml(path: str | Path) -> Any:
    """Parse a YAML file strictly; errors become ConfigError with line numbers."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError([f"cannot read: {exc.strerror}"], str(p)) from None
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - strict SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError([f"{where}invalid YAML: {problem}"], str(p)) from None


# --------------------------------------------------------------------------
# Schema
@dataclass(frozen=True)
class Num:
    """A number field (int or float in YAML; bools rejected)."""

    default: Any = _REQUIRED
    min: float | None = None
    max: float | None = None
    min_exclusive: bool = False
    integer: bool = False
    optional: bool = False  # None allowed
    doc: str = ""


@dataclass(frozen=True)
class Str:
    default: Any = _REQUIRED
    choices: tuple[str, ...] | None = None
    optional: bool = False
    doc: str = ""


@dataclass(frozen=True)
class Bool:
    default: Any = _REQUIRED
    doc: str = ""


@dataclass(frozen=True)
class Section:
    fields: Mapping[str, Any]
    doc: str = ""
    optional: bool = True  # absent section → all defaults


@dataclass(frozen=True)
class Union:
    """A section whose allowed keys depend on its discriminator key."""

    key: str
    variants: Mapping[str, Mapping[str, Any]]
    default: str | None = None
    doc: str = ""


@dataclass(frozen=True)
class Custom:
    """A field validated by a function: value, key path → (result, errors)."""

    check: Callable[[Any, str], tuple[Any, list[str]]]
    default: Any = _REQUIRED
    doc: str = ""


class Node:
    """Validated config section: attribute access, read-only, printable."""

    def __init__(self, values: dict[str, Any]) -> None:
        object.__setattr__(self, "_values", values)

    def __getattr__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("config is read-only")

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def get(self, name: str, default: Any = None) -> Any:
        return self._values.get(name, default)

    def to_dict(self) -> dict[str, Any]:
        return {k: (v.to_dict() if isinstance(v, Node) else v) for k, v in self._values.items()}

    def __repr__(self) -> str:
        return f"Node({self.to_dict()!r})"


def _path(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _check_num(spec: Num, value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None and spec.optional:
        return None, []
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None, [f"{path}: must be a number, got {value!r}"]
    if spec.integer and not (isinstance(value, int) or float(value).is_integer()):
        return None, [f"{path}: must be a whole number, got {value!r}"]
    if not math.isfinite(float(value)):
        return None, [f"{path}: must be finite, got {value!r}"]
    v = int(value) if spec.integer else float(value)
    lo, hi = spec.min, spec.max
    if lo is not None and (v <= lo if spec.min_exclusive else v < lo):
        rel = ">" if spec.min_exclusive else ">="
        return None, [f"{path}: {value!r} out of range (must be {rel} {lo:g}{f' and <= {hi:g}' if hi is not None else ''})"]
    if hi is not None and v > hi:
        return None, [f"{path}: {value!r} out of range (must be <= {hi:g})"]
    return v, []


def _validate_fields(fields_: Mapping[str, Any], data: Any, path: str) -> tuple[Node, list[str]]:
    errors: list[str] = []
    if data is None:
        data = {}
    if not isinstance(data, dict):
        return Node({}), [f"{path or 'config'}: must be a mapping, got {type(data).__name__}"]
    for key in data:
        if key not in fields_:
            allowed = ", ".join(fields_)
            errors.append(f"{_path(path, str(key))}: unknown key (allowed here: {allowed})")
    out: dict[str, Any] = {}
    for key, spec in fields_.items():
        kpath = _path(path, key)
        present = key in data
        value = data.get(key)
        if isinstance(spec, Section):
            if not present and not spec.optional:
                errors.append(f"{kpath}: missing required section")
                continue
            node, errs = _validate_fields(spec.fields, value if present else {}, kpath)
            out[key] = node
            errors += errs
            continue
        if isinstance(spec, Union):
            node, errs = _validate_union(spec, value if present else None, kpath, present)
            out[key] = node
            errors += errs
            continue
        if not present:
            if spec.default is _REQUIRED:
                errors.append(f"{kpath}: missing required key")
            elif isinstance(spec, Custom):  # defaults of custom fields are inputs too
                out[key], errs = spec.check(spec.default, kpath)
                errors += errs
            else:
                out[key] = spec.default
            continue
        if isinstance(spec, Num):
            v, errs = _check_num(spec, value, kpath)
        elif isinstance(spec, Str):
            if value is None and spec.optional:
                v, errs = None, []
            elif not isinstance(value, str):
                v, errs = None, [f"{kpath}: must be a string, got {value!r}"]
            elif spec.choices is not None and value not in spec.choices:
                v, errs = None, [f"{kpath}: {value!r} not allowed (allowed: {', '.join(spec.choices)})"]
            else:
                v, errs = value, []
        elif isinstance(spec, Bool):
            v, errs = (value, []) if isinstance(value, bool) else (None, [f"{kpath}: must be true or false, got {value!r}"])
        elif isinstance(spec, Custom):
            v, errs = spec.check(value, kpath)
        else:  # pragma: no cover - schema bug
            raise TypeError(f"bad schema entry at {kpath}")
        out[key] = v
        errors += errs
    return Node(out), errors


def _validate_union(spec: Union, data: Any, path: str, present: bool) -> tuple[Node, list[str]]:
    if not present or data is None:
        if spec.default is None:
            return Node({}), [f"{path}: missing required section (with {spec.key}: one of {', '.join(spec.variants)})"]
        data = {spec.key: spec.default}
    if not isinstance(data, dict):
        return Node({}), [f"{path}: must be a mapping, got {type(data).__name__}"]
    kind = data.get(spec.key, spec.default)
    if kind is None:
        return Node({}), [f"{_path(path, spec.key)}: missing (one of {', '.join(spec.variants)})"]
    if not isinstance(kind, str) or kind not in spec.variants:
        return Node({}), [f"{_path(path, spec.key)}: {kind!r} not allowed (allowed: {', '.join(spec.variants)})"]
    variant = {spec.key: Str(default=kind), **spec.variants[kind]}
    return _validate_fields(variant, data, path)


# --------------------------------------------------------------------------
# Parameters: Table I, a file of spec names, or inline overrides
_PARAM_FILE_META = ("version", "description", "source", "fit")


def load_params_file(path: str | Path) -> LuGreParams:
    """Read a parameters YAML (keys: the spec's names, plus metadata keys
    version/description/source/fit which are ignored)."""
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(["must be a mapping of parameter names to numbers"], str(path))
    values = {k: v for k, v in data.items() if k not in _PARAM_FILE_META}
    errors = []
    known = set(LuGreParams.names())
    for k in values:
        if k not in known:
            errors.append(f"{k}: unknown parameter (expected: {', '.join(LuGreParams.names())})")
    if errors:
        raise ConfigError(errors, str(path))
    try:
        return params_from_mapping(values)
    except ValueError as exc:
        raise ConfigError([str(exc)], str(path)) from None


def _make_params_check(base_dir: Path) -> Callable[[Any, str], tuple[Any, list[str]]]:
    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if value is None and path.endswith("plant.parameters"):
            return None, []  # the simulated damper uses the law's set
        if value is None or value == "table1":
            return LuGreParams(), []
        if isinstance(value, str):
            value = {"file": value}
        if not isinstance(value, dict):
            return None, [f"{path}: must be 'table1', a parameters file path, or a mapping of parameter names"]
        overrides = dict(value)
        base = LuGreParams()
        if "file" in overrides:
            fpath = overrides.pop("file")
            if not isinstance(fpath, str):
                return None, [f"{path}.file: must be a path string, got {fpath!r}"]
            full = (base_dir / fpath) if not Path(fpath).is_absolute() else Path(fpath)
            try:
                base = load_params_file(full)
            except ConfigError as exc:
                return None, [f"{path}.file ({full}): {e}" for e in exc.errors]
        errors = []
        good: dict[str, float] = {}
        known = set(LuGreParams.names())
        for k, v in overrides.items():
            if k not in known:
                errors.append(f"{path}.{k}: unknown parameter (expected: file, {', '.join(LuGreParams.names())})")
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                errors.append(f"{path}.{k}: must be a finite number, got {v!r}")
            else:
                good[k] = float(v)
        if errors:
            return None, errors
        return base.with_overrides(**good), []

    return check


def _file_check(base_dir: Path) -> Callable[[Any, str], tuple[Any, list[str]]]:
    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if not isinstance(value, str) or not value:
            return None, [f"{path}: must be a file path, got {value!r}"]
        p = Path(value)
        full = p if p.is_absolute() else base_dir / p
        if not full.is_file():
            return None, [f"{path}: no such file: {full}"]
        return str(full), []

    return check


def _current_list(value: Any, path: str) -> tuple[Any, list[str]]:
    if not isinstance(value, list) or not value:
        return None, [f"{path}: must be a non-empty list of currents (A)"]
    out, errors = [], []
    for i, v in enumerate(value):
        num, errs = _check_num(Num(min=0.0), v, f"{path}[{i}]")
        out.append(num)
        errors += errs
    return out, errors


def _range_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    if not isinstance(value, list) or len(value) != 2:
        return None, [f"{path}: must be [lo, hi] or null, got {value!r}"]
    lo, e1 = _check_num(Num(), value[0], f"{path}[0]")
    hi, e2 = _check_num(Num(), value[1], f"{path}[1]")
    if e1 or e2:
        return None, e1 + e2
    if not lo <= hi:
        return None, [f"{path}: need lo <= hi, got {value!r}"]
    return (lo, hi), []


def _cpu_list(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    if not isinstance(value, list) or not value:
        return None, [f"{path}: must be a non-empty list of CPU numbers or null"]
    cpus, errors = [], []
    for i, c in enumerate(value):
        n, errs = _check_num(Num(integer=True, min=0, max=4095), c, f"{path}[{i}]")
        cpus.append(n)
        errors += errs
    return (frozenset(cpus) if not errors else None), errors


def _lead_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value == "auto":
        return "auto", []
    return _check_num(Num(min=0.0, max=0.1), value, path)


def _optional_bool(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None or isinstance(value, bool):
        return value, []
    return None, [f"{path}: must be true, false or null (probe), got {value!r}"]


def _register_map(value: Any, path: str) -> tuple[Any, list[str]]:
    """The Modbus register map (docs/registers.md); null = the default map."""
    try:
        from mrctl.io.registers import default_register_map
    except ImportError:  # pragma: no cover - the module ships with mrctl
        return None, [f"{path}: Modbus register maps are not available in this build"]
    if value is None:
        return default_register_map(), []
    from mrctl.io.registers import validate_register_map

    rmap, errors = validate_register_map(value, path)
    return rmap, errors


def experiment_schema(base_dir: Path) -> dict[str, Any]:
    """The experiment schema; relative file paths resolve against ``base_dir``."""
    modbus_common = {
        "timeout_s": Num(default=0.005, min=0.0, min_exclusive=True, max=1.0, doc="reply timeout (s)"),
        "use_fc23": Custom(_optional_bool, default=None, doc="one FC23 transaction per tick; null = probe at start"),
        "register_map": Custom(_register_map, default=None, doc="register map (docs/registers.md); null = default"),
        "open_timeout_s": Num(default=1.0, min=0.0, min_exclusive=True, max=60.0, doc="connect and FC23 probe (s)"),
        "watchdog_ms": Num(default=50, integer=True, min=0, max=65535,
                           doc="device applies 0 A if setpoints stop this long (0 = device default)"),
        "spin_wait": Bool(default=True, doc=SPIN_WAIT_DOC),
    }
    return {
        "version": Num(integer=True, min=CONFIG_VERSION, max=CONFIG_VERSION, doc="config format version (1)"),
        "name": Str(default=None, optional=True, doc="experiment name (logs, file titles)"),
        "description": Str(default=None, optional=True, doc="free text, kept in the run log"),
        "duration_s": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=7 * 86400.0,
                          doc="run length (s); none = until stopped (excitation files: their length)"),
        "rate_hz": Num(default=1000.0, min=1.0, max=20000.0, doc="control rate (Hz)"),
        "parameters": Custom(_make_params_check(base_dir), default="table1",
                             doc="'table1', a parameters YAML path, or {file: ..., <name>: value} overrides"),
        "excitation": Union("type", {
            "sine": {"amplitude_m": Num(min=0.0, max=1.0, doc="displacement amplitude (m)"),
                     "frequency_hz": Num(min=0.0, min_exclusive=True, max=500.0, doc="frequency (Hz)"),
                     "phase_rad": Num(default=0.0, doc="phase at t = 0 (rad)")},
            "chirp": {"amplitude_m": Num(min=0.0, max=1.0, doc="displacement amplitude (m)"),
                      "f0_hz": Num(min=0.0, min_exclusive=True, max=500.0, doc="start frequency (Hz)"),
                      "f1_hz": Num(min=0.0, min_exclusive=True, max=500.0, doc="end frequency (Hz)"),
                      "sweep_s": Num(min=0.0, min_exclusive=True, doc="sweep time (s); f1 is held afterwards")},
            "file": {"path": Custom(_file_check(base_dir), doc="CSV with columns t,x (s, m) and optionally v (m/s)")},
        }, doc="shaker motion on the simulated bench"),
        "demand": Union("type", {
            "viscous": {"c_des": Num(min=0.0, max=1e5, doc="desired damping (N·s/m), eq (13)")},
            "constant": {"F_N": Num(min=-1e4, max=1e4, doc="desired force (N)")},
            "file": {"path": Custom(_file_check(base_dir), doc="CSV with columns t,F_des (s, N)")},
        }, doc="desired-force law"),
        "inverse": Union("law", {
            "paper": {},
            "smooth": {"eps_N_per_A": Num(default=3.0, min=0.0, max=1e4, doc="regularisation: hold where dF/dI is below this (N/A)"),
                       "max_slew_A_per_s": Num(default=50.0, min=0.0, min_exclusive=True, max=1e6,
                                               doc="driver slew rate the law respects (A/s)")},
            "constant": {"current_A": Num(min=0.0, doc="the current (A), <= safety.I_max")},
            "schedule": {"currents_A": Custom(_current_list, doc="list of currents (A), each held step_s, then 0 A"),
                         "step_s": Num(min=0.0, min_exclusive=True, doc="time per current (s)")},
        }, doc="inverse law"),
        "safety": Section({
            "I_max": Num(min=0.0, min_exclusive=True, max=2.0, doc="current limit (A); RD-1097-01 rating is 1 A"),
            "max_slew_A_per_s": Num(default=None, optional=True, min=0.0, min_exclusive=True,
                                    doc="slew limit of the command (A/s); none = off"),
            "hold_ticks": Num(default=5, integer=True, min=0, max=1000,
                              doc="bad samples bridged with the last good one before 0 A"),
            "max_age_s": Num(default=None, optional=True, min=0.0, min_exclusive=True,
                             doc="a sample whose read took longer is late; none = off"),
            "x_range_m": Custom(_range_check, default=None, doc="[lo, hi] valid displacement (m); outside = bad sample"),
            "v_range_mps": Custom(_range_check, default=None, doc="[lo, hi] valid velocity (m/s)"),
            "F_range_N": Custom(_range_check, default=None, doc="[lo, hi] valid load-cell force (N)"),
            "require_force": Bool(default=False, doc="a non-finite load-cell force is a bad sample"),
            "fault_on_device_status": Bool(default=True, doc="device fault bits make a sample bad"),
            "auto_resume": Bool(default=False, doc="leave the fault by itself after good samples"),
            "resume_good_ticks": Num(default=10, integer=True, min=1, max=100000, doc="good samples needed to resume"),
            "driver_retries": Num(default=2, integer=True, min=0, max=10,
                                  doc="extra write attempts within a tick before the driver is lost"),
            "link_loss_s": Num(default=0.1, min=0.0, min_exclusive=True, max=60.0,
                               doc="exchange links: no good exchange for this long = driver lost, exit 3"),
            "reconnect_interval_s": Num(default=0.05, min=0.001, max=60.0,
                                        doc="exchange links: reopen a disconnected link at most this often"),
        }),
        "latency": Section({
            "lead_s": Custom(_lead_check, default=0.0,
                             doc="latency compensation: predict v this far ahead (s); 'auto' = 1.5 ticks on "
                                 "exchange links (serial, Modbus), 0 on the in-process sim. Off by default: "
                                 "not yet shown to help (docs/performance.md)"),
        }, doc="what the controller does about actuation delay (mrctl/estimation.py)"),
        "loop": Section({
            "wait": Str(default="hybrid", choices=("sleep", "hybrid", "spin"), doc="how to wait for the deadline"),
            "spin_margin_s": Num(default=3e-4, min=0.0, max=0.01, doc="hybrid: spin this long before the deadline"),
            "pacing": Str(default="host", choices=("host", "device"),
                          doc="host: the loop keeps its own deadlines; device: each exchange asks the device to "
                              "answer after its next tick (SYNC flag, docs/protocol.md), so the loop runs on the "
                              "device's clock with one tick of actuation latency (serial and Modbus links)"),
        }, doc="pacing of the real-time loop (mrctl run)"),
        "rt": Section({
            "fifo_priority": Num(default=None, optional=True, integer=True, min=1, max=99, doc="SCHED_FIFO priority; null = normal"),
            "lock_memory": Bool(default=False, doc="mlockall (needs LimitMEMLOCK)"),
            "cpus": Custom(_cpu_list, default=None, doc="CPU affinity, e.g. [1]; null = any"),
            "timer_slack_ns": Num(default=None, optional=True, integer=True, min=1, max=10**9, doc="prctl timer slack"),
            "gc_freeze": Bool(default=True, doc="gc.freeze() after start-up"),
            "gc_disable": Bool(default=True, doc="no cyclic GC during the loop"),
        }, doc="real-time settings, each applied or reported refused"),
        "record": Section({
            "flush_interval_s": Num(default=1.0, min=0.05, max=10.0, doc="fsync the log at least this often (s)"),
            "buffer_ticks": Num(default=16384, integer=True, min=256, max=10**7, doc="rows buffered before overflow"),
        }, doc="run log"),
        "service": Section({
            "status_socket": Str(default=None, optional=True, doc="Unix socket for mrctl status"),
        }),
        "plant": Section({
            "parameters": Custom(_make_params_check(base_dir), default=None,
                                 doc="the simulated damper's own parameter set (same forms as parameters); "
                                     "null = the law's set. Set it to test a law with identified parameters "
                                     "against a known damper"),
            "driver_tau_s": Num(default=0.0, min=0.0, max=1.0, doc="current-driver lag (s), 0 = ideal"),
            "sensors": Section({
                "seed": Num(default=0, integer=True, min=0, doc="noise seed (runs are reproducible)"),
                "x_noise_m": Num(default=0.0, min=0.0, doc="std dev of displacement noise (m)"),
                "v_noise_mps": Num(default=0.0, min=0.0, doc="std dev of velocity noise (m/s)"),
                "F_noise_N": Num(default=0.0, min=0.0, doc="std dev of load-cell noise (N)"),
                "x_lsb_m": Num(default=0.0, min=0.0, doc="displacement quantisation step (m), 0 = none"),
                "v_lsb_mps": Num(default=0.0, min=0.0, doc="velocity quantisation step (m/s)"),
                "F_lsb_N": Num(default=0.0, min=0.0, doc="force quantisation step (N)"),
            }),
        }, doc="simulated bench (backend sim)"),
        "backend": Union("type", {
            "sim": {},
            "serial": {
                "url": Str(doc="device path, socket://host:port or loop://"),
                "baudrate": Num(default=921600, integer=True, min=1200, max=20_000_000, doc="baud (see docs/protocol.md)"),
                "timeout_s": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=1.0,
                                 doc="reply timeout (s); null = wire time + 250 us"),
                "watchdog_ms": Num(default=50, integer=True, min=1, max=255,
                                   doc="device applies 0 A if setpoints stop this long"),
                "spin_wait": Bool(default=True, doc=SPIN_WAIT_DOC),
            },
            "modbus-tcp": {
                "host": Str(default="127.0.0.1", doc="device address"),
                "port": Num(default=502, integer=True, min=1, max=65535, doc="TCP port"),
                "unit_id": Num(default=1, integer=True, min=0, max=247, doc="Modbus unit id"),
                **modbus_common,
            },
            "modbus-rtu": {
                "url": Str(doc="serial device path (or any pyserial URL)"),
                "baudrate": Num(default=921600, integer=True, min=1200, max=20_000_000, doc="baud"),
                "parity": Str(default="E", choices=("E", "O", "N"), doc="RTU standard: E (8E1); N needs stopbits 2"),
                "stopbits": Num(default=1, min=1, max=2, doc="stop bits"),
                "rtu_local_echo": Bool(default=False, doc="an RS-485 adapter echoes our requests: read and drop them"),
                "unit_id": Num(default=1, integer=True, min=1, max=247, doc="Modbus unit id (RTU: 1-247)"),
                **modbus_common,
            },
        }, default="sim", doc="where samples come from and currents go"),
        "link": Section({
            "on_infeasible": Str(default="refuse", choices=("refuse", "reduce_rate"),
                                 doc="if the link cannot sustain rate_hz: refuse, or run slower"),
            "probe_exchanges": Num(default=50, integer=True, min=0, max=10000,
                                   doc="round trips measured at start-up (0 = wire-time estimate only)"),
        }, doc="start-up feasibility check of real links"),
    }


def _cross_checks(cfg: Node) -> list[str]:
    """Rules that span keys (each still names the key to fix)."""
    errors: list[str] = []
    I_max = cfg.safety.get("I_max") if "safety" in cfg else None
    params = cfg.get("parameters")
    if isinstance(params, LuGreParams) and isinstance(I_max, float):
        errors += [f"parameters: {e}" for e in params.check_range(I_max)]
    plant_params = cfg.plant.get("parameters") if "plant" in cfg else None
    if isinstance(plant_params, LuGreParams) and isinstance(I_max, float):
        errors += [f"plant.parameters: {e}" for e in plant_params.check_range(I_max)]
    inv = cfg.get("inverse")
    if inv is not None and inv.get("law") == "constant" and isinstance(I_max, float):
        cur = inv.get("current_A")
        if isinstance(cur, float) and cur > I_max:
            errors.append(f"inverse.current_A: {cur:g} A exceeds safety.I_max = {I_max:g} A")
    if inv is not None and inv.get("law") == "schedule" and isinstance(I_max, float):
        for i, cur in enumerate(inv.get("currents_A") or []):
            if isinstance(cur, float) and cur > I_max:
                errors.append(f"inverse.currents_A[{i}]: {cur:g} A exceeds safety.I_max = {I_max:g} A")
    loop, backend = cfg.get("loop"), cfg.get("backend")
    if loop is not None and loop.get("pacing") == "device" and backend is not None and backend.get("type") == "sim":
        errors.append("loop.pacing: 'device' needs a device with its own clock (a serial or Modbus backend); "
                      "the in-process sim bench is ticked by the loop itself")
    exc = cfg.get("excitation")
    if exc is not None and exc.get("type") == "chirp":
        f0, f1 = exc.get("f0_hz"), exc.get("f1_hz")
        if isinstance(f0, float) and isinstance(f1, float) and f1 == f0:
            errors.append("excitation.f1_hz: must differ from f0_hz (use type: sine for one frequency)")
    return errors


def validate_experiment(data: Any, base_dir: Path, source: str | None = None) -> Node:
    """Validate a parsed experiment; raises ConfigError listing every problem."""
    if not isinstance(data, dict):
        raise ConfigError([f"config: must be a mapping, got {type(data).__name__}"], source)
    # the safety section is required: a daemon must never guess a current limit
    schema = experiment_schema(base_dir)
    schema["safety"] = Section(schema["safety"].fields, optional=False)
    node, errors = _validate_fields(schema, data, "")
    if not errors:
        errors = _cross_checks(node)
    if errors:
        raise ConfigError(errors, source)
    return node


def load_experiment(path: str | Path) -> Node:
    """Load and validate an experiment YAML file."""
    p = Path(path)
    return validate_experiment(load_yaml(p), p.parent, str(p))


# --------------------------------------------------------------------------
# Reference documentation, generated from the schema (docs/config.md)
def _kind(spec: Any) -> str:
    if isinstance(spec, Num):
        kind = "integer" if spec.integer else "number"
        lo = "" if spec.min is None else (f"> {spec.min:g}" if spec.min_exclusive else f">= {spec.min:g}")
        hi = "" if spec.max is None else f"<= {spec.max:g}"
        rng = ", ".join(x for x in (lo, hi) if x)
        return kind + (f" ({rng})" if rng else "") + (" or null" if spec.optional else "")
    if isinstance(spec, Str):
        return ("one of " + ", ".join(f"`{c}`" for c in spec.choices)) if spec.choices else "string"
    if isinstance(spec, Bool):
        return "true/false"
    return "see description"


def _default(spec: Any) -> str:
    d = getattr(spec, "default", _REQUIRED)
    if d is _REQUIRED:
        return "**required**"
    return "null" if d is None else f"`{d}`"


def schema_markdown() -> str:
    """The experiment schema as markdown tables (docs/config.md's generated part)."""
    lines: list[str] = []

    def table(fields_: Mapping[str, Any], prefix: str) -> None:
        rows = [(k, v) for k, v in fields_.items() if not isinstance(v, (Section, Union))]
        if rows:
            lines.append("| key | type | default | meaning |")
            lines.append("|---|---|---|---|")
            for k, spec in rows:
                lines.append(f"| `{_path(prefix, k)}` | {_kind(spec)} | {_default(spec)} | {getattr(spec, 'doc', '')} |")
            lines.append("")
        for k, spec in fields_.items():
            path = _path(prefix, k)
            if isinstance(spec, Section):
                lines.append(f"### `{path}`" + (f": {spec.doc}" if spec.doc else ""))
                lines.append("")
                table(spec.fields, path)
            elif isinstance(spec, Union):
                lines.append(f"### `{path}`: {spec.doc}")
                lines.append("")
                lines.append(f"Chosen by `{path}.{spec.key}`" + (f" (default `{spec.default}`)" if spec.default else "") + ".")
                lines.append("")
                for name, vfields in spec.variants.items():
                    lines.append(f"#### `{path}.{spec.key}: {name}`")
                    lines.append("")
                    if vfields:
                        table(vfields, path)
                    else:
                        lines.append("(no further keys)")
                        lines.append("")

    table(experiment_schema(Path(".")), "")
    return "\n".join(lines)
