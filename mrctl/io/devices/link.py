"""PresetLink: a bought DAQ (a device preset, e.g. the LabJack T7) over Modbus TCP (docs/hardware.md).

Chosen by the backend table for a ``backend.device`` (:func:`mrctl.io.link_class_for`); it shares
the TCP byte transport (:class:`mrctl.io.modbus.transport.TcpIO`) with the register-map links, not
their class. One tick is **one request** when the device answers LabJack's Modbus Feedback
(:mod:`mrctl.io.devices.mbfb`), in this order:

1. read DAC (what the last tick wrote: the device's watchdog, or another client, changed it?);
2. write DAC (the volts of this tick's current; of 0 A while disabled);
3. write the enable output (toggled every ``enable_toggle_s`` while enabled, low otherwise);
4. write the strict watchdog's key to its clear register (only mrctl clears the watchdog);
5. read the analog inputs in use (one block); 6. read the E-stop DIO (reading ``DIO#`` keeps the
   line an input); 7. read ``CORE_TIMER`` (the sample's device time, 40 MHz).

A device that refuses MBFB (ILLEGAL_FUNCTION, or silence) gets the same operations as one FC3/FC16
each; the start-up line says which was chosen. Every reply is checked (transaction id, protocol
id, unit, function, exact length, FC3's byte count, FC16's echo); a reply to another transaction
is skipped and counted (``stale_replies``), never taken for this tick's; an impossible MBAP header
flushes the stream (``bytes_discarded``), as :class:`~mrctl.io.modbus.tcp.ModbusTcpLink` does.

At open, each value read back: the identity and firmware (too old for the watchdog block: refused,
exit 3), range, resolution index, negative channel and settling of every input in use, the enable
output low, the E-stop DIO an input, the watchdog block (strict, :mod:`mrctl.io.devices.watchdog`).
Safe close: 0 A on the DAC, the enable output low.
"""

from __future__ import annotations

import math
import struct
import time
from typing import Any

from mrctl.io.base import (
    CounterUnwrap, DeviceError, Disconnected, FrameError, Link, LinkError, LinkTimeout, Sample, Status,
    network_device_key,
)
from mrctl.io.devices import DeviceSetup
from mrctl.io.devices.mbfb import Op, Request, as_stored, mbfb_request, plain_requests
from mrctl.io.devices.setup import DeviceSetupError, identify, set_up
from mrctl.io.devices.tick import _DAC, _ENABLE, _KEY, model_period_s, tick_ops
from mrctl.io.devices.watchdog import WatchdogError, configure_watchdog, disarm_watchdog, watchdog_plan
from mrctl.io.modbus.codec import ILLEGAL_FUNCTION, exception_name
from mrctl.io.modbus.tcp import next_mbap_frame
from mrctl.io.modbus.transport import TcpIO

__all__ = ["PresetLink", "DeviceSetupError", "model_period_s"]

_NO_LOAD_CELL = int(Status.NO_LOAD_CELL)
_WD_TRIPPED = int(Status.WATCHDOG_TRIPPED)
_DRIVER_FAULT = int(Status.DRIVER_FAULT)
_ESTOP = int(Status.ESTOP)
_NAN = math.nan


