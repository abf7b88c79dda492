"""What a calibration file (``mrctl calibrate --out CAL.yaml``) may say, and how an
experiment takes it (``calibration: CAL.yaml``).

The file holds what day one on a bench measured: the volts each input
reads at rest (its offset), the noise there, and the driver+coil lag. An
experiment that names it gets, before anything else is checked:

* ``backend.channels.<role>.offset_V`` from ``channels.<role>.offset_V``;
* ``sensing.x_noise_m`` from ``noise.x_m`` (unless the experiment sets it);
* ``parameters.tau_input`` from ``driver.tau_s`` (unless the experiment sets it).

The file is checked on the schema engine, every error with its key path
(prefixed ``calibration (FILE):``).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

from mrctl.util.files import Fence
from mrctl.util.schema import ConfigError, Custom, Node, Num, Section, Str, key_repr, read_named_yaml, short_repr, \
    validate_fields

__all__ = ["CALIBRATION_VERSION", "calibration_schema", "merge_calibration", "describe_calibration"]

CALIBRATION_VERSION = 1
_ROLES = ("x", "v", "F", "current_monitor")


def _channels(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return {}, []
    if not isinstance(value, dict):
        return None, [f"{path}: must be a mapping of role -> {{offset_V, noise_V}}"]
    fields = {"offset_V": Num(default=None, optional=True, min=-20.0, max=20.0, doc="volts at rest"),
              "noise_V": Num(default=None, optional=True, min=0.0, doc="std dev at rest (V)")}
    out, errors = {}, []
    for role, sub in value.items():
        if role not in _ROLES:
            errors.append(f"{path}.{key_repr(role)}: unknown channel (allowed here: {', '.join(_ROLES)})")
            continue
        node, errs = validate_fields(fields, sub, f"{path}.{role}")
        errors += errs
        out[role] = node
    return out, errors


def calibration_schema() -> dict[str, Any]:
    """The calibration file's keys."""
    return {
        "version": Num(integer=True, min=CALIBRATION_VERSION, max=CALIBRATION_VERSION, doc="format version (1)"),
        "written_by": Str(default=None, optional=True, doc="the command and date that wrote it"),
        "device": Str(default=None, optional=True, doc="the backend.device it was measured on"),
        "channels": Custom(_channels, default=None, doc="role -> {offset_V, noise_V} at rest and 0 A"),
        "noise": Section({
            "x_m": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=0.01,
                       doc="displacement noise at rest (m): sensing.x_noise_m"),
            "F_N": Num(default=None, optional=True, min=0.0, doc="load-cell noise at rest (N)"),
        }),
        "driver": Section({
            "tau_s": Num(default=None, optional=True, min=0.0, max=1.0,
                         doc="driver+coil first-order lag (s): parameters.tau_input"),
            "delay_s": Num(default=None, optional=True, min=-1.0, max=1.0,
                           doc="dead time of a current step as the host's stamps see it (s): link and DAQ, "
                               "not the coil; below 0 when a reading is older than its stamp"),
            "steps": Num(default=None, optional=True, integer=True, min=0, doc="current steps fitted"),
        }),
    }


def _read(path: Path, raw: Any) -> Node:
    cal, errors = validate_fields(calibration_schema(), raw, "")
    if errors:
        raise ConfigError(errors)
    return cal


def merge_calibration(data: dict[str, Any], base_dir: Path, fence: Fence | None = None
                      ) -> tuple[dict[str, Any], list[str]]:
    """``data`` with its ``calibration`` file merged in (a copy), and the
    errors; the file admitted by ``fence`` (default: under ``base_dir``'s
    folder) and read without quoting it."""
    ref = data.get("calibration")
    if ref is None:
        return data, []
    if not isinstance(ref, str):
        return data, [f"calibration: must be a path to a file written by mrctl calibrate, got {short_repr(ref)}"]
    fence = fence if fence is not None else Fence.around(base_dir)
    cal, errors = read_named_yaml(ref, base_dir, fence, "calibration", _read)
    if cal is None:
        return data, errors
    path = Path(ref) if Path(ref).is_absolute() else base_dir / ref
    out = copy.deepcopy(data)
    backend = out.get("backend")
    if cal.channels:
        if not isinstance(backend, dict) or not isinstance(backend.get("channels"), dict):
            return data, [f"calibration ({path}): channel offsets, but backend.channels is not set "
                          "(a device preset's channels, docs/hardware.md)"]
        for role, node in cal.channels.items():
            ch = backend["channels"].get(role)
            if node.offset_V is None:
                continue
            if not isinstance(ch, dict):
                errors.append(f"calibration ({path}): channels.{role}: backend.channels has no {role}")
                continue
            ch["offset_V"] = node.offset_V
    if cal.device is not None and isinstance(backend, dict) and backend.get("device") not in (None, cal.device):
        errors.append(f"calibration ({path}): device: measured on {cal.device}, the experiment's "
                      f"backend.device is {backend.get('device')}")
    if cal.noise.x_m is not None:
        sensing = out.setdefault("sensing", {})
        if isinstance(sensing, dict):
            sensing.setdefault("x_noise_m", cal.noise.x_m)
    if cal.driver.tau_s is not None:
        params = out.get("parameters")
        if params is None or params == "table1":
            out["parameters"] = {"tau_input": cal.driver.tau_s}
        elif isinstance(params, str):
            out["parameters"] = {"file": params, "tau_input": cal.driver.tau_s}
        elif isinstance(params, dict):
            params.setdefault("tau_input", cal.driver.tau_s)
    return out, errors


def describe_calibration(ref: str, base_dir: Path, fence: Fence | None = None) -> str:
    """The start-up line of a run that takes ``calibration: ref``: the file
    applied (resolved against the experiment's folder) and what it set, so a
    wrong or stale file shows before the first tick."""
    path = (Path(ref) if Path(ref).is_absolute() else base_dir / ref).resolve()
    cal, errors = read_named_yaml(ref, base_dir, fence if fence is not None else Fence.around(base_dir),
                                  "calibration", _read)
    if cal is None:
        return f"calibration: {path}: " + "; ".join(errors)
    parts = [f"{role} offset {node.offset_V:.5f} V" for role, node in (cal.channels or {}).items()
             if node.offset_V is not None]
    if cal.noise.x_m is not None:
        parts.append(f"x noise {cal.noise.x_m * 1e6:.2f} um")
    if cal.driver.tau_s is not None:
        parts.append(f"driver tau {cal.driver.tau_s * 1e3:.2f} ms")
    return f"calibration: {path} applied ({', '.join(parts) or 'nothing in it'})"
