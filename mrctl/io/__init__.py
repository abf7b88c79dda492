"""I/O backends: the neutral types live in :mod:`mrctl.io.base`.

Only the hardware-free names are re-exported here, so ``import mrctl.io``
never pulls in pyserial/pymodbus. Import backends explicitly, e.g.
``from mrctl.io.serial import SerialLink``.
"""

from mrctl.io.base import (
    Backend,
    CurrentDriver,
    Daq,
    DeviceError,
    Disconnected,
    FrameError,
    Link,
    LinkError,
    LinkTimeout,
    Sample,
    SplitLink,
    Status,
)

__all__ = [
    "Backend",
    "CurrentDriver",
    "Daq",
    "DeviceError",
    "Disconnected",
    "FrameError",
    "Link",
    "LinkError",
    "LinkTimeout",
    "Sample",
    "SplitLink",
    "Status",
]
