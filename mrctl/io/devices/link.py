"""PresetTcpLink: a Modbus TCP link to a device preset (docs/hardware.md).

The tick is the ordinary :class:`~mrctl.io.modbus.ModbusTcpLink` tick over
the register map that :func:`mrctl.io.devices.resolve_device` built from the
lab's channels (FC16 to the DAC, FC3 over the analog inputs: a T7 has no
FC23). What this class adds is what a bought DAQ needs and mrctl's own
register map does not:

* **set-up at open, each value read back**: the identity register, the range
  and resolution index of every analog input in use, the enable output low;
* **the device watchdog** (the T7's counts whole seconds and is cleared by
  any communication): on timeout the DAC goes to the volts of 0 A and the
  enable output low. Its registers are power-up defaults kept in flash, so
  they are read first and written only when they differ;
* **the enable output** (``enable_dio``): toggled every ``enable_toggle_s``
  while the output is enabled, one extra FC16 then. Wired to the driver's
  enable input through a retriggerable monostable (a charge pump), it
  disables the driver within the monostable's time when the toggling stops
  (the host died, the link hangs): faster than any device watchdog;
* **safe close**: 0 A on the DAC, then the enable output low.

No device clock and no sample counter: the sample time is the host's at
reception, ``seq`` counts exchanges (docs/hardware.md says what that costs).
"""

from __future__ import annotations

import struct
import time
from typing import Any

from mrctl.io.base import DeviceError, Disconnected, LinkError, Sample
from mrctl.io.devices import DeviceSetup
from mrctl.io.modbus.codec import FC_READ_HOLDING, FC_WRITE_MULTIPLE, Tx, read_request_pdu, write_request_pdu
from mrctl.io.modbus.tcp import ModbusTcpLink

__all__ = ["PresetTcpLink", "DeviceSetupError"]

_PACK = {"float32": struct.Struct(">f"), "uint32": struct.Struct(">I"), "uint16": struct.Struct(">H")}


class DeviceSetupError(DeviceError):
    """The device did not take (or read back) a set-up value: not the device
    the config names, or a value it refuses. Exit 3 at start-up."""

    def __init__(self, message: str) -> None:
        super().__init__(0, message)


