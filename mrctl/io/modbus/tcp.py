"""ModbusTcpLink: the Modbus link over TCP (MBAP framing, transaction ids).

A request's frame is precompiled (:class:`~mrctl.io.modbus.codec.Tx`); per
transaction the link patches the next transaction id into it, sends it and
reads until the response with that id. Responses with another id (the late
answer to a tick that timed out) are skipped and counted
(``stale_replies``); an impossible MBAP header flushes the stream
(``bytes_discarded``) and is a :class:`~mrctl.io.base.FrameError`. The
usual case (exactly the expected response in one segment, nothing
buffered) is one slice compare against the precomputed reply header.
"""

from __future__ import annotations

from typing import Any

from mrctl.io.base import FrameError, LinkTimeout, network_device_key
from mrctl.io.modbus.codec import FC_WRITE_MULTIPLE, MAX_ADU_TCP, Tx, decode_tcp_response
from mrctl.io.modbus.link import DEFAULT_TCP_TIMEOUT_S, ModbusLink
from mrctl.io.modbus.transport import TcpIO

__all__ = ["ModbusTcpLink", "next_mbap_frame"]


def next_mbap_frame(link: Any, rx: bytearray, io: TcpIO) -> bytes | None:
    """The first whole MBAP frame in ``rx`` (6 bytes or more; removed from it), or None while it is
    incomplete. An impossible header (protocol id not 0, length outside 2..254) drops ``rx`` and what
    ``io`` has queued, counts them in ``link.bytes_discarded`` and raises :class:`FrameError` (naming
    ``link._where()``): every frame returned has protocol id 0 and its MBAP length."""
    if rx[2] or rx[3] or not 2 <= (rx[4] << 8 | rx[5]) <= MAX_ADU_TCP - 6:
        link.bytes_discarded += len(rx) + io.drain()
        rx.clear()
        raise FrameError(f"{link._where()}: bad MBAP header; stream flushed")
    total = 6 + (rx[4] << 8 | rx[5])
    if len(rx) < total:
        return None
    frame = bytes(rx[:total])
    del rx[:total]
    return frame


class ModbusTcpLink(ModbusLink):
    """Backend ``modbus-tcp``: ``host``, ``port`` (default 502), ``gateway``
    (the endpoint is a gateway: each unit id a device of its own, for the
    ownership lock); see :class:`ModbusLink`."""

    kinds = ("modbus-tcp",)
    transport = "tcp"

    def _configure(self, *, host: str | None, port: int, gateway: bool = False, **_other: Any) -> None:
        if not host:
            raise ValueError("Modbus TCP needs host")
        self.host = host
        self.gateway = bool(gateway)
        self.port = int(port)
        self.url: str | int | None = None
        self._tid = 0
        self._rx = bytearray()  # bytes received beyond the last whole frame

    @classmethod
    def _options(cls, cfg: Any) -> dict[str, Any]:
        return {"host": cfg.host, "port": cfg.port, "gateway": cfg.get("gateway", False)}

    def device_key(self) -> str | None:
        """The endpoint; per unit id only behind a gateway (a direct device answers any unit id)."""
        return network_device_key("modbus-tcp", str(self.host), self.port, self.unit_id if self.gateway else None)

    def _default_timeout(self, fc23: bool) -> float:
        return float(self._timeout_arg) if self._timeout_arg is not None else DEFAULT_TCP_TIMEOUT_S

    def _connect(self) -> TcpIO:
        io = TcpIO.connect(self.host, self.port, self.open_timeout_s, self.spin_wait)
        self._rx.clear()
        return io

    def _wrap(self, sock: Any, io: Any) -> TcpIO:
        return TcpIO(sock, self.spin_wait, f"{self.host}:{self.port}")

    def _where(self) -> str:
        return f"modbus-tcp {self.host}:{self.port}"

    def _exchange_tx(self, tx: Tx, deadline: float, wake_ns: int) -> bytes:
        io = self._io
        tid = self._tid = (self._tid + 1) & 0xFFFF
        adu = tx.adu
        adu[0] = tid >> 8
        adu[1] = tid & 0xFF
        io.write(adu, deadline)
        rx = self._rx
        while True:
            frame = next_mbap_frame(self, rx, io) if len(rx) >= 6 else None
            if frame is not None:
                if frame[0] << 8 | frame[1] != tid:
                    self.stale_replies += 1
                    continue
                return decode_tcp_response(frame, tid, self.unit_id, tx.fc, tx.n_regs)
            chunk = io.recv(deadline, wake_ns)
            wake_ns = 0
            if not chunk:
                raise LinkTimeout(
                    f"{self.host}:{self.port}: no reply to tid {tid} within {self.timeout_s * 1e3:.3g} ms"
                )
            # Fast path: exactly the expected reply, nothing buffered.
            if not rx and len(chunk) == tx.resp_len and chunk[0] << 8 | chunk[1] == tid:
                if tx.fc == FC_WRITE_MULTIPLE:
                    if chunk[2:] == tx.resp_tail:
                        return b""
                elif chunk[2:9] == tx.resp_tail:
                    return chunk[9:]
            rx += chunk
