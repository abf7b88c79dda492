"""What every link shares: the sample, the error tree, and the :class:`Link` base.

The python-can way: :class:`Link` owns everything that is the same on every
wire (open/close idempotence and the safe 0 A on close, the per-exchange
error counting, device pacing's deadline and wake-up, unwrapping the
device's clock, the counters), and a subclass supplies only its byte
exchange (:meth:`Link._transact`), its transport (:meth:`Link._open_transport`,
:meth:`Link._close_transport`), its wire-time estimate and a log line. The
in-process simulated bench (:mod:`mrctl.io.sim`) is a plain peer: it
subclasses the same base and says ``split = True``.

Nothing here imports pyserial or knows LuGre: links know bytes and
registers, the loop knows time, the laws know physics. Units are SI: m,
m/s, N, A, s.
"""

from __future__ import annotations

import abc
import enum
import math
import time
from typing import Any, ClassVar, NamedTuple

from mrctl.errors import LinkFailure
from mrctl.io.device_keys import network_device_key, serial_device_key

__all__ = [
    "Sample",
    "Status",
    "LinkError",
    "LinkTimeout",
    "FrameError",
    "DeviceError",
    "Disconnected",
    "Link",
    "CounterUnwrap",
    "sleep_until_ns",
    "serial_device_key",
    "network_device_key",
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
    the same way whatever the link; the serial protocol (docs/protocol.md)
    uses exactly these bit positions on the wire.
    """

    DRIVER_FAULT = 1 << 0  #: current driver reports a fault (open/short coil, overtemp)
    SENSOR_FAULT = 1 << 1  #: a DAQ channel is out of range or failed
    WATCHDOG_TRIPPED = 1 << 2  #: setpoints stopped arriving; the device applied 0 A (latched)
    OUTPUT_ENABLED = 1 << 3  #: driver output is enabled (ENABLE flag honoured, no fault)
    CURRENT_CLAMPED = 1 << 4  #: last setpoint was limited or non-finite and was clamped
    NO_LOAD_CELL = 1 << 5  #: no force channel; F_N is NaN
    RX_ERROR = 1 << 6  #: device discarded a corrupt/unknown frame since the last sample
    #: the E-stop / interlock input is open (or was, and the device's latch is not yet cleared):
    #: the device holds 0 A; a link that reads the input itself (a T7 DIO, a register) sets it
    #: while the input is at its active level (``safety.estop``, docs/hardware.md)
    ESTOP = 1 << 7

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


# ----------------------------------------------------------------------------
# errors: one root, typed by what the loop should do about them
class LinkError(LinkFailure):
    """Base of every error a link raises for link/device trouble.

    The loop catches this one type to count a missed tick; subclasses say
    whether to retry (timeout, frame), reconnect (disconnected) or alarm
    (device error). One that escapes to the CLI exits 3.
    """


class LinkTimeout(LinkError):
    """No valid reply arrived within the per-tick timeout. Retry next tick."""


class FrameError(LinkError):
    """Bytes arrived but not a valid frame (CRC, framing, length, version)."""


class DeviceError(LinkError):
    """The device answered with an error/NAK (or a Modbus exception).

    ``code`` is the link's numeric error code, kept so logs and tests can
    tell a CRC NAK from an unsupported request without parsing messages.
    """

    def __init__(self, code: int, message: str | None = None) -> None:
        self.code = int(code)
        super().__init__(message if message is not None else f"device error code {self.code}")


class Disconnected(LinkError):
    """The port/connection is gone (unplugged, peer closed, not open). Reopen."""


# ----------------------------------------------------------------------------
# device identity, for the daemon's one-owner-per-device lock (mrctl/daemon/ownership.py)
# ----------------------------------------------------------------------------
class CounterUnwrap:
    """Extends a wrapping device counter (modulus ``mod``) to a running total.

    A step forward of less than half the modulus is normal progress (also
    across the wrap); a larger one is the counter going *back*, i.e. the
    device restarted: the total restarts from the raw value and ``resets``
    counts it. With ``restarts=False`` every step is progress (a sequence
    number extended to 32 bits: a restart must not look like the sequence
    going back, which the safety layer would take for stale samples).
    ``reset()`` forgets the history (after a reopen)."""

    __slots__ = ("mod", "half", "last", "total", "resets")

    def __init__(self, mod: int, *, restarts: bool = True) -> None:
        self.mod = int(mod)
        self.half = self.mod >> 1 if restarts else self.mod
        self.last: int | None = None
        self.total = 0
        self.resets = 0

    def reset(self) -> None:
        self.last = None

    def __call__(self, raw: int) -> int:
        last = self.last
        if last is None:
            self.total = raw
        else:
            delta = (raw - last) % self.mod
            if delta < self.half:
                self.total += delta
            else:
                self.resets += 1
                self.total = raw
        self.last = raw
        return self.total


class Link(abc.ABC):
    """A link to the damper's DAQ and current driver, one transaction per tick.

    The controller relies on exactly this interface (no duck typing):

    - ``split``: True if the link can :meth:`read` and :meth:`write` within
      one tick with no latency (the in-process bench); otherwise every tick
      is one :meth:`exchange` (setpoint out, latest sample back), and the
      current computed from a sample goes out on the next tick.
    - ``host_clocked``: True if the device has no clock of its own and the
      loop tells it the tick (:meth:`begin_tick`).
    - :attr:`true_force_N`: the plant's ground-truth force on a simulated
      bench, NaN on hardware.
    - :meth:`set_device_paced`: the device's clock paces the loop (SYNC).
    - :meth:`counters`: cumulative counts for logs and metrics.

    Subclasses implement :meth:`_open_transport`, :meth:`_close_transport`,
    :attr:`is_open`, :meth:`_transact` (split links: :meth:`read` and
    :meth:`write` instead), :meth:`describe`, and the class methods
    :meth:`from_config` and (for wires whose speed limits the rate)
    :meth:`wire_time_s`. Optional hooks: :meth:`_send_safe` (the last words
    on close), :meth:`_set_sync` (device pacing), :meth:`_note_error` (extra
    bookkeeping per failed exchange; call the base), ``_clock`` (a
    :class:`CounterUnwrap` for the device's wrapping clock: reset at every
    :meth:`open`, its restarts reported as ``device_clock_resets``) and
    ``COUNTERS`` (extend the tuple; a name may be a property).
    """

    #: the ``backend.type`` names this class serves (the BACKENDS table)
    kinds: ClassVar[tuple[str, ...]] = ()
    split: ClassVar[bool] = False
    host_clocked: ClassVar[bool] = False
    #: names reported by :meth:`counters`: plain int attributes (cheap to bump
    #: per tick, set to 0 here) or read-only properties of the subclass
    COUNTERS: ClassVar[tuple[str, ...]] = (
        "exchanges", "timeouts", "frame_errors", "device_errors", "stale_replies", "disconnects",
    )
    #: the device's wrapping clock counter, if the link unwraps one
    _clock: CounterUnwrap | None = None

    def __init__(self, timeout_s: float, *, safe_on_close: bool = True) -> None:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.timeout_s = float(timeout_s)
        self.safe_on_close = safe_on_close
        #: False → setpoints go out with the output disabled (device holds 0 A)
        self.enabled = True
        #: extra named channels (SI units) beside x, v, F: one dict the link
        #: updates in place each tick (the laws' ``Measurement.channels``);
        #: its keys are fixed once the link is open (docs/laws.md)
        self.channels: dict[str, float] = {}
        cls = type(self)
        for name in self.COUNTERS:
            if not isinstance(getattr(cls, name, None), property):
                setattr(self, name, 0)
        # device pacing (set_device_paced)
        self._period_ns = 0
        self._sleep_margin_ns = 0
        self._pace_extra_s = 0.0
        self._t_reply_ns = 0  # monotonic ns of the last paced reply (0 = none yet)

    # -- construction (the BACKENDS table) ------------------------------------
    @classmethod
    @abc.abstractmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "Link":
        """Build from the validated ``backend`` section; ``context`` is the
        experiment (the sim link builds its bench from it)."""

    @classmethod
    def wire_time_s(cls, cfg: Any) -> float | None:
        """Seconds one tick occupies the wire at ``cfg``'s settings, or None
        where the wire is not the limit (TCP, in-process). Physics only: no
        link is opened, so ``mrctl check`` can report it."""
        return None

    # -- lifecycle ---------------------------------------------------------------
    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    def open(self) -> None:
        """Acquire the port/connection (idempotent). Raises :class:`Disconnected`
        (or another :class:`LinkError`) if it cannot. The device's clock is
        unwrapped afresh after every open (it may have restarted meanwhile)."""
        if self.is_open:
            return
        if self._clock is not None:
            self._clock.reset()
        self._open_transport()

    def close(self) -> None:
        """Command 0 A with the output disabled (best effort) and release the
        transport. Idempotent; never raises."""
        if not self.is_open:
            return
        try:
            if self.safe_on_close:
                self._send_safe()
        except Exception:  # noqa: BLE001 - closing must not fail on a dead link
            pass
        finally:
            self._close_transport()

    def _send_safe(self) -> None:
        """The last words on close: 0 A, output disabled. Default: one exchange."""
        enabled, self.enabled = self.enabled, False
        try:
            self.exchange(0.0)
        finally:
            self.enabled = enabled

    @abc.abstractmethod
    def _open_transport(self) -> None: ...

    @abc.abstractmethod
    def _close_transport(self) -> None:
        """Release the port/socket at once (no more bytes); never raises."""

    @abc.abstractmethod
    def describe(self) -> str:
        """One human-readable line for logs and start-up (port, rate, protocol)."""

    def device_key(self) -> str | None:
        """The device's identity for the daemon's ownership lock (two daemons
        must never drive one device): stable across the names a user may
        give it (:func:`serial_device_key`, :func:`network_device_key`); None
        for a device no other process can reach (the in-process bench)."""
        return None

    def __enter__(self) -> "Link":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the tick ----------------------------------------------------------------
    def exchange(self, current_A: float) -> Sample:
        """Write ``current_A`` (A), return the latest sample.

        Raises :class:`LinkTimeout`, :class:`FrameError`, :class:`DeviceError`
        or :class:`Disconnected`, each counted; after :class:`Disconnected`
        the transport is closed and :meth:`open` reconnects."""
        if not self.is_open:
            raise Disconnected(f"{self.describe()}: not open")
        if not -3.4e38 < current_A < 3.4e38:
            raise ValueError(f"current_A must be finite, got {current_A!r}")
        period = self._period_ns
        last = self._t_reply_ns
        deadline = time.monotonic() + self.timeout_s + self._pace_extra_s
        wake_ns = last + period - self._sleep_margin_ns if period and last else 0
        try:
            sample = self._transact(current_A, deadline, wake_ns)
        except LinkError as e:
            self._note_error(e)
            raise
        if period:
            self._t_reply_ns = time.monotonic_ns()
        self.exchanges += 1
        return sample

    def _note_error(self, e: LinkError) -> None:
        """Count a failed exchange by its type; after :class:`Disconnected`,
        release the transport. Subclasses may note more (call the base)."""
        if isinstance(e, LinkTimeout):
            self.timeouts += 1
        elif isinstance(e, FrameError):
            self.frame_errors += 1
        elif isinstance(e, DeviceError):
            self.device_errors += 1
        elif isinstance(e, Disconnected):
            self.disconnects += 1
            self._close_transport()

    def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Sample:
        """One tick's bytes: send the setpoint (with :attr:`enabled` and, when
        paced, the SYNC flag), wait for the reply until ``deadline``
        (``time.monotonic()`` s), sleeping first until ``wake_ns`` if it is
        not 0 (nothing can arrive earlier), decode it. Raise the typed
        :class:`LinkError`; the base counts it."""
        raise NotImplementedError(f"{type(self).__name__} has no exchange (a split link: read, then write)")

    def read(self) -> Sample:
        """Split links: the sample at this tick."""
        raise NotImplementedError(f"{type(self).__name__} is not a split link: use exchange()")

    def write(self, current_A: float) -> None:
        """Split links: command ``current_A`` (A) at this tick."""
        raise NotImplementedError(f"{type(self).__name__} is not a split link: use exchange()")

    def begin_tick(self, k: int) -> None:
        """Host-clocked links: the loop's tick index. Others ignore it."""

    def request_clear_faults(self) -> bool:
        """Ask the device to clear its latched status bits (``WATCHDOG_TRIPPED``,
        ``ESTOP`` once its input closed) with the next exchange: a new run's
        start and ``mrctl arm``. False if this link has no way to (the bits,
        if any, clear by themselves)."""
        return False

    def request_channels(self) -> tuple[str, ...]:
        """Find out which extra channels the device provides and fill
        :attr:`channels` (start-up, only when a law reads channels; links
        whose channels are known from the start just report them)."""
        return tuple(self.channels)

    @property
    def true_force_N(self) -> float:
        """The plant's ground-truth force at this tick (simulated benches), else NaN."""
        return math.nan

    # -- device pacing -------------------------------------------------------------
    @property
    def device_paced(self) -> bool:
        """True while every setpoint asks the device to answer after its next tick."""
        return self._period_ns != 0

    def set_device_paced(self, on: bool, period_s: float, spin_margin_s: float = 3e-4) -> None:
        """Device pacing (docs/protocol.md §6.1): every setpoint carries SYNC,
        so the device applies it at its next tick and answers after it; an
        exchange then returns at the device's next tick, and the loop runs
        on the device's clock with one tick of actuation latency. The reply
        deadline grows by one period. While waiting, the link sleeps until
        ``spin_margin_s`` before the reply is due (one period after the
        previous one), then polls. Raises ValueError if this link cannot."""
        if on and not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s!r}")
        self._set_sync(on)
        self._period_ns = round(period_s * 1e9) if on else 0
        self._pace_extra_s = float(period_s) if on else 0.0
        self._sleep_margin_ns = round(spin_margin_s * 1e9)
        self._t_reply_ns = 0

    def _set_sync(self, on: bool) -> None:
        """Turn the SYNC flag of the wire on or off; ValueError if unsupported."""
        if on:
            raise ValueError(f"{type(self).__name__} cannot be device-paced")

    # -- counters ------------------------------------------------------------------
    @property
    def device_clock_resets(self) -> int:
        """Times the device's clock went back (the device restarted?)."""
        return 0 if self._clock is None else self._clock.resets

    def counters(self) -> dict[str, int]:
        """Snapshot of every counter, for logs and metrics (not for the hot path)."""
        return {name: getattr(self, name) for name in self.COUNTERS}