class PresetTcpLink(ModbusTcpLink):
    """``backend: {type: modbus-tcp, device: NAME, channels: ...}``.

    A split link: the tick reads the inputs (FC3), the laws run, and the
    current goes out (FC16) in the same tick, about one command-response
    time after its sample, not one period later as with an exchange (the
    device has no combined read/write, so a tick is two requests either
    way). :meth:`exchange` (write, then read) still serves the start-up probe
    of the old kind and the safe close."""

    split = True
    COUNTERS = ModbusTcpLink.COUNTERS + ("enable_toggles",)

    def __init__(self, setup: DeviceSetup, **options: Any) -> None:
        """``setup``: the checked preset and wiring; ``options``: ModbusTcpLink's (host, port, ...)."""
        self.setup = setup
        options.setdefault("port", setup.preset.port)
        super().__init__(register_map=setup.register_map, use_fc23=setup.preset.fc23 or False,
                         watchdog_ms=0, **options)
        self._toggle_ns = round(setup.enable_toggle_s * 1e9)
        self._level = 0
        self._t_toggle_ns = 0
        self._toggle_tx: Tx | None = None
        #: what the set-up found and did, for the start-up log: (register, value read back)
        self.setup_report: list[tuple[str, Any]] = []

    @classmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "PresetTcpLink":
        return cls(cfg.device, host=cfg.host, port=cfg.port, unit_id=cfg.unit_id, timeout_s=cfg.timeout_s,
                   open_timeout_s=cfg.open_timeout_s, spin_wait=cfg.spin_wait)

    def describe(self) -> str:
        return f"{super().describe()}; {self.setup.describe()}"

    # -- register access outside the tick (set-up, close) ---------------------------
    def _tx(self, fc: int, pdu: bytes, n_regs: int) -> Tx:
        return Tx(fc, pdu, n_regs, None, False).build_tcp(self.unit_id)

    def read_value(self, address: int, dtype: str, deadline: float | None = None) -> Any:
        """One register value (FC3), outside the tick."""
        self._step = f"reading register {address}"
        st = _PACK[dtype]
        n = st.size // 2
        data = self._exchange_tx(self._tx(FC_READ_HOLDING, read_request_pdu(FC_READ_HOLDING, address, n), n),
                                 deadline or time.monotonic() + self.open_timeout_s, 0)
        self.transactions += 1
        return st.unpack(data)[0]

    def write_value(self, address: int, dtype: str, value: Any, deadline: float | None = None) -> None:
        """One register value (FC16), outside the tick."""
        self._step = f"writing {value!r} to register {address}"
        data = _PACK[dtype].pack(value)
        self._exchange_tx(self._tx(FC_WRITE_MULTIPLE, write_request_pdu(address, data), len(data) // 2),
                          deadline or time.monotonic() + self.open_timeout_s, 0)
        self.transactions += 1

    def _set(self, name: str, address: int, dtype: str, value: Any) -> None:
        """Write, read back, compare (float32 compared as float32)."""
        self.write_value(address, dtype, value)
        got = self.read_value(address, dtype)
        want = _PACK[dtype].unpack(_PACK[dtype].pack(value))[0]
        if got != want:
            raise DeviceSetupError(f"{self._where()}: {name} = {value!r} written, read back {got!r}")
        self.setup_report.append((name, got))

    # -- open: set-up ----------------------------------------------------------------------
    def _open_transport(self) -> None:
        super()._open_transport()
        self._step = "set-up"
        try:
            self._setup_device()
        except DeviceSetupError:
            self._close_transport()
            raise
        except DeviceError as e:  # the device refused a set-up register: say which, and what it means
            self._close_transport()
            raise DeviceSetupError(f"{self._where()}: {self._step} refused ({e}): is this a "
                                   f"{self.setup.preset.name}?") from None
        except BaseException:
            self._close_transport()
            raise

    def _setup_device(self) -> None:
        s, p = self.setup, self.setup.preset
        self.setup_report = []
        for name, ident in (p.data.get("identity") or {}).items():
            got = self.read_value(int(ident["address"]), ident["type"])
            if got != ident["value"]:
                raise DeviceSetupError(f"{self._where()}: {name} reads {got!r}, a {p.name} has {ident['value']!r}: "
                                       "not the device the config names")
            self.setup_report.append((name, got))
        ain = p.io("ain")
        rr, ri = ain["range_register"], ain["resolution_register"]
        for n in s.ains:
            self._set(f"AIN{n}_RANGE", int(rr["address"]) + int(rr["stride"]) * n, rr["type"], s.ain_range_V)
            self._set(f"AIN{n}_RESOLUTION_INDEX", int(ri["address"]) + int(ri["stride"]) * n, ri["type"],
                      s.ain_resolution_index)
        if s.enable_dio is not None:
            addr = p.address("dio", s.enable_dio)
            self.write_value(addr, p.io("dio")["type"], 0)  # output, low: driver disabled until we toggle
            self._toggle_tx = self._tx(FC_WRITE_MULTIPLE, write_request_pdu(addr, b"\x00\x00"), 1)
            self._level = 0
            self._t_toggle_ns = 0
        self._configure_watchdog()

    def _configure_watchdog(self) -> None:
        """Device watchdog: read what is there; if it differs from what we
        want, disable it, write the differing values, enable it; read back."""
        s, wd = self.setup, self.setup.preset.watchdog
        if wd is None:
            return
        regs = wd["registers"]
        want: dict[str, Any] = {"timeout_s": s.watchdog_s}
        dac_n = s.dac.n
        for n in (0, 1):
            if f"dac{n}_enable" in regs:
                want[f"dac{n}_enable"] = 1 if n == dac_n else 0
        want[f"dac{dac_n}_value"] = s.dac_volts(0.0)
        if s.enable_dio is not None:
            bit = 1 << s.enable_dio
            want.update(dio_enable=1, dio_state=0, dio_direction=bit, dio_inhibit=((1 << 23) - 1) & ~bit)
        else:
            want["dio_enable"] = 0

        def read(k: str) -> Any:
            return self.read_value(int(regs[k]["address"]), regs[k]["type"])

        def same(k: str, v: Any) -> bool:
            st = _PACK[regs[k]["type"]]
            return read(k) == st.unpack(st.pack(v))[0]

        differs = [k for k, v in want.items() if not same(k, v)]
        if differs or read("enable") != 1:
            self.write_value(int(regs["enable"]["address"]), regs["enable"]["type"], 0)
            for k in differs:
                self.write_value(int(regs[k]["address"]), regs[k]["type"], want[k])
            self.write_value(int(regs["enable"]["address"]), regs["enable"]["type"], 1)
        for k, v in {**want, "enable": 1}.items():
            if not same(k, v):
                raise DeviceSetupError(f"{self._where()}: watchdog {k} did not keep {v!r} "
                                       f"(read back {read(k)!r})")
            self.setup_report.append((f"WATCHDOG {k}", v))

    # -- the tick -----------------------------------------------------------------------------
    def read(self) -> Sample:
        """The tick's sample: one FC3 (FC4) per read block."""
        if self._io is None:
            raise Disconnected(f"{self.describe()}: not open")
        deadline = time.monotonic() + self.timeout_s
        bufs = self._read_bufs
        try:
            for tx in self._txs:
                if tx.block >= 0:
                    bufs[tx.block] = self._exchange_tx(tx, deadline, 0)
                    self.transactions += 1
        except LinkError as e:
            self._note_error(e)
            raise
        self.exchanges += 1
        return self._to_sample()

    def write(self, current_A: float) -> None:
        """The tick's current (FC16 to the DAC), then the enable output's toggle when due."""
        if self._io is None:
            raise Disconnected(f"{self.describe()}: not open")
        if not -3.4e38 < current_A < 3.4e38:
            raise ValueError(f"current_A must be finite, got {current_A!r}")
        deadline = time.monotonic() + self.timeout_s
        try:
            self._request(self._txs[0], current_A if self.enabled else 0.0, 1 if self.enabled else 0, deadline, 0)
            self._toggle(deadline)
        except LinkError as e:
            self._note_error(e)
            raise

    def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Sample:
        sample = super()._transact(current_A, deadline, wake_ns)
        self._toggle(deadline)
        return sample

    def _toggle(self, deadline: float) -> None:
        """Flip the enable output if ``enable_toggle_s`` has passed (held low while disabled)."""
        tx = self._toggle_tx
        if tx is not None:
            now = time.monotonic_ns()
            if now - self._t_toggle_ns >= self._toggle_ns:
                level = (self._level ^ 1) if self.enabled else 0
                if level != self._level:
                    tx.adu[-1] = level  # the register's low byte: the last byte of the FC16 request
                    self._exchange_tx(tx, deadline, 0)
                    self.transactions += 1
                    self.enable_toggles += 1
                    self._level = level
                self._t_toggle_ns = now

    def _send_safe(self) -> None:
        """0 A on the DAC, then the enable output low."""
        try:
            super()._send_safe()
        finally:
            tx = self._toggle_tx
            if tx is not None:
                tx.adu[-1] = 0
                self._exchange_tx(tx, time.monotonic() + max(self.timeout_s, 0.05), 0)
                self._level = 0
