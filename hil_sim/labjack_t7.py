"""The simulated bench behind a LabJack T7's Modbus TCP registers (``--device labjack_t7``).

The register facts come from mrctl's preset (``mrctl/io/devices/labjack_t7.yaml``, itself from
LabJack's ``ljm_constants.json``); the bench's wiring (which input carries which sensor, at how
many volts per unit, with which offset; the E-stop contact; the enable monostable) is the bench
config's ``labjack_t7`` section. Served, per request:

* ``AIN#`` 0-15 (FLOAT32 at 2n): the wired sensors in volts (single-ended, or between the pair
  with ``AIN#_NEGATIVE_CH``: a sensor wired ``negative_ain`` also carries ``common_mode_V`` on both
  pins), clipped to the range; AIN14 the internal temperature sensor, AIN15 ground; every AIN of one
  request from one sample of the bench;
* ``DAC#`` (FLOAT32 at 1000 + 2n): the wired DAC drives the bench's current driver (0-5 V);
* ``DIO#`` (2000 + n), ``DIO_STATE``/``DIO_DIRECTION``/``DIO_INHIBIT``: :mod:`hil_sim.t7_io`; the
  enable line feeds a retriggerable monostable (rising edges keep the driver enabled for
  ``enable.hold_s``), the E-stop DIO reads its active level while the bench's ``estop`` fault is on;
* ``AIN#_RANGE``/``_RESOLUTION_INDEX``/``_NEGATIVE_CH``/``_SETTLING_US``, the whole watchdog
  block with ``WATCHDOG_STRICT_CLEAR`` (:mod:`hil_sim.t7_io`), ``PRODUCT_ID`` (7),
  ``FIRMWARE_VERSION``, ``CORE_TIMER`` (40 MHz from the emulator's clock, with optional drift and
  jitter; read with inputs, it stamps their conversion), ``TEST`` and ``TEST_FLOAT32``.

Functions 3, 4, 6, 16 and LabJack's Modbus Feedback (76, frames executed in order; a refused frame
ends the request with an exception, the writes before it stay done) are answered; anything else
(FC23 included) is ILLEGAL_FUNCTION; an address that is no register, a read or write that splits
a 32-bit value, a write to a read-only register or a read of a write-only one is
ILLEGAL_DATA_ADDRESS; a value the T7 does not take, a watchdog register written while the watchdog
is enabled, ILLEGAL_DATA_VALUE. Each reply leaves after the datasheet's command-response time:
``latency_s`` (A-1 "No I/O" overhead), ``latency_io_extra_s`` more with DAC/DIO writes, plus each
input's sample time at its resolution index and its settling (docs/hardware.md). At most
``max_connections`` TCP clients (2, as a T7 on port 502); the server closes a third at once.

Not emulated: streaming, the Mux80, resolution-dependent noise, LabJack's own error codes (Modbus
exception codes instead), the T7's boot time after a watchdog reset (it answers again at once).
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
from hil_sim.t7_io import SINGLE_ENDED, T7Io
from hil_sim.t7_mbfb import handle_mbfb
from hil_sim.t7_wiring import device_errors, t7_fields
from mrctl.io.devices import load_preset

__all__ = ["T7Device", "t7_fields", "device_errors"]

_MBAP = struct.Struct(">HHHB")
_HH = struct.Struct(">HH")
_HHB = struct.Struct(">HHB")
_FMT = {"float32": ">f", "uint32": ">I", "uint16": ">H"}
#: the bench's own setpoint watchdog is the T7's business here: never expire (ms)
_NO_BENCH_WATCHDOG_MS = 2**31 - 1
FC_READ_HOLDING, FC_READ_INPUT, FC_WRITE_SINGLE, FC_WRITE_MULTIPLE = 3, 4, 6, 16


class _Reg:
    __slots__ = ("name", "address", "fmt", "n", "get", "set")

    def __init__(self, name: str, address: int, dtype: str, get: Callable[[], Any] | None,
                 set_: Callable[[Any], int | None] | None) -> None:
        self.name, self.address, self.fmt = name, address, struct.Struct(_FMT[dtype])
        self.n = self.fmt.size // 2
        self.get, self.set = get, set_


class T7Device:
    """Register image + request handling of an emulated T7 over the bench.

    The same face as :class:`hil_sim.modbus_device.ModbusDevice` towards
    :class:`hil_sim.modbus_tcp.ModbusTcpInline` (``handle_tcp_frame``, ``reply_now``,
    ``counters``, ``max_connections``, ``generation``: a restart drops every connection), plus
    :meth:`check`: the watchdog and the monostable, run from the clock's idle loop."""

    def __init__(self, state: DeviceState, wiring: Any, clock_ns: Callable[[], int] = time.monotonic_ns,
                 latency_s: float | None = None) -> None:
        self.state = state
        state.estop_latches = False  # a T7 has no E-stop logic: the hard-wired chain and mrctl's latch
        self.clock_ns = clock_ns  #: the watchdog's, the monostable's and CORE_TIMER's clock (tests: a virtual one)
        self.w = wiring
        self.preset = p = load_preset("labjack_t7")
        self.latency_s = float(wiring.latency_s if latency_s is None else latency_s)
        self.latency_io_s = float(wiring.latency_io_extra_s)
        self.ain_sample_s = {int(k): float(v) for k, v in p.data["timing"]["ain_sample_s"].items()}
        self.max_connections = int(wiring.max_connections)
        self.mbfb = bool(wiring.mbfb)
        self.fc_mbfb = int(p.data["modbus"]["mbfb"])  #: Modbus Feedback's function code (the preset's)
        self.firmware = float(wiring.firmware)
        self._lock = threading.Lock()
        ain, dac, dio = p.io("ain"), p.io("dac"), p.io("dio")
        self.n_ain, self.n_dac, self.n_dio = int(ain["count"]) + 2, int(dac["count"]), int(dio["count"])
        self.ranges = [float(r) for r in ain["ranges_V"]]
        self.res_hi = int(ain["resolution_indices"][1])
        self.dac_max = float(dac["max_V"])
        self._wiring_ain: dict[int, tuple[str, float, float, float]] = {}  # AIN -> role, per, offset, common mode
        self._minus: dict[int, float] = {}  # AIN wired as a sensor's minus side -> its common-mode volts
        for role, per in (("x", "m_per_V"), ("F", "N_per_V"), ("current_monitor", "A_per_V")):
            sec = getattr(wiring, role)
            if sec is not None:
                cm = float(sec.get("common_mode_V") or 0.0)
                self._wiring_ain[int(sec.ain)] = (role, float(sec.get(per)), float(sec.offset_V), cm)
                if sec.get("negative_ain") is not None:
                    self._minus[int(sec.negative_ain)] = cm
        self.drv_dac = int(wiring.driver.dac)
        self.drv_A_per_V = float(wiring.driver.A_per_V)
        self.en_dio = None if wiring.enable is None else int(wiring.enable.dio)
        self.hold_ns = 0 if wiring.enable is None else round(float(wiring.enable.hold_s) * 1e9)
        self.es_dio = None if wiring.estop is None else int(wiring.estop.dio)
        self.es_active = 1 if wiring.estop is not None and wiring.estop.active == "high" else 0
        ct = wiring.core_timer
        self._ct_rate = 40e6 * (1.0 + float(ct.drift_ppm) * 1e-6) * 1e-9  # ticks per ns
        self._ct_jitter = float(ct.jitter_s) * 40e6
        self._rng = random.Random(int(ct.seed))
        self._t_edge_ns = 0
        self._enabled = self.en_dio is None
        #: the converter's noise (seeded: runs are reproducible); see ain_volts
        self._noise = random.Random(0x7)
        # counters and events (monotonic ns: tests compare them with their own clock)
        self.requests = self.exceptions = self.setpoints = self.frames_dropped = 0
        self.fc_counts: dict[int, int] = {}
        self.enable_drops: list[int] = []
        self.enable_rises: list[int] = []
        self.fault_counts: dict[str, int] = {}
        self._latency_now = self.latency_s
        self._req_sample: Any = None
        self._stamp_ns = 0
        pulled = {self.en_dio} if self.en_dio is not None and wiring.enable.pull_down else set()
        self.io = T7Io(self.n_ain, self.n_dac, self.n_dio, p.watchdog["registers"], clock_ns, pulled)
        self.io.external = self._external
        self.io.on_dio_change = self._dio_changed
        self.test_float32 = float(p.data["test_float32"]["default"])
        self._regs = self._build()
        self._apply()

    @property
    def generation(self) -> int:
        """Emulated restarts so far (the server drops every connection when it changes)."""
        return self.io.restarts

    @property
    def watchdog_trips(self) -> list[int]:
        return self.io.watchdog_trips

    @property
    def dac_V(self) -> list[float]:
        return self.io.dac_V

    # -- the register space ------------------------------------------------------------
    def _build(self) -> dict[int, _Reg]:
        p, io = self.preset, self.io
        ain = p.io("ain")
        regs: list[_Reg] = []

        def per_ain(key: str, name: str, arr: str, check: Callable[[int, Any], bool]) -> None:
            r = ain[key]
            for n in range(self.n_ain):
                regs.append(_Reg(f"AIN{n}_{name}", int(r["address"]) + int(r["stride"]) * n, r["type"],
                                 lambda n=n: getattr(io, arr)[n],
                                 lambda v, n=n: self._set_arr(arr, n, v, check(n, v))))

        for n in range(self.n_ain):
            regs.append(_Reg(f"AIN{n}", p.address("ain", n), "float32", lambda n=n: self.ain_volts(n), None))
        per_ain("range_register", "RANGE", "ain_range",
                lambda n, v: v == 0.0 or any(math.isclose(v, r, rel_tol=1e-6) for r in self.ranges))
        per_ain("resolution_register", "RESOLUTION_INDEX", "ain_res", lambda n, v: 0 <= v <= self.res_hi)
        per_ain("negative_register", "NEGATIVE_CH", "ain_neg",
                lambda n, v: v == SINGLE_ENDED or (n % 2 == 0 and n <= 12 and v == n + 1))
        per_ain("settling_register", "SETTLING_US", "ain_settle",
                lambda n, v: math.isfinite(v) and 0 <= v <= float(ain["settling_register"]["max_us"]))
        for n in range(self.n_dac):
            regs.append(_Reg(f"DAC{n}", p.address("dac", n), "float32", lambda n=n: io.dac_V[n],
                             lambda v, n=n: self._set_dac(n, v)))
        for n in range(self.n_dio):
            regs.append(_Reg(f"DIO{n}", p.address("dio", n), "uint16", lambda n=n: io.read_dio(n),
                             lambda v, n=n: ILLEGAL_DATA_VALUE if v not in (0, 1) else io.write_dio(n, v)))
        dio = p.io("dio")
        regs.append(_Reg("DIO_STATE", int(dio["state_register"]["address"]), "uint32", io.state_bits,
                         lambda v: io.write_state_bits(v, False)))
        regs.append(_Reg("DIO_DIRECTION", int(dio["direction_register"]["address"]), "uint32", io.direction_bits,
                         lambda v: io.write_state_bits(v, True)))
        regs.append(_Reg("DIO_INHIBIT", int(dio["inhibit_register"]["address"]), "uint32",
                         lambda: io.dio_inhibit, lambda v: setattr(io, "dio_inhibit", v)))
        wd = p.watchdog
        for k, spec in wd["registers"].items():
            regs.append(_Reg(f"WATCHDOG {k}", int(spec["address"]), spec["type"], lambda k=k: io.flash[k],
                             lambda v, k=k: self._set_wd(k, v)))
        regs.append(_Reg("WATCHDOG_STRICT_CLEAR", int(wd["strict_clear"]["address"]), "uint32", None,
                         lambda v: setattr(self, "_key_written", v)))
        for k, spec in (p.data.get("identity") or {}).items():
            regs.append(_Reg(k, int(spec["address"]), spec["type"], lambda v=spec["value"]: v, None))
        fw, ct, tf = p.data["firmware"], p.data["core_timer"], p.data["test_float32"]
        regs.append(_Reg("FIRMWARE_VERSION", int(fw["address"]), "float32", lambda: self.firmware, None))
        if self.firmware >= float(fw["min_core_timer"]):
            regs.append(_Reg("CORE_TIMER", int(ct["address"]), "uint32", self.core_timer, None))
        regs.append(_Reg("TEST", 55100, "uint32", lambda: 0x00112233, None))
        regs.append(_Reg("TEST_FLOAT32", int(tf["address"]), "float32", lambda: self.test_float32,
                         lambda v: setattr(self, "test_float32", v)))
        if self.firmware < float(fw["min"]):  # no watchdog block before its fwmin
            regs = [r for r in regs if not r.name.startswith("WATCHDOG")]
        return {r.address: r for r in regs}

    def _set_arr(self, arr: str, n: int, v: Any, ok: bool) -> int | None:
        if not ok:
            return ILLEGAL_DATA_VALUE
        getattr(self.io, arr)[n] = v
        return None

    def _set_dac(self, n: int, v: float) -> int | None:
        if not math.isfinite(v):
            return ILLEGAL_DATA_VALUE
        self.io.dac_V[n] = max(0.0, min(self.dac_max, v))  # the output saturates at its rails
        return None

    def _set_wd(self, k: str, v: Any) -> int | None:
        f = self.io.flash
        if k != "enable" and f["enable"]:
            return ILLEGAL_DATA_VALUE  # "must be disabled before writing any of the other watchdog registers"
        if k in ("enable", "strict_enable", "reset_enable", "dio_enable", "dac0_enable", "dac1_enable") \
                and v not in (0, 1):
            return ILLEGAL_DATA_VALUE
        if isinstance(v, float) and not math.isfinite(v):
            return ILLEGAL_DATA_VALUE
        f[k] = v
        self.io.flash_writes += 1
        if k == "enable" and v:
            self.io.clear()
        return None

    # -- what the pins see -----------------------------------------------------------------
    def _sample(self) -> Any:
        """The bench sample this request's inputs come from (one per request), stamping CORE_TIMER."""
        if self._req_sample is None:
            s, ns = self.state.latest_sample_ns()
            self._req_sample = s
            if ns:
                self._stamp_ns = ns
        return self._req_sample

    def _pin(self, n: int) -> float:
        wired = self._wiring_ain.get(n)
        if wired is None:
            if n in self._minus:
                return self._minus[n]
            return 1.808 if n == 14 else 0.0  # AIN14: the LM94021 at ~300 K; AIN15: ground
        role, per, off, cm = wired
        s = self._sample()
        val = s.x_m if role == "x" else s.F_N if role == "F" else s.current_A
        return cm + (off if not val - val == 0.0 else val / per + off)

    def ain_volts(self, n: int) -> float:
        """AIN n now: single-ended or against its pair, with 1 LSB rms of noise,
        in whole LSBs of 16 bits over the range, clipped to it (datasheet A-3-1:
        effective resolution below 16 bits means noise above an LSB rms; a
        constant reading is a dead input's)."""
        io = self.io
        v = self._pin(n)
        if io.ain_neg[n] != SINGLE_ENDED:
            v -= self._pin(io.ain_neg[n])
        rng = io.ain_range[n] or 10.0
        lsb = 2.0 * rng / 65536.0
        v = round((v + self._noise.gauss(0.0, lsb)) / lsb) * lsb
        return max(-rng, min(rng, v))

    def core_timer(self) -> int:
        t = (self._stamp_ns - self.io.boot_ns) * self._ct_rate
        if self._ct_jitter:
            t += self._rng.gauss(0.0, self._ct_jitter)
        return int(max(t, 0.0)) & 0xFFFFFFFF

    def _external(self, n: int) -> int | None:
        if n == self.es_dio:
            return self.es_active if self.state.estop_input else 1 - self.es_active
        return None

    def _dio_changed(self, n: int, old: int, new: int) -> None:
        if n == self.en_dio and new == 1:  # a rising edge retriggers the monostable
            self._t_edge_ns = self.clock_ns()
            if not self._enabled:
                self._enabled = True
                self.enable_rises.append(self._t_edge_ns)
                self._apply()

    def _apply(self) -> None:
        """Hand the driver's input to the bench (caller holds the lock or is the constructor)."""
        self.setpoints += 1
        I = self.io.dac_V[self.drv_dac] * self.drv_A_per_V
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
            if self.io.check():
                self._apply()

    # -- requests ---------------------------------------------------------------------------
    def counters(self) -> dict[str, Any]:
        return {"requests": self.requests, "exceptions": self.exceptions, "setpoints": self.setpoints,
                "frames_dropped": self.frames_dropped, "dac_V": list(self.io.dac_V),
                "function_counts": {str(k): v for k, v in sorted(self.fc_counts.items())},
                "watchdog_trips_ns": list(self.io.watchdog_trips), "restarts": self.io.restarts,
                "flash_writes": self.io.flash_writes, "enable_drops_ns": list(self.enable_drops),
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

    def _read(self, address: int, count: int) -> bytes | int:
        regs = self._span(address, count) if count >= 1 else None
        if regs is None or any(r.get is None for r in regs):
            return ILLEGAL_DATA_ADDRESS
        for r in regs:
            if r.name.startswith("AIN") and "_" not in r.name:
                n = int(r.name[3:])
                self._latency_now += self.ain_sample_s[self.io.ain_res[n] or 8] + self.io.ain_settle[n] * 1e-6
        return b"".join(r.fmt.pack(r.get()) for r in regs)  # type: ignore[misc]

    def _write(self, address: int, data: bytes) -> int | None:
        regs = self._span(address, len(data) // 2)
        if regs is None or any(r.set is None for r in regs):
            return ILLEGAL_DATA_ADDRESS
        off = 0
        for r in regs:
            v = r.fmt.unpack_from(data, off)[0]
            off += r.fmt.size
            err = r.set(v)  # type: ignore[misc]
            if err is not None:
                return err
            if r.name.startswith(("DAC", "DIO")):
                self._io_written = True
        return None

    def handle_pdu(self, pdu: bytes) -> bytes:
        self.requests += 1
        fc = pdu[0]
        self.fc_counts[fc] = self.fc_counts.get(fc, 0) + 1
        with self._lock:
            self._req_sample, self._stamp_ns = None, self.clock_ns()
            self._latency_now, self._io_written, self._key_written = self.latency_s, False, None
            try:
                return self._handle(fc, pdu)
            finally:
                self.io.request(self._key_written)
                if self._io_written:
                    self._latency_now += self.latency_io_s
                    self._apply()

    def _handle(self, fc: int, pdu: bytes) -> bytes:
        if fc in (FC_READ_HOLDING, FC_READ_INPUT):
            if len(pdu) != 5:
                return self._exc(fc, ILLEGAL_DATA_VALUE)
            address, count = _HH.unpack_from(pdu, 1)
            data = self._read(address, count) if count <= 125 else ILLEGAL_DATA_ADDRESS
            return self._exc(fc, data) if isinstance(data, int) else bytes((fc, len(data))) + data
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
            err = self._write(address, data)
            return self._exc(fc, err) if err is not None else bytes(echo)
        if fc == self.fc_mbfb and self.mbfb:
            return handle_mbfb(pdu, self._read, self._write, lambda code: self._exc(fc, code))
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
        """Every reply leaves its command-response time after its request (in order)."""
        lat = self._latency_now
        if lat <= 0 and not delayed:
            return adu
        due = time.monotonic() + lat
        if delayed and delayed[-1][0] > due:
            due = delayed[-1][0]
        delayed.append((due, adu))
        return None
