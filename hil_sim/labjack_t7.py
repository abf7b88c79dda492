"""The simulated bench behind a LabJack T7's Modbus TCP registers (``--device labjack_t7``).

The register facts come from mrctl's preset (``mrctl/io/devices/labjack_t7.yaml``,
itself from LabJack's ``ljm_constants.json``); what the bench's wiring is
(which input carries which sensor, at how many volts per unit, with which
offset) is the bench config's ``labjack_t7`` section, so a calibration has
true offsets to find. Served, per tick of the bench's clock:

* ``AIN#`` (FLOAT32 at 2n): the bench's sensors in volts through the wiring,
  clipped to the input's range; unwired inputs read 0 V;
* ``DAC#`` (FLOAT32 at 1000 + 2n): the wired DAC drives the bench's current
  driver (``driver.A_per_V``, 0-5 V; the output saturates there);
* ``DIO#`` (UINT16 at 2000 + n): 0/1; the wired enable line feeds a
  retriggerable monostable triggered by rising edges: the driver is enabled
  while they come within ``enable.hold_s``, off otherwise (a line left high
  or driven low by the watchdog does not keep it on);
* ``AIN#_RANGE``, ``AIN#_RESOLUTION_INDEX``, the ``WATCHDOG_*_DEFAULT``
  registers, ``PRODUCT_ID`` (7) and ``TEST`` (0x00112233).

What a T7 refuses is refused: FC23 and any function but 3, 4, 6, 16
(ILLEGAL_FUNCTION); an address that is no register, a read or write that
splits a 32-bit value, a write to a read-only register (ILLEGAL_DATA_ADDRESS);
a range, resolution index, DIO level or non-finite DAC value the T7 does not
take, a watchdog register written while the watchdog is enabled
(ILLEGAL_DATA_VALUE). The watchdog: any request clears its timer; after
``WATCHDOG_TIMEOUT_S_DEFAULT`` whole seconds of silence the enabled actions
happen (DAC to its value, DIO lines to their state). Every reply leaves
``latency_s`` after its request (a T7's command-response time, docs/hardware.md).

Not emulated: streaming, the Mux80, resolution-dependent noise and
conversion time (the latency is one figure), LabJack's own error codes
(Modbus exception codes instead), the watchdog's strict mode.
"""

from __future__ import annotations

import math
import random
import struct
import threading
import time
from collections import deque
from typing import Any, Callable

from hil_sim.modbus_wire import ILLEGAL_DATA_ADDRESS, ILLEGAL_DATA_VALUE, ILLEGAL_FUNCTION
from hil_sim.state import DeviceState
from mrctl.io.devices import load_preset
from mrctl.util.schema import Custom, Num, Section

__all__ = ["T7Device", "t7_fields"]

_MBAP = struct.Struct(">HHHB")
_HH = struct.Struct(">HH")
_HHB = struct.Struct(">HHB")
_FMT = {"float32": ">f", "uint32": ">I", "uint16": ">H"}
#: the bench's own setpoint watchdog is the T7's business here: never expire (ms)
_NO_BENCH_WATCHDOG_MS = 2**31 - 1
FC_READ_HOLDING, FC_READ_INPUT, FC_WRITE_SINGLE, FC_WRITE_MULTIPLE = 3, 4, 6, 16


def _optional_section(fields: dict[str, Any], what: str) -> Custom:
    from mrctl.util.schema import validate_fields

    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if value is None:
            return None, []
        return validate_fields(fields, value, path)

    return Custom(check, default=None, doc=what)


