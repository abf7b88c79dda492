"""ModbusLink: what the Modbus TCP and RTU links share.

One exchange per tick writes the setpoint block and reads the sample
block(s) described by a :class:`~mrctl.io.registers.RegisterMap`:

* **FC23** (read/write multiple registers) when the map's read quantities
  are all holding registers: one request, one response per tick. The device
  performs the write before the read (Modbus spec), like the serial protocol.
* otherwise (or when the device rejects FC23) **FC16** write, then one
  **FC3/FC4** read per read block: two or more transactions per tick.

``use_fc23=None`` probes once at :meth:`~mrctl.io.base.Link.open`: an FC23
with 0 A, output disabled; an ILLEGAL_FUNCTION exception (or no answer at
all) makes the link fall back to FC16 + FC3/FC4 for good.

:class:`ModbusLink` holds what both transports share (the register map, the
tick's transactions, the probe, the safe close, decoding the sample); the
subclasses :class:`~mrctl.io.modbus.tcp.ModbusTcpLink` and
:class:`~mrctl.io.modbus.rtu.ModbusRtuLink` supply the bytes of one
transaction on their wire, and RTU its wire time. ``ModbusLink("tcp" | "rtu", **options)`` builds
the subclass for that transport (as ``pathlib.Path`` builds ``PosixPath``);
options of the other transport are ignored.

Why not pymodbus's clients on the hot path (numbers: docs/registers.md): its
synchronous serial client *sleeps* at least 1 ms twice per transaction to
detect end-of-frame silence, so 1 kHz is impossible with it; its TCP client
costs ~60 µs more per FC23 at p50 and its timeouts have millisecond
granularity. The formats are tiny and fixed (every response length is known
in advance), so this package frames MBAP/RTU itself
(:mod:`mrctl.io.modbus.codec`) and does not import pymodbus at all; the
tests check our bytes against it.

Error mapping, every exchange:

* nothing (valid) arrived by the deadline → :class:`LinkTimeout`
* bytes arrived but not a valid response: CRC, length, byte count, unit id,
  function code, MBAP protocol id, a non-finite float t_dev → :class:`FrameError`
* Modbus exception response → :class:`DeviceError` (``code`` = exception
  code, message names it, e.g. ``ILLEGAL_FUNCTION``)
* connection refused/reset/closed by peer, tty gone → :class:`Disconnected`;
  the link drops the socket/port and :meth:`open` reconnects.

A TCP response with another transaction id (the late answer to a tick that
timed out) is discarded and counted (``stale_replies``); RTU has no
transaction id, so the input is flushed before every request (a late reply
can't shift later exchanges by one).
"""

from __future__ import annotations

import abc
import math
import time
from typing import Any, ClassVar, Mapping

from mrctl.io.base import CounterUnwrap, DeviceError, FrameError, Link, LinkError, LinkTimeout, Sample, Status
from mrctl.io.modbus.codec import ILLEGAL_FUNCTION, Tx, plan_transactions
from mrctl.io.registers import RegisterMap, default_register_map

__all__ = [
    "ModbusLink",
    "DEFAULT_TCP_PORT",
    "DEFAULT_RTU_BAUD",
    "DEFAULT_TCP_TIMEOUT_S",
    "DEFAULT_WATCHDOG_MS",
    "DEFAULT_OPEN_TIMEOUT_S",
]

DEFAULT_TCP_PORT = 502
DEFAULT_RTU_BAUD = 921600
#: TCP reply deadline per tick. Loopback p99 is ~0.1-0.2 ms (docs/registers.md);
#: a real device/gateway on a LAN usually needs more: set timeout_s.
DEFAULT_TCP_TIMEOUT_S = 0.5e-3
#: Written to the watchdog register (if mapped) every tick, as the serial protocol does.
DEFAULT_WATCHDOG_MS = 50
#: Connect + FC23 probe deadline at open().
DEFAULT_OPEN_TIMEOUT_S = 1.0

_NO_LOAD_CELL = int(Status.NO_LOAD_CELL)  # plain int: IntFlag ops cost µs on the hot path
_INF = math.inf
_NAN = math.nan
_U32 = 0xFFFFFFFF


