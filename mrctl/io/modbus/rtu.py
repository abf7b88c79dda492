"""ModbusRtuLink: the Modbus link over a serial line (RTU framing, CRC).

RTU has no transaction id: whatever is waiting before a request is a late
answer to an earlier one (or noise), so the input is flushed before every
request (one select(), ~1-2 µs; ``bytes_discarded``), or one late reply
would shift every later exchange by one. Every response length is known in
advance (FC23/FC3/FC4: 5 + 2·n, FC16: 8, exception: 5): the link reads 5
bytes (enough to tell an exception from data), then exactly the rest.
Junk before the reply is skipped by hunting for ``unit, function``. The
CRC of a request's constant prefix is computed once
(:class:`~mrctl.io.modbus.codec.Tx`); per tick only the write block's part.
"""

from __future__ import annotations

from typing import Any

from mrctl.io.base import DeviceError, FrameError, LinkTimeout, serial_device_key
from mrctl.io.modbus.codec import (
    Tx,
    crc16_modbus,
    decode_rtu_response,
    default_rtu_timeout_s,
    rtu_bits_per_char,
    rtu_transaction_wire_time_s,
)
from mrctl.io.modbus.link import ModbusLink
from mrctl.io.modbus.transport import open_rtu

__all__ = ["ModbusRtuLink"]

_MAX_HUNT_BYTES = 256  # garbage skipped before giving up on a reply


class ModbusRtuLink(ModbusLink):
    """Backend ``modbus-rtu``: ``url`` (device path, pyserial URL or an open
    fd), ``baudrate``, ``parity``, ``stopbits``, ``rtu_local_echo``,
    ``serial_kwargs``; see :class:`ModbusLink`."""

    kinds = ("modbus-rtu",)
    transport = "rtu"

    def _configure(self, *, url: str | int | None, baudrate: int, parity: str, stopbits: float,
                   rtu_local_echo: bool, serial_kwargs: Any, **_other: Any) -> None:
        if not 1 <= self.unit_id <= 247:
            raise ValueError(f"RTU unit_id must be 1..247 (0 is broadcast: no replies), got {self.unit_id}")
        if url is None or url == "":
            raise ValueError("Modbus RTU needs url (device path, pyserial URL or fd)")
        self.url = url
        self.host = None
        self.port = 0
        self.baudrate = int(baudrate)
        self.parity = str(parity).upper()
        self.stopbits = stopbits
        self.bits_per_char = rtu_bits_per_char(self.parity, stopbits)
        self.rtu_local_echo = rtu_local_echo
        self._serial_kwargs = dict(serial_kwargs or {})

    @classmethod
    def _options(cls, cfg: Any) -> dict[str, Any]:
        return {"url": cfg.url, "baudrate": cfg.baudrate, "parity": cfg.parity, "stopbits": cfg.stopbits,
                "rtu_local_echo": cfg.rtu_local_echo}

    @classmethod
    def wire_time_s(cls, cfg: Any) -> float | None:
        """Every frame of one tick plus the 3.5-character gaps (FC23 unless ``use_fc23: false``)."""
        fc23 = cfg.use_fc23 if cfg.use_fc23 is not None else True
        bits = rtu_bits_per_char(getattr(cfg, "parity", "E"), getattr(cfg, "stopbits", 1))
        return rtu_transaction_wire_time_s(cfg.register_map, cfg.baudrate, fc23, bits)

    def _default_timeout(self, fc23: bool) -> float:
        if self._timeout_arg is not None:
            return float(self._timeout_arg)
        return default_rtu_timeout_s(self.register_map, self.baudrate, fc23, self.bits_per_char)

    def device_key(self) -> str | None:
        return serial_device_key(self.url)

    def _connect(self) -> Any:
        return open_rtu(self.url, baudrate=self.baudrate, parity=self.parity, stopbits=self.stopbits,  # type: ignore[arg-type]
                        timeout_s=self.timeout_s, spin=self.spin_wait, serial_kwargs={"exclusive": True, **self._serial_kwargs})  # flock: one owner

    def _wrap(self, sock: Any, io: Any) -> Any:
        return io

    def _where(self) -> str:
        rm = self.register_map
        fc23 = bool(self.use_fc23) if self.use_fc23 is not None else rm.fc23_capable
        wire = rtu_transaction_wire_time_s(rm, self.baudrate, fc23, self.bits_per_char)
        url = f"fd {self.url}" if isinstance(self.url, int) else self.url
        return (f"modbus-rtu {url} @ {self.baudrate} Bd 8{self.parity}{self.stopbits:g} "
                f"({wire * 1e6:.0f} µs on the wire per tick)")

    def _exchange_tx(self, tx: Tx, deadline: float, wake_ns: int) -> bytes:
        io = self._io
        self.bytes_discarded += io.flush_input()
        adu = tx.adu
        n = len(adu)
        crc = crc16_modbus(memoryview(adu)[tx.crc_prefix_len : n - 2], tx.crc_prefix) if tx.writes else tx.crc_prefix
        adu[n - 2] = crc & 0xFF
        adu[n - 1] = crc >> 8
        io.write(adu, deadline)
        if self.rtu_local_echo:
            echo = io.read(n, deadline)
            if echo != adu:
                raise FrameError(f"{self.url}: local echo mismatch ({len(echo)} of {n} bytes)")
        # ≥ 5 bytes tell an exception (5 bytes long) from data; ask for the
        # whole expected reply at once (RTU: nothing can follow it).
        buf = self._hunt(io.read(5, deadline, tx.resp_len, wake_ns), tx, deadline)
        total = 5 if buf[1] & 0x80 else tx.resp_len
        if buf[0] == self.unit_id and len(buf) < total:
            buf += io.read(total - len(buf), deadline)
            if len(buf) < total:
                raise FrameError(f"{self.url}: reply truncated at {len(buf)} of {total} bytes "
                                 f"within {self.timeout_s * 1e3:.3g} ms")
        elif len(buf) > total:  # trailing junk (flushed before the next request anyway)
            self.bytes_discarded += len(buf) - total
            buf = buf[:total]
        try:
            return decode_rtu_response(buf, self.unit_id, tx.fc, tx.n_regs)
        except FrameError as e:
            if "CRC" in str(e):
                self.crc_errors += 1
            raise FrameError(f"{self.url}: {e}") from None
        except DeviceError as e:
            raise DeviceError(e.code, f"{self.url}: {e}") from None

    def _hunt(self, buf: bytes, tx: Tx, deadline: float) -> bytes:
        """Skip junk before "unit, fc" (or its exception form); ≥ 5 bytes or raise."""
        unit, fc = self.unit_id, tx.fc
        skipped = 0
        while len(buf) >= 2 and not (buf[0] == unit and (buf[1] == fc or buf[1] == fc | 0x80)):
            if skipped >= _MAX_HUNT_BYTES:
                break
            i = 1
            while i < len(buf) and buf[i] != unit:
                i += 1
            skipped += i
            buf = buf[i:]
            if len(buf) < 5:
                buf += self._io.read(5 - len(buf), deadline, tx.resp_len - len(buf))
                if len(buf) < 5:
                    break
        self.bytes_discarded += skipped
        if len(buf) < 5:
            if not buf and not skipped:
                raise LinkTimeout(f"{self.url}: no reply within {self.timeout_s * 1e3:.3g} ms")
            raise FrameError(
                f"{self.url}: incomplete reply ({len(buf)} bytes after {skipped} skipped) "
                f"within {self.timeout_s * 1e3:.3g} ms"
            )
        return buf