def t7_fields() -> dict[str, Any]:
    """The bench config's ``labjack_t7`` section: the bench's wiring to the emulated T7."""

    def ain(per: str, off: float) -> Section:
        return Section({"ain": Num(integer=True, min=0, max=13, doc="AIN number"),
                        per: Num(doc="physical units per volt"),
                        "offset_V": Num(default=off, doc="volts at zero (what mrctl calibrate finds)")})

    return {
        "latency_s": Num(default=0.001, min=0.0, max=0.1, doc="command-response time per request (s)"),
        "x": ain("m_per_V", 2.5),
        "F": ain("N_per_V", 0.0),
        "current_monitor": _optional_section({
            "ain": Num(integer=True, min=0, max=13), "A_per_V": Num(), "offset_V": Num(default=0.0)},
            "the driver's current-monitor output on an AIN; null = not wired"),
        "driver": Section({"dac": Num(default=0, integer=True, min=0, max=1, doc="DAC driving the driver"),
                           "A_per_V": Num(default=0.4, min=0.0, min_exclusive=True,
                                          doc="driver gain: 0-5 V in -> 0-2 A out at 0.4")}),
        "enable": _optional_section({
            "dio": Num(integer=True, min=0, max=22, doc="DIO into the monostable"),
            "hold_s": Num(default=0.04, min=0.0, min_exclusive=True, max=1.0,
                          doc="monostable time: the driver stays enabled this long after an edge")},
            "the driver's enable input through a retriggerable monostable; null = not wired (always enabled)"),
    }


def device_errors(args: Any, cfg: Any) -> list[str]:
    """Why ``python -m hil_sim --device labjack_t7 ...`` cannot start (empty: it can)."""
    errors = []
    if args.transport != "modbus-tcp":
        errors.append(f"--device {args.device}: needs --transport modbus-tcp")
    if args.serve != "inline":
        errors.append(f"--device {args.device}: needs --serve inline (its timers run in the clock's idle loop)")
    if cfg.t7 is None:
        errors.append(f"--device {args.device}: the config has no labjack_t7 section (the bench's wiring)")
    if args.latency_s is not None and not 0 <= args.latency_s <= 0.1:
        errors.append(f"--latency-s: must be 0-0.1 s, got {args.latency_s}")
    return errors


class _Reg:
    __slots__ = ("name", "address", "fmt", "n", "get", "set")

    def __init__(self, name: str, address: int, dtype: str, get: Callable[[], Any],
                 set_: Callable[[Any], int | None] | None) -> None:
        self.name, self.address, self.fmt = name, address, struct.Struct(_FMT[dtype])
        self.n = self.fmt.size // 2
        self.get, self.set = get, set_