class PresetLink(Link):
    """``backend: {type: modbus-tcp, device: NAME, channels: ...}``: an exchange link, one request
    per tick (MBFB), the current computed from a sample going out with the next tick's request."""

    kinds = ("modbus-tcp",)
    split = False
    COUNTERS = Link.COUNTERS + ("transactions", "bytes_discarded", "device_clock_resets", "enable_toggles",
                                "watchdog_trips", "dac_mismatches", "estop_ticks", "invalid_values")

    def __init__(self, setup: DeviceSetup, *, host: str, port: int | None = None, unit_id: int | None = None,
                 timeout_s: float | None = None, open_timeout_s: float = 1.0, spin_wait: bool = True,
                 protocol: str | None = None) -> None:
        """``protocol``: "mbfb", "plain" (FC3/FC16), or None to try MBFB at open (if the preset names
        its function code, ``modbus.mbfb``) and fall back."""
        if protocol not in (None, "mbfb", "plain"):
            raise ValueError(f"protocol must be 'mbfb', 'plain' or None, got {protocol!r}")
        super().__init__(0.01 if timeout_s is None else timeout_s)
        self.setup = setup
        p = setup.preset
        fc = p.data["modbus"].get("mbfb")
        self._fc_mbfb = None if fc is None else int(fc)  #: the device's MBFB function code; None: it has none
        if protocol == "mbfb" and fc is None:
            raise ValueError(f"protocol 'mbfb': a {p.name} has no Modbus Feedback (no modbus.mbfb in its preset)")
        self.host, self.port = host, int(p.port if port is None else port)
        self.unit_id = int(p.unit_id if unit_id is None else unit_id)
        self.open_timeout_s = float(open_timeout_s)
        self.spin_wait = bool(spin_wait)
        self.protocol_config = protocol
        self.protocol: str | None = None  #: "mbfb" | "plain", decided at open
        self.configure_on_open = True  #: False: connect and identify only (mrctl device disarm)
        self.firmware: float | None = None
        self.core_timer = False  #: CORE_TIMER read every tick (firmware 1.0071 on)
        self.setup_report: list[tuple[str, Any]] = []
        self._step = ""
        self._io: TcpIO | None = None
        self._rx = bytearray()
        self._tid = 0
        self._reqs: list[Request] = []
        self._roles: list[list[int]] = []  # per request: what each of its written values carries
        self._vals = [0.0, 0, 0]  # this tick's DAC volts, enable level, key (by role)
        self._toggle_ns = round(setup.enable_toggle_s * 1e9)
        self._level = 0
        self._t_toggle_ns = 0
        self._last_volts: float | None = None
        #: DAC volts of ticks that failed since the last sample: each may have reached the device
        #: (a reply lost or late after the write was applied), so reading one back is no mismatch
        self._unsure_volts: list[float] = []
        wd = p.watchdog
        self._key = int(wd["strict_key"]) if wd is not None else 0
        self._wd_volts = as_stored("float32", setup.dac_volts(0.0))
        self._seq_local = 0
        self._hz = float(p.data.get("core_timer", {}).get("hz", 1.0))
        # CORE_TIMER (UINT32) unwrapped: one for the link's life, so the base class forgets its last
        # value at every open and the timer going back is counted across reopens (device_clock_resets)
        self._clock = CounterUnwrap(1 << 32) if "core_timer" in p.data else None
        io = p.io("dac")
        self._vlo, self._vhi = float(io["min_V"]), float(io["max_V"])
        self._dac_per, self._dac_off = setup.dac.per_V, setup.dac.offset_V  # setup.dac_volts, inlined
        self._dac_slot: tuple[Request, struct.Struct, int] | None = None  # where the tick's DAC volts go
        ch = setup.channels
        lo, n_ain = setup.ain_block
        self._i_after_ain = 1 + n_ain  # reads: the DAC, the AIN block, then the rest
        self._estop_high = setup.estop_active_high

        def idx(role: str) -> tuple[int, float, float] | None:
            c = ch.get(role)
            return None if c is None else (c.n - lo, c.per_V, c.offset_V)

        self._x, self._v, self._F, self._I = idx("x"), idx("v"), idx("F"), idx("current_monitor")

    @classmethod
    def from_config(cls, cfg: Any, context: Any = None) -> "PresetLink":
        return cls(cfg.device, host=cfg.host, port=cfg.port, unit_id=cfg.unit_id, timeout_s=cfg.timeout_s,
                   open_timeout_s=cfg.open_timeout_s, spin_wait=cfg.spin_wait)

    @classmethod
    def wire_time_s(cls, cfg: Any) -> float | None:
        """The datasheet's model of one MBFB tick over Ethernet (``mrctl check``'s estimate)."""
        setup = getattr(cfg, "get", lambda _k: None)("device")
        return model_period_s(setup) if isinstance(setup, DeviceSetup) else None

    @classmethod
    def wire_what(cls, cfg: Any) -> str:
        s = cfg.device
        t = s.preset.data["timing"]
        return (f"{s.preset.name} over Ethernet, one MBFB request per tick (datasheet A-1/A-3-1 model: "
                f"{float(t['overhead_io_s']['ethernet']) * 1e3:g} ms + {s.ain_block[1]} AIN x "
                f"{float(t['ain_sample_s'][s.ain_resolution_index]) * 1e3:g} ms at resolution index "
                f"{s.ain_resolution_index})")

    @classmethod
    def infeasible_advice(cls, cfg: Any) -> str:
        return ("; or read fewer inputs, a lower ain_resolution_index, ain_settling_us 0; Ethernet, not WiFi "
                "(6.5 ms a request); USB is not Modbus TCP (mrctl does not speak it); for 1 kHz the reference "
                "firmware (firmware/README.md)")

    def device_key(self) -> str | None:
        return network_device_key("modbus-tcp", str(self.host), self.port, None)

    def describe(self) -> str:
        how = {"mbfb": "one MBFB request per tick", "plain": "FC3/FC16 per value (no MBFB)",
               None: "MBFB (tried at open)"}[self.protocol]
        clock = ("host clock" if not self.core_timer else "device clock CORE_TIMER"
                 if self.setup.device_time_stamps else "host clock (CORE_TIMER for staleness)")
        return (f"modbus-tcp {self.host}:{self.port}, {how}, {clock}, timeout {self.timeout_s * 1e3:.3g} ms; "
                f"{self.setup.describe()}")

    # -- the wire ----------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._io is not None

    def _close_transport(self) -> None:
        io, self._io = self._io, None
        if io is not None:
            io.close()

    def _where(self) -> str:
        return f"{self.setup.preset.name} at {self.host}:{self.port}"

    def _rpc(self, req: Request, deadline: float, wake_ns: int = 0) -> bytes:
        """Send ``req`` with the next transaction id; the reply's whole frame, checked. The usual
        case (exactly the reply, alone in one segment) is one ``startswith`` against ``req.tail``;
        anything else goes through the MBAP framing ModbusTcpLink uses (:func:`next_mbap_frame`)."""
        io = self._io
        if io is None:
            raise Disconnected(f"{self._where()}: not open")
        tid = self._tid = (self._tid + 1) & 0xFFFF
        adu = req.adu
        adu[0], adu[1] = tid >> 8, tid & 0xFF
        io.write(adu, deadline)
        self.transactions += 1
        rx = self._rx
        while True:
            frame = next_mbap_frame(self, rx, io) if len(rx) >= 6 else None
            if frame is not None:
                if frame[0] << 8 | frame[1] != tid:
                    self.stale_replies += 1  # the late answer to an earlier request
                    continue
                return self._check(frame, req)
            chunk = io.recv(deadline, wake_ns)
            wake_ns = 0
            if not chunk:
                raise LinkTimeout(f"{self._where()}: no reply to tid {tid} within {self.timeout_s * 1e3:.3g} ms")
            if not rx and len(chunk) == req.resp_len and chunk[0] << 8 | chunk[1] == tid \
                    and chunk.startswith(req.tail, 2):
                return chunk
            rx += chunk

    def _check(self, frame: bytes, req: Request) -> bytes:
        """A whole frame with this request's tid (protocol id 0 and its MBAP length: the framing saw to it)."""
        fc = req.fc
        if frame[6] != self.unit_id:
            raise FrameError(f"{self._where()}: reply from unit {frame[6]}, asked unit {self.unit_id}")
        got = frame[7]
        if got == fc | 0x80 and len(frame) >= 9:
            raise DeviceError(frame[8], f"{self._where()}: function {fc} refused: {exception_name(frame[8])}")
        if got != fc:
            raise FrameError(f"{self._where()}: reply with function {got}, asked {fc}")
        if len(frame) != req.resp_len:
            raise FrameError(f"{self._where()}: function {fc} reply of {len(frame)} bytes, expected {req.resp_len}")
        if not frame.startswith(req.tail, 2):  # FC3's byte count, FC16's echo
            raise FrameError(f"{self._where()}: function {fc} reply {frame[8:2 + len(req.tail)].hex()}, expected "
                             f"{req.tail[6:].hex()} (FC3's byte count, FC16's echoed address and count)")
        return frame

    def read_value(self, address: int, dtype: str, deadline: float | None = None) -> Any:
        """One register value (FC3), outside the tick."""
        self._step = f"reading register {address}"
        req = plain_requests([Op(False, address, dtype)], self.unit_id)[0]
        frame = self._rpc(req, deadline or time.monotonic() + self.open_timeout_s)
        return req.decode.unpack_from(frame, req.data_off)[0]  # type: ignore[union-attr]

    def write_value(self, address: int, dtype: str, value: Any, deadline: float | None = None) -> None:
        """One register value (FC16), outside the tick."""
        self._step = f"writing {value!r} to register {address}"
        req = plain_requests([Op(True, address, dtype)], self.unit_id)[0]
        st, off = req.slots[0]
        st.pack_into(req.adu, off, value)
        self._rpc(req, deadline or time.monotonic() + self.open_timeout_s)

    # -- open: set-up ----------------------------------------------------------------------------
    def _open_transport(self) -> None:
        self._io = TcpIO.connect(self.host, self.port, self.open_timeout_s, self.spin_wait)
        self._rx.clear()
        self._last_volts = None
        self._unsure_volts.clear()
        self._reqs = []
        self._step = "connecting"
        try:
            identify(self)
            if self.configure_on_open:
                set_up(self)
                self._step = "the first tick"
                self._choose_protocol()
        except DeviceSetupError:
            self._close_transport()
            raise
        except WatchdogError as e:
            self._close_transport()
            raise DeviceSetupError(f"{self._where()}: {e}") from None
        except DeviceError as e:
            self._close_transport()
            raise DeviceSetupError(f"{self._where()}: {self._step} refused ({e}): is this a "
                                   f"{self.setup.preset.name}?") from None
        except BaseException:
            self._close_transport()
            raise

    def _choose_protocol(self) -> None:
        """MBFB once at 0 A, output disabled; ILLEGAL_FUNCTION or silence: FC3/FC16 per value."""
        ops = tick_ops(self.setup, self.core_timer)
        only = [op for op, _r in ops]
        want = self.protocol_config
        if want in (None, "mbfb") and self._fc_mbfb is not None:
            self._use("mbfb", [mbfb_request(only, self.unit_id, self._fc_mbfb)], [[r for _op, r in ops if r >= 0]])
            try:
                self._tick(0.0, False, time.monotonic() + self.open_timeout_s, 0)
                return
            except DeviceError as e:
                if want == "mbfb" or e.code != ILLEGAL_FUNCTION:
                    raise
            except LinkTimeout:
                if want == "mbfb":
                    raise
            self.setup_report.append(("protocol", "MBFB refused: FC3/FC16 per value"))
        self._use("plain", plain_requests(only, self.unit_id), [[r] if r >= 0 else [] for _op, r in ops])
        self._tick(0.0, False, time.monotonic() + self.open_timeout_s, 0)

    def _use(self, protocol: str, reqs: list[Request], roles: list[list[int]]) -> None:
        self.protocol, self._reqs, self._roles = protocol, reqs, roles
        self._dac_slot = next((req, st, off) for req, rs in zip(reqs, roles)
                              for (st, off), r in zip(req.slots, rs) if r == _DAC)

    def _send_safe(self) -> None:
        """0 A on the DAC, the enable output low: the tick's request, or (not set up: device
        disarm, a failed start) the two registers written alone."""
        if self._reqs:
            super()._send_safe()
            return
        p, s = self.setup.preset, self.setup
        deadline = time.monotonic() + max(self.timeout_s, 0.05)
        self.write_value(p.address("dac", s.dac.n), "float32", s.dac_volts(0.0), deadline)
        if s.enable_dio is not None:
            self.write_value(p.address("dio", s.enable_dio), p.io("dio")["type"], 0, deadline)

    def disarm(self) -> bool:
        """The device's watchdog off in flash (``mrctl device disarm``); True if it was armed."""
        wd = self.setup.preset.watchdog
        if wd is None:
            return False
        try:
            return disarm_watchdog(wd, self.read_value, self.write_value)
        except WatchdogError as e:
            raise DeviceSetupError(f"{self._where()}: {e}") from None

    def arm_watchdog(self) -> None:
        """The strict watchdog block as :mod:`mrctl.io.devices.watchdog` plans it (at open)."""
        s, wd = self.setup, self.setup.preset.watchdog
        if wd is None:
            return
        want = watchdog_plan(wd, s.watchdog_s, s.dac.n, s.dac_volts(0.0), s.enable_dio, int(s.preset.io("dio")["count"]))
        report, written = configure_watchdog(wd, want, self.read_value, self.write_value)
        self.setup_report += [(f"WATCHDOG {k}", v) for k, v in report]
        self.setup_report.append(("WATCHDOG written", ", ".join(written) or "nothing (already as needed)"))

    # -- the tick ---------------------------------------------------------------------------------
    def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Sample:
        return self._tick(current_A, self.enabled, deadline, wake_ns)

    def _tick(self, current_A: float, enabled: bool, deadline: float, wake_ns: int) -> Sample:
        volts = (current_A if enabled else 0.0) * self._dac_per + self._dac_off
        volts = self._vlo if volts < self._vlo else self._vhi if volts > self._vhi else volts
        level = self._next_level(enabled)
        vals = self._vals
        vals[_DAC], vals[_ENABLE], vals[_KEY] = volts, level, self._key
        reads: tuple[Any, ...] = ()
        roles = self._roles
        for j, req in enumerate(self._reqs):
            adu = req.adu
            for (st, off), role in zip(req.slots, roles[j]):
                st.pack_into(adu, off, vals[role])
            frame = self._rpc(req, deadline, wake_ns)
            wake_ns = 0
            if req.decode is not None:
                got = req.decode.unpack_from(frame, req.data_off)
                reads = reads + got if reads else got  # MBFB: the one reply's tuple as it is
        if level != self._level:
            self.enable_toggles += 1
            self._level = level
        dreq, dst, doff = self._dac_slot  # type: ignore[misc]
        return self._sample(reads, dst.unpack_from(dreq.adu, doff)[0])  # the volts as written (float32)

    def _note_error(self, e: LinkError) -> None:
        """A failed tick's DAC write may have been applied (its reply lost or late): the next
        sample's read-back may show it, which is neither the device's watchdog nor another writer."""
        super()._note_error(e)
        if self._dac_slot is not None and len(self._unsure_volts) < 64:
            dreq, dst, doff = self._dac_slot
            self._unsure_volts.append(dst.unpack_from(dreq.adu, doff)[0])

    def _next_level(self, enabled: bool) -> int:
        if self.setup.enable_dio is None or not enabled:
            return 0
        now = time.monotonic_ns()
        if now - self._t_toggle_ns >= self._toggle_ns:
            self._t_toggle_ns = now
            return self._level ^ 1
        return self._level

    def _sample(self, reads: tuple[Any, ...], volts_written: float) -> Sample:
        """reads: DAC before the write, the AIN block, [E-stop DIO], [CORE_TIMER]."""
        status = 0
        prev, last = reads[0], self._last_volts
        self._last_volts = volts_written
        if last is not None and prev != last and prev not in self._unsure_volts:
            self.dac_mismatches += 1
            if prev == self._wd_volts:
                self.watchdog_trips += 1
                status |= _WD_TRIPPED  # the device's watchdog acted (or it restarted) since the last tick
            else:
                status |= _DRIVER_FAULT  # someone else writes the DAC
        if self._unsure_volts:
            self._unsure_volts.clear()
        i = self._i_after_ain
        if self.setup.estop_dio is not None:
            if (reads[i] == 1) == self._estop_high:
                status |= _ESTOP
                self.estop_ticks += 1
            i += 1
        if self.core_timer:
            raw = int(reads[i])
            seq, t = raw, self._clock(raw) / self._hz  # type: ignore[misc]
            if not self.setup.device_time_stamps:  # the timer tells stale samples; the host's clock stamps them
                t = time.monotonic()
        else:
            self._seq_local = (self._seq_local + 1) & 0xFFFFFFFF
            seq, t = self._seq_local, time.monotonic()
        x = self._phys(self._x, reads)
        v = self._phys(self._v, reads)
        F = self._phys(self._F, reads)
        if self._F is None:
            status |= _NO_LOAD_CELL
        if not (x - x == 0.0 and (self._v is None or v - v == 0.0) and (self._F is None or F - F == 0.0)):
            self.invalid_values += 1
        return Sample(seq, t, x, v, F, status, self._phys(self._I, reads))

    @staticmethod
    def _phys(ch: tuple[int, float, float] | None, reads: tuple[Any, ...]) -> float:
        if ch is None:
            return _NAN
        i, per, off = ch
        return (reads[1 + i] - off) * per
