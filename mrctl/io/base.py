"""Backend-neutral I/O types: the sample, the error hierarchy, the interfaces.

Why a separate module: the control loop, the simulator and every hardware
backend (serial, Modbus, ...) agree on these few names and nothing else.
Backends know bytes and registers; the loop knows physics. Nothing here
imports pyserial or pymodbus, so the loop and its tests can use these types
without any hardware library installed.

Units are SI throughout: m, m/s, N, A, s.
"""

from __future__ import annotations

import enum
import math
import time
from typing import NamedTuple, Protocol, runtime_checkable

__all__ = [
    "Sample",
    "Status",
    "LinkError",
    "LinkTimeout",
    "FrameError",
    "DeviceError",
    "Disconnected",
    "Backend",
    "Daq",
    "CurrentDriver",
    "Link",
    "SplitLink",
    "sleep_until_ns",
]


def sleep_until_ns(t_ns: int) -> None:
    """Sleep until ``time.monotonic_ns()`` reaches ``t_ns`` (no-op if past).
    The links' device-paced wait: nothing can arrive before then."""
    dt = t_ns - time.monotonic_ns()
    if dt > 0:
        time.sleep(dt * 1e-9)


class Status(enum.IntFlag):
    """Device status bits carried in :attr:`Sample.status`.

    Defined here, not in a protocol module, so the loop can interpret status
    the same way whatever the backend; the serial protocol (docs/protocol.md)
    uses exactly these bit positions on the wire.
    """

    DRIVER_FAULT = 1 << 0  #: current driver reports a fault (open/short coil, overtemp)
    SENSOR_FAULT = 1 << 1  #: a DAQ channel is out of range or failed
    WATCHDOG_TRIPPED = 1 << 2  #: setpoints stopped arriving; the device applied 0 A (latched)
    OUTPUT_ENABLED = 1 << 3  #: driver output is enabled (ENABLE flag honoured, no fault)
    CURRENT_CLAMPED = 1 << 4  #: last setpoint was limited or non-finite and was clamped
    NO_LOAD_CELL = 1 << 5  #: no force channel; F_N is NaN
    RX_ERROR = 1 << 6  #: device discarded a corrupt/unknown frame since the last sample

    #: bits that mean "do not trust this sample / the actuator".
    FAULTS = DRIVER_FAULT | SENSOR_FAULT


class Sample(NamedTuple):
    """One DAQ sample as the loop sees it.

    A NamedTuple because it is created once per tick on the hot path: cheap to
    build, immutable, unpackable, no per-instance dict.
    """

    seq: int  #: device sequence number (uint32 on the serial wire, wraps)
    t_dev_s: float  #: device time of the measurement, s (monotonic on the device)
    x_m: float  #: displacement, m
    v_mps: float  #: velocity, m/s
    F_N: float  #: force, N; math.nan when the DAQ has no load cell
    status: int  #: :class:`Status` bits
    current_A: float = math.nan  #: current the driver actually applied, A (nan if unknown)


class LinkError(Exception):
    """Base of every error a backend raises for link/device trouble.

    The loop catches this one type to count a missed tick; subclasses say
    whether to retry (timeout, frame), reconnect (disconnected) or alarm
    (device error).
    """


class LinkTimeout(LinkError):
    """No valid reply arrived within the per-tick timeout. Retry next tick."""


class FrameError(LinkError):
    """Bytes arrived but not a valid frame (CRC, framing, length, version)."""


class DeviceError(LinkError):
    """The device answered with an error/NAK (or a Modbus exception).

    ``code`` is the backend's numeric error code, kept so logs and tests can
    tell a CRC NAK from an unsupported request without parsing messages.
    """

    def __init__(self, code: int, message: str | None = None) -> None:
        self.code = int(code)
        super().__init__(message if message is not None else f"device error code {self.code}")


class Disconnected(LinkError):
    """The port/connection is gone (unplugged, peer closed, not open). Reopen."""


@runtime_checkable
class Backend(Protocol):
    """Lifecycle shared by all backends: explicit open/close and a log line."""

    def open(self) -> None:
        """Acquire the port/connection. Idempotent; may raise :class:`LinkError`."""
        ...

    def close(self) -> None:
        """Release it, leaving the actuator safe (0 A) if possible. Idempotent."""
        ...

    def describe(self) -> str:
        """One human-readable line for logs/start-up (port, rate, protocol)."""
        ...


@runtime_checkable
class Daq(Backend, Protocol):
    """Something that measures x, v (and maybe F)."""

    def read(self) -> Sample:
        """Return the latest sample; raise :class:`LinkError` on failure."""
        ...


@runtime_checkable
class CurrentDriver(Backend, Protocol):
    """Something that sets the damper coil current. 0 A is the safe state."""

    def write(self, current_A: float) -> None:
        """Command ``current_A`` (A); raise :class:`LinkError` on failure."""
        ...


@runtime_checkable
class Link(Backend, Protocol):
    """One transaction per tick: send the setpoint, get the latest sample.

    Why combined: on a request/reply wire (the serial protocol) the setpoint
    and the sample travel in one round trip; splitting it into read() and
    write() would double the transactions per tick.
    """

    def exchange(self, current_A: float) -> Sample:
        """Write ``current_A`` (A), return the latest sample.

        Raises :class:`LinkTimeout`, :class:`FrameError`, :class:`DeviceError`
        or :class:`Disconnected` (all :class:`LinkError`).
        """
        ...


class SplitLink:
    """Adapts a separate :class:`Daq` and :class:`CurrentDriver` to :class:`Link`.

    Lets the loop always speak ``exchange`` even when the hardware has two
    independent channels (e.g. Modbus DAQ + analogue driver). The setpoint is
    written before the read, matching the serial protocol's ordering.
    """

    def __init__(self, daq: Daq, driver: CurrentDriver) -> None:
        self.daq = daq
        self.driver = driver

    def open(self) -> None:
        self.daq.open()
        self.driver.open()

    def close(self) -> None:
        # Driver first: make the actuator safe before anything else can fail.
        try:
            self.driver.close()
        finally:
            self.daq.close()

    def exchange(self, current_A: float) -> Sample:
        self.driver.write(current_A)
        return self.daq.read()

    def describe(self) -> str:
        return f"daq: {self.daq.describe()}; driver: {self.driver.describe()}"
