"""``mrctl device disarm CONFIG``: a device preset's watchdog off in flash (docs/hardware.md).

The T7's watchdog block lives in its flash (``WATCHDOG_*_DEFAULT``): after ``mrctl run`` exits it
stays armed, strict, with mrctl's key, so with nobody writing the key the T7 puts DAC0 at the volts
of 0 A and the enable line low one timeout after every power-up, every time. That is what a bench
left powered wants; a lab that takes the T7 to another use disarms it here. The command takes the
same device lock as ``mrctl run`` (a running daemon's device is refused, exit 3, before a byte is
sent), connects, checks the device's identity, writes ``WATCHDOG_ENABLE_DEFAULT`` = 0 only if it is
not 0 already, reads it back, and leaves the DAC at the volts of 0 A and the enable output low.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable

from mrctl.daemon import ownership
from mrctl.errors import BadInput, LinkFailure
from mrctl.io.base import LinkError

__all__ = ["disarm"]


def disarm(exp: Any, config_path: str, say: Callable[[str], None], warn: Callable[[str], None]) -> int:
    """Disarm the watchdog of ``exp``'s device preset; exit code 0, or raises (2 no preset, 3 link)."""
    backend = exp.config.backend
    if backend.get("device") is None or not hasattr(backend.device, "preset"):
        raise BadInput(f"{config_path}: device disarm: the backend has no device preset (backend.device: "
                       "docs/hardware.md)")
    link = exp.make_link()
    if not hasattr(link, "disarm"):
        raise BadInput(f"{config_path}: device disarm: {backend.device.preset.name} has no watchdog to disarm")
    with ownership.own(link, f"mrctl device disarm {config_path}", warn) or contextlib.nullcontext():
        link.configure_on_open = False
        try:
            link.open()
            was = link.disarm()
        except LinkError as e:
            raise LinkFailure(f"device disarm: {link.describe().split(';')[0]}: {e}") from None
        finally:
            link.close()
    name = backend.device.preset.name
    say(f"{name} at {backend.host}:{link.port}: watchdog " + ("disarmed (WATCHDOG_ENABLE_DEFAULT 1 -> 0, read back 0)"
                                                             if was else "was not armed (WATCHDOG_ENABLE_DEFAULT "
                                                                         "reads 0; nothing written)"))
    return 0