class T7Device:
    """Register image + request handling of an emulated T7 over the bench.

    The same face as :class:`hil_sim.modbus_device.ModbusDevice` towards
    :class:`hil_sim.modbus_tcp.ModbusTcpInline` (``handle_tcp_frame``,
    ``reply_now``, ``counters``), plus :meth:`check`: the watchdog and the
    monostable, run from the clock's idle loop."""

    def __init__(self, state: DeviceState, wiring: Any, clock_ns: Callable[[], int] = time.monotonic_ns,
                 latency_s: float | None = None) -> None:
        self.state = state
        state.estop_latches = False  # a T7 has no E-stop logic: the hard-wired chain and mrctl's latch
        self.clock_ns = clock_ns  #: the watchdog's and the monostable's clock (tests: a virtual one)
        self.w = wiring
        self.preset = p = load_preset("labjack_t7")
        self.latency_s = float(wiring.latency_s if latency_s is None else latency_s)
        self._lock = threading.Lock()
        ain, dac, dio = p.io("ain"), p.io("dac"), p.io("dio")
        self.n_ain, self.n_dac, self.n_dio = int(ain["count"]), int(dac["count"]), int(dio["count"])
        self.ranges = [float(r) for r in ain["ranges_V"]]
        self.res_lo, self.res_hi = ain["resolution_indices"]
        self.dac_max = float(dac["max_V"])
        self.ain_range = [0.0] * self.n_ain  # 0 = default (+/-10 V)
        self.ain_res = [0] * self.n_ain
        self.dac_V = [0.0] * self.n_dac
        self.dio = [0] * self.n_dio
        self.wd: dict[str, Any] = {k: (0.0 if v["type"] == "float32" else 0) for k, v in
                                   p.watchdog["registers"].items()}
        self._wiring_ain: dict[int, tuple[str, float, float]] = {}
        for role, per in (("x", "m_per_V"), ("F", "N_per_V"), ("current_monitor", "A_per_V")):
            sec = getattr(wiring, role)
            if sec is not None:
                self._wiring_ain[int(sec.ain)] = (role, float(sec.get(per)), float(sec.offset_V))
        self.drv_dac = int(wiring.driver.dac)
        self.drv_A_per_V = float(wiring.driver.A_per_V)
        self.en_dio = None if wiring.enable is None else int(wiring.enable.dio)
        self.hold_ns = 0 if wiring.enable is None else round(float(wiring.enable.hold_s) * 1e9)
        self._t_edge_ns = 0
        self._enabled = self.en_dio is None
        self._last_comm_ns = clock_ns()
        self._tripped = False
        #: the converter's noise (seeded: runs are reproducible); see ain_volts
        self._noise = random.Random(0x7)
        self._regs = self._build()
        # counters and events (monotonic ns: tests compare them with their own clock)
        self.requests = self.exceptions = self.setpoints = self.frames_dropped = 0
        self.watchdog_trips: list[int] = []
        self.enable_drops: list[int] = []
        self.enable_rises: list[int] = []
        self.fault_counts: dict[str, int] = {}
        self._apply()

    # -- the register space ------------------------------------------------------------
    def _build(self) -> dict[int, _Reg]:
        p = self.preset
        regs: list[_Reg] = []
        for n in range(self.n_ain):
            regs.append(_Reg(f"AIN{n}", p.address("ain", n), "float32", lambda n=n: self.ain_volts(n), None))
            rr, ri = p.io("ain")["range_register"], p.io("ain")["resolution_register"]
            regs.append(_Reg(f"AIN{n}_RANGE", int(rr["address"]) + int(rr["stride"]) * n, "float32",
                             lambda n=n: self.ain_range[n], lambda v, n=n: self._set_range(n, v)))
            regs.append(_Reg(f"AIN{n}_RESOLUTION_INDEX", int(ri["address"]) + int(ri["stride"]) * n, "uint16",
                             lambda n=n: self.ain_res[n], lambda v, n=n: self._set_res(n, v)))
        for n in range(self.n_dac):
            regs.append(_Reg(f"DAC{n}", p.address("dac", n), "float32", lambda n=n: self.dac_V[n],
                             lambda v, n=n: self._set_dac(n, v)))
        for n in range(self.n_dio):
            regs.append(_Reg(f"DIO{n}", p.address("dio", n), "uint16", lambda n=n: self.dio[n],
                             lambda v, n=n: self._set_dio(n, v)))
        for k, spec in p.watchdog["registers"].items():
            regs.append(_Reg(f"WATCHDOG {k}", int(spec["address"]), spec["type"], lambda k=k: self.wd[k],
                             lambda v, k=k: self._set_wd(k, v)))
        for k, spec in (p.data.get("identity") or {}).items():
            regs.append(_Reg(k, int(spec["address"]), spec["type"], lambda v=spec["value"]: v, None))
        regs.append(_Reg("TEST", 55100, "uint32", lambda: 0x00112233, None))
        return {r.address: r for r in regs}

    def ain_volts(self, n: int) -> float:
        """What AIN n reads now: the wired sensor in volts (an unwired input: 0 V),
        with the converter's noise, quantised to its 16 bits over the range and
        clipped to it. LabJack's T-series datasheet, A-3-1 "Noise and
        Resolution": a 16-bit ADC over +/-10 V has an LSB of 0.305 mV, and the
        effective resolution (from the RMS noise) is below the converter's 16
        bits, so the noise is at least an LSB RMS: modelled as exactly that, the
        kindest the device can be (a constant reading is a dead input's)."""
        rng = self.ain_range[n] or 10.0
        lsb = 2.0 * rng / 65536.0
        wired = self._wiring_ain.get(n)
        v = 0.0
        if wired is not None:
            role, per, off = wired
            s = self.state.latest_sample()
            val = s.x_m if role == "x" else s.F_N if role == "F" else s.current_A
            v = off if not val - val == 0.0 else val / per + off
        v = round((v + self._noise.gauss(0.0, lsb)) / lsb) * lsb
        return max(-rng, min(rng, v))

    def _set_range(self, n: int, v: float) -> int | None:
        if v != 0.0 and not any(math.isclose(v, r, rel_tol=1e-6) for r in self.ranges):
            return ILLEGAL_DATA_VALUE
        self.ain_range[n] = v
        return None

    def _set_res(self, n: int, v: int) -> int | None:
        if v != 0 and not self.res_lo <= v <= self.res_hi:
            return ILLEGAL_DATA_VALUE
        self.ain_res[n] = v
        return None

    def _set_dac(self, n: int, v: float) -> int | None:
        if not math.isfinite(v):
            return ILLEGAL_DATA_VALUE
        self.dac_V[n] = max(0.0, min(self.dac_max, v))  # the output saturates at its rails
        if n == self.drv_dac:
            self._apply()
        return None

    def _set_dio(self, n: int, v: int) -> int | None:
        if v not in (0, 1):
            return ILLEGAL_DATA_VALUE
        if n == self.en_dio and v == 1 and self.dio[n] == 0:  # a rising edge retriggers the monostable
            self._t_edge_ns = self.clock_ns()
            if not self._enabled:
                self._enabled = True
                self.enable_rises.append(self._t_edge_ns)
                self.dio[n] = v
                self._apply()
        self.dio[n] = v
        return None

    def _set_wd(self, k: str, v: Any) -> int | None:
        if k != "enable" and self.wd["enable"]:
            return ILLEGAL_DATA_VALUE  # "must be disabled before writing any of the other watchdog registers"
        if k == "enable" and v not in (0, 1):
            return ILLEGAL_DATA_VALUE
        self.wd[k] = v
        return None

    def _apply(self) -> None:
        """Hand the driver's input to the bench (caller holds the lock or is the constructor)."""
        self.setpoints += 1
        I = self.dac_V[self.drv_dac] * self.drv_A_per_V
        self.state.set_setpoint(I, self._enabled, watchdog_ms=_NO_BENCH_WATCHDOG_MS)

    # -- timers: the watchdog and the monostable (the clock's idle loop) -----------------
    def poll_with(self, serve: Callable[[], object]) -> Callable[[], None]:
        """The clock's idle work: serve requests, then run the timers."""
        check = self.check

        def poll() -> None:
            serve()
            check()

        return poll

    def check(self) -> None:
        now = self.clock_ns()
        with self._lock:
            if self.en_dio is not None and self._enabled and now - self._t_edge_ns > self.hold_ns:
                self._enabled = False
                self.enable_drops.append(now)
                self._apply()
            wd = self.wd
            if wd["enable"] and not self._tripped and wd["timeout_s"] > 0 \
                    and now - self._last_comm_ns > wd["timeout_s"] * 1_000_000_000:
                self._tripped = True
                self.watchdog_trips.append(now)
                for n in range(self.n_dac):
                    if wd.get(f"dac{n}_enable"):
                        self.dac_V[n] = max(0.0, min(self.dac_max, float(wd[f"dac{n}_value"])))
                if wd.get("dio_enable"):
                    mask = int(wd["dio_direction"]) & ~int(wd["dio_inhibit"])
                    for n in range(self.n_dio):
                        if mask >> n & 1:
                            self._set_dio(n, int(wd["dio_state"]) >> n & 1)
                self._apply()

    # -- requests ---------------------------------------------------------------------------
    def counters(self) -> dict[str, Any]:
        return {"requests": self.requests, "exceptions": self.exceptions, "setpoints": self.setpoints,
                "frames_dropped": self.frames_dropped, "dac_V": list(self.dac_V),
                "watchdog_trips_ns": list(self.watchdog_trips), "enable_drops_ns": list(self.enable_drops),
                "enable_rises_ns": list(self.enable_rises)}

    def _exc(self, fc: int, code: int) -> bytes:
        self.exceptions += 1
        return bytes(((fc | 0x80) & 0xFF, code))

    def _span(self, address: int, count: int) -> list[_Reg] | None:
        out, a, end = [], address, address + count
        while a < end:
            r = self._regs.get(a)
            if r is None or a + r.n > end:
                return None
            out.append(r)
            a += r.n
        return out

    def handle_pdu(self, pdu: bytes) -> bytes:
        self.requests += 1
        fc = pdu[0]
        with self._lock:
            self._last_comm_ns = self.clock_ns()
            self._tripped = False
            if fc in (FC_READ_HOLDING, FC_READ_INPUT):
                if len(pdu) != 5:
                    return self._exc(fc, ILLEGAL_DATA_VALUE)
                address, count = _HH.unpack_from(pdu, 1)
                regs = self._span(address, count) if 1 <= count <= 125 else None
                if regs is None:
                    return self._exc(fc, ILLEGAL_DATA_ADDRESS)
                data = b"".join(r.fmt.pack(r.get()) for r in regs)
                return bytes((fc, len(data))) + data
            if fc == FC_WRITE_SINGLE or fc == FC_WRITE_MULTIPLE:
                if fc == FC_WRITE_SINGLE:
                    if len(pdu) != 5:
                        return self._exc(fc, ILLEGAL_DATA_VALUE)
                    address, data, echo = _HH.unpack_from(pdu, 1)[0], pdu[3:5], pdu
                else:
                    if len(pdu) < 6:
                        return self._exc(fc, ILLEGAL_DATA_VALUE)
                    address, count, bc = _HHB.unpack_from(pdu, 1)
                    if bc != 2 * count or len(pdu) != 6 + bc or not 1 <= count <= 123:
                        return self._exc(fc, ILLEGAL_DATA_VALUE)
                    data, echo = pdu[6:], pdu[:5]
                regs = self._span(address, len(data) // 2)
                if regs is None or any(r.set is None for r in regs):
                    return self._exc(fc, ILLEGAL_DATA_ADDRESS)
                off = 0
                for r in regs:
                    v = r.fmt.unpack_from(data, off)[0]
                    off += r.fmt.size
                    err = r.set(v)
                    if err is not None:
                        return self._exc(fc, err)
                return bytes(echo)
            return self._exc(fc, ILLEGAL_FUNCTION)

    def handle_tcp_frame(self, frame: bytes | bytearray) -> bytes | None:
        """Response ADU for one complete MBAP frame (a T7 answers whatever unit id)."""
        if len(frame) < 8:
            return None
        tid, _pid, _length, unit = _MBAP.unpack_from(frame, 0)
        try:
            resp = self.handle_pdu(bytes(frame[7:]))
        except Exception:  # noqa: BLE001 - a device answers, it does not die
            resp = self._exc(frame[7], 0x04)
        return _MBAP.pack(tid, 0, len(resp) + 1, unit) + resp

    def reply_now(self, adu: bytes, tcp: bool, delayed: deque) -> bytes | None:
        """Every reply leaves ``latency_s`` after its request (in order)."""
        if self.latency_s <= 0 and not delayed:
            return adu
        due = time.monotonic() + self.latency_s
        if delayed and delayed[-1][0] > due:
            due = delayed[-1][0]
        delayed.append((due, adu))
        return None
