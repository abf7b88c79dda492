"""Links to the damper's DAQ and current driver, and the name table.

:data:`BACKENDS` maps every ``backend.type`` a user can write in YAML to the
class that serves it, imported only when asked for (python-can's
``BACKENDS``): ``import mrctl.io`` never pulls in pyserial. The neutral types
(:class:`~mrctl.io.base.Link`, :class:`~mrctl.io.base.Sample`, the
:class:`~mrctl.io.base.LinkError` tree) live in :mod:`mrctl.io.base`.
"""

from __future__ import annotations

import importlib

from mrctl.io.base import (
    DeviceError,
    Disconnected,
    FrameError,
    Link,
    LinkError,
    LinkTimeout,
    Sample,
    Status,
)

#: backend.type → (module, class)
BACKENDS: dict[str, tuple[str, str]] = {
    "sim": ("mrctl.io.sim", "SimLink"),
    "serial": ("mrctl.io.serial", "SerialLink"),
    "modbus-tcp": ("mrctl.io.modbus", "ModbusTcpLink"),
    "modbus-rtu": ("mrctl.io.modbus", "ModbusRtuLink"),
}
#: a backend with ``device: NAME`` (a DAQ preset, docs/hardware.md) → the preset link, whatever its type
PRESET_BACKEND: tuple[str, str] = ("mrctl.io.devices.link", "PresetLink")


def link_class(kind: str) -> type[Link]:
    """The class serving ``backend.type: kind``; KeyError names the known ones."""
    try:
        module, name = BACKENDS[kind]
    except KeyError:
        raise KeyError(f"unknown backend type {kind!r} (known: {', '.join(BACKENDS)})") from None
    return getattr(importlib.import_module(module), name)


def link_class_for(backend: object) -> type[Link]:
    """The class serving a validated ``backend`` section: the preset link for a
    ``backend.device``, else :data:`BACKENDS`' class for its type."""
    get = getattr(backend, "get", None)
    if get is not None and get("device") is not None:
        module, name = PRESET_BACKEND
        return getattr(importlib.import_module(module), name)
    return link_class(str(getattr(backend, "type")))


__all__ = [
    "BACKENDS",
    "DeviceError",
    "Disconnected",
    "FrameError",
    "Link",
    "LinkError",
    "LinkTimeout",
    "Sample",
    "Status",
    "link_class",
    "link_class_for",
]