class ModbusLink(Link):
    """:class:`~mrctl.io.base.Link` over Modbus; ``ModbusLink("tcp" | "rtu", ...)``
    builds :class:`ModbusTcpLink` or :class:`ModbusRtuLink`.

    TCP: ``host``, ``port``. RTU: ``url`` = device path or pyserial URL, or an
    already-open file descriptor (int; e.g. a pty master — the link sets it
    non-blocking and does not close it), plus ``baudrate``/``parity``/``stopbits``
    (Modbus default 8E1).

    ``unit_id`` overrides the register map's. ``timeout_s`` is the deadline of
    a whole tick (all its transactions); default TCP 0.5 ms, RTU wire time +
    250 µs (≥ 0.5 ms). ``use_fc23``: True/False, or None to probe at open.
    ``watchdog_ms`` is written every tick if the map has a watchdog register.
    ``rtu_local_echo``: the RS-485 adapter echoes what we send; read it back
    and drop it before the response. ``spin_wait``: wait for a reply by
    polling (select with timeout 0) instead of sleeping in select(): busy for
    one round trip (~0.1-0.3 ms), but a thread sleeping in select() wakes up
    to ~1.5 ms late on a VM (docs/performance.md), as with the serial link.
    """

    #: "tcp" | "rtu": the subclass's wire
    transport: ClassVar[str] = ""
    #: transport → subclass (each registers itself on definition)
    _by_transport: ClassVar[dict[str, type["ModbusLink"]]] = {}
    COUNTERS = Link.COUNTERS + (
        "transactions", "crc_errors", "invalid_values", "bytes_discarded", "device_clock_resets", "fc23_fallbacks",
    )

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("transport"):  # a wire's own class, not a subclass of one (device presets)
            ModbusLink._by_transport[cls.transport] = cls

    def __new__(cls, transport: str | None = None, /, **options: Any) -> "ModbusLink":
        if cls is ModbusLink:
            sub = ModbusLink._by_transport.get(transport)  # type: ignore[arg-type]
            if sub is None:
                raise ValueError(f"transport must be 'tcp' or 'rtu', got {transport!r}")
            cls = sub
        return super().__new__(cls)

    def __init__(
        self,
        transport: str | None = None,
        /,
        *,
        host: str | None = None,
        port: int = DEFAULT_TCP_PORT,
        url: str | int | None = None,
        baudrate: int = DEFAULT_RTU_BAUD,
        parity: str = "E",
        stopbits: float = 1,
        unit_id: int | None = None,
        register_map: RegisterMap | Mapping[str, Any] | None = None,
        timeout_s: float | None = None,
        use_fc23: bool | None = None,
        watchdog_ms: float = DEFAULT_WATCHDOG_MS,
        open_timeout_s: float = DEFAULT_OPEN_TIMEOUT_S,
        safe_on_close: bool = True,
        rtu_local_echo: bool = False,
        serial_kwargs: Mapping[str, Any] | None = None,
        spin_wait: bool = True,
        gateway: bool = False,
    ) -> None:
        if transport is not None and transport != self.transport:
            raise ValueError(f"{type(self).__name__} is Modbus {self.transport.upper()}, not {transport!r}")
        rmap = _as_map(register_map, unit_id)
        if use_fc23 and not rmap.fc23_capable:
            raise ValueError(
                "use_fc23=True but the register map's read quantities are not one holding block "
                f"({rmap.describe()})"
            )
        self.register_map = rmap
        self.unit_id = rmap.unit_id
        self._configure(host=host, port=port, url=url, baudrate=baudrate, parity=parity, stopbits=stopbits,
                        rtu_local_echo=rtu_local_echo, serial_kwargs=serial_kwargs, gateway=gateway)
        if timeout_s is not None and not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self._timeout_arg = timeout_s
        self.use_fc23_config = use_fc23
        #: decided at construction (True/False) or at open() (probe); None before the probe
        self.use_fc23: bool | None = use_fc23 if use_fc23 is not None else (None if rmap.fc23_capable else False)
        super().__init__(self._default_timeout(self.use_fc23 if self.use_fc23 is not None else rmap.fc23_capable),
                         safe_on_close=safe_on_close)
        self.watchdog_ms = watchdog_ms
        rmap.encode_write(0.0, False, watchdog_ms)  # ValueError now if the watchdog doesn't fit its register
        self.open_timeout_s = float(open_timeout_s)
        self.spin_wait = bool(spin_wait)
        self._sync_bits = 0  # SYNC (bit 2 of enable) while device-paced
        self._clear_pending = False
        self._io: Any = None  # the byte transport while open
        self._txs: list[Tx] = []
        self._read_bufs: list[bytes] = [b""] * len(rmap.read_blocks)
        self._encode_write = rmap.encode_write_into
        self._decode_read = rmap.decode_read
        # counters: seq extended to 32 bits (no restarts: see CounterUnwrap), t_dev unwrapped
        seq_mod, t_mod = rmap.counter_modulus("seq"), rmap.counter_modulus("t_dev")
        self._seq_unwrap = CounterUnwrap(seq_mod, restarts=False) if seq_mod and seq_mod != 1 << 32 else None
        self._seq_local = 0  # exchanges counted when the map has no seq register
        self._clock = CounterUnwrap(t_mod) if t_mod else None
        self.last_exception_code: int | None = None

    # -- what a transport supplies ------------------------------------------------
    @abc.abstractmethod
    def _configure(self, **options: Any) -> None:
        """Check and keep the transport's own constructor options."""

    @abc.abstractmethod
    def _default_timeout(self, fc23: bool) -> float:
        """The per-tick deadline when none was given."""

    @abc.abstractmethod
    def _connect(self) -> Any:
        """Open the byte transport (raises :class:`Disconnected`)."""

    @abc.abstractmethod
    def _wrap(self, sock: Any, io: Any) -> Any:
        """An already-open transport as this link's byte transport (:meth:`_attach_transport`)."""

    @abc.abstractmethod
    def _exchange_tx(self, tx: Tx, deadline: float, wake_ns: int) -> bytes:
        """Send ``tx.adu`` (write block already packed), return the response's register bytes."""

    @abc.abstractmethod
    def _where(self) -> str:
        """The first part of :meth:`describe`."""

    @classmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "ModbusLink":
        """From the validated ``backend`` section (type modbus-tcp or modbus-rtu; a
        ``backend.device`` is the preset link's: :func:`mrctl.io.link_class_for`)."""
        sub = ModbusLink._by_transport[cfg.type.removeprefix("modbus-")]
        return sub(unit_id=cfg.unit_id, register_map=cfg.register_map, timeout_s=cfg.timeout_s,
                   use_fc23=cfg.use_fc23, watchdog_ms=cfg.watchdog_ms, open_timeout_s=cfg.open_timeout_s,
                   spin_wait=cfg.spin_wait, **sub._options(cfg))

    @classmethod
    @abc.abstractmethod
    def _options(cls, cfg: Any) -> dict[str, Any]:
        """The transport's own constructor options from the ``backend`` section."""

    # -- lifecycle -------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._io is not None

    def _open_transport(self) -> None:
        """Connect; probe FC23 if ``use_fc23`` was None (the probe's error fails open())."""
        self._io = self._connect()
        if self._seq_unwrap is not None:
            self._seq_unwrap.reset()
        try:
            if self.use_fc23_config is None and self.register_map.fc23_capable:
                self._probe()
            else:
                self._set_plan(bool(self.use_fc23))
        except BaseException:
            self._close_transport()
            raise

    def _attach_transport(self, *, use_fc23: bool, sock: Any = None, io: Any = None) -> None:
        """Use an already-open transport instead of open() (tests, benchmarks).

        ``sock``: a non-blocking socket-like object (send, recv, fileno,
        close) for TCP; ``io``: an object with ``write(data, deadline)``,
        ``read(n, deadline, max_n=0, wake_ns=0)``, ``flush_input()``,
        ``close()`` for RTU. No probe.
        """
        self._io = self._wrap(sock, io)
        self._set_plan(use_fc23)

    def _set_plan(self, fc23: bool) -> None:
        self.use_fc23 = fc23
        self.timeout_s = self._default_timeout(fc23)
        self._txs = plan_transactions(self.register_map, fc23, self.transport, self.unit_id)

    def _probe(self) -> None:
        """FC23 once (0 A, disabled); ILLEGAL_FUNCTION or silence → FC16 + FC3/FC4."""
        self._set_plan(True)
        try:
            self._requests(self._txs, time.monotonic() + self.open_timeout_s)
            return
        except DeviceError as e:
            if e.code != ILLEGAL_FUNCTION:
                raise
        except LinkTimeout:
            pass  # some devices ignore unknown functions instead of answering
        self.fc23_fallbacks += 1
        self._set_plan(False)
        self._requests(self._txs, time.monotonic() + self.open_timeout_s)

    def _send_safe(self) -> None:
        """Write 0 A with enable = 0: the tick's writing transaction only (FC23 or FC16)."""
        if self._txs:
            self._requests(self._txs[:1], time.monotonic() + max(self.timeout_s, 0.05))

    def _requests(self, txs: list[Tx], deadline: float) -> None:
        """``txs`` at 0 A, output disabled, outside exchange() (probe, close); counted as there."""
        try:
            for tx in txs:
                self._request(tx, 0.0, 0, deadline, 0)
        except LinkError as e:
            self._note_error(e)
            raise

    def _close_transport(self) -> None:
        io, self._io = self._io, None
        if io is not None:
            io.close()

    def describe(self) -> str:
        mode = {True: "FC23", False: "FC16+FC3/4", None: "FC23 (probe at open)"}[self.use_fc23]
        return f"{self._where()}, {self.register_map.describe()}, {mode}, timeout {self.timeout_s * 1e3:.3g} ms"

    # -- the tick ------------------------------------------------------------------------
    def _set_sync(self, on: bool) -> None:
        """SYNC is bit 2 of the enable register (docs/registers.md)."""
        if on and not self.register_map.has("enable"):
            raise ValueError("device pacing needs an 'enable' register in the map (its bit 2 is SYNC)")
        self._sync_bits = 4 if on else 0

    def request_clear_faults(self) -> bool:
        """Set CLEAR_FAULTS (bit 1 of the enable register) in the next exchange's write.

        Clears latched device status such as WATCHDOG_TRIPPED, like the serial
        protocol's CLEAR_FAULTS flag. False if the map has no enable register.
        """
        if not self.register_map.has("enable"):
            return False
        self._clear_pending = True
        return True

    def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Sample:
        """The tick's transactions (the first one's wait starts with a sleep
        until ``wake_ns``: device pacing), then the sample."""
        flags = (1 if self.enabled else 0) | self._sync_bits | (2 if self._clear_pending else 0)
        bufs = self._read_bufs
        for tx in self._txs:
            data = self._request(tx, current_A, flags, deadline, wake_ns)
            wake_ns = 0
            if tx.block >= 0:
                bufs[tx.block] = data
        self._clear_pending = False
        return self._to_sample()

    def _request(self, tx: Tx, current_A: float, flags: int, deadline: float, wake_ns: int) -> bytes:
        """One request/response: pack the write block (if any), exchange, count."""
        if tx.writes:
            self._encode_write(tx.adu, tx.data_off, current_A, flags, self.watchdog_ms)
        data = self._exchange_tx(tx, deadline, wake_ns)
        self.transactions += 1
        return data

    def _note_error(self, e: LinkError) -> None:
        super()._note_error(e)
        if isinstance(e, DeviceError):
            self.last_exception_code = e.code

    def _to_sample(self) -> Sample:
        seq, t_raw, x, v, F, status, I_app = self._decode_read(*self._read_bufs)
        # A well-formed reply with non-finite values is a healthy link carrying
        # bad data: return it and let the safety supervisor judge it (bad
        # sample: hold, then 0 A), as the serial backend does. Counted for the log.
        if v is None:  # no velocity register: NaN, the observer's job (sensing.velocity)
            v = _NAN
            if not x - x == 0.0:
                self.invalid_values += 1
        elif not (x - x == 0.0 and v - v == 0.0):
            self.invalid_values += 1
        if F is None:
            F = _NAN
            status = (status or 0) | _NO_LOAD_CELL
        elif F == _INF or F == -_INF:
            self.invalid_values += 1
        if status is None:
            status = 0
        elif status & _NO_LOAD_CELL:
            F = _NAN
        if I_app is None:
            I_app = _NAN
        elif I_app == _INF or I_app == -_INF:
            self.invalid_values += 1
        return Sample(self._seq_out(seq), self._t_out(t_raw), x, v, F, status, I_app)

    def _seq_out(self, seq: int | None) -> int:
        """32-bit seq: a narrower counter is extended so the safety layer's
        modulo-2**32 staleness test works across its wrap; none → count."""
        if seq is None:
            self._seq_local = (self._seq_local + 1) & _U32
            return self._seq_local
        return seq if self._seq_unwrap is None else self._seq_unwrap(seq) & _U32

    def _t_out(self, t_raw: int | float | None) -> float:
        """t_dev in seconds: an integer one unwrapped; none → the host's clock."""
        if t_raw is None:
            return time.monotonic()
        if self._clock is None:  # float32 seconds, already scaled
            if not t_raw - t_raw == 0.0:
                self.invalid_values += 1
                raise FrameError(f"t_dev decoded to {t_raw!r}")
            return t_raw
        return self.register_map.t_dev_seconds(self._clock(t_raw))


def _as_map(register_map: RegisterMap | Mapping[str, Any] | None, unit_id: int | None) -> RegisterMap:
    if register_map is None:
        rmap = default_register_map()
    elif isinstance(register_map, RegisterMap):
        rmap = register_map
    else:
        rmap = RegisterMap.from_mapping(register_map)
    if unit_id is not None and unit_id != rmap.unit_id:
        rmap = rmap.with_unit_id(unit_id)
    return rmap

