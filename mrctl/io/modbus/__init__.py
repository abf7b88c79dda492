"""Modbus TCP and RTU links (docs/registers.md).

* :mod:`.codec`: CRC, request/response frames, exception names, the
  precompiled per-tick transactions, RTU wire time (pure bytes, no I/O);
* :mod:`.transport`: the byte transports (serial fd, pyserial URL, TCP socket);
* :mod:`.link`: :class:`ModbusLink`, what both transports share;
  :mod:`.tcp` / :mod:`.rtu`: :class:`ModbusTcpLink`, :class:`ModbusRtuLink`.

The names below are the package's interface (the daemon, hil_sim, the
benchmarks and the tests import them from here). Nothing here imports pymodbus.
"""

from mrctl.io.modbus.codec import (
    EXCEPTION_NAMES,
    FC_READ_HOLDING,
    FC_READ_INPUT,
    FC_READ_WRITE,
    FC_WRITE_MULTIPLE,
    crc16_modbus,
    decode_response_pdu,
    decode_rtu_response,
    decode_tcp_response,
    default_rtu_timeout_s,
    exception_name,
    mbap_frame,
    read_request_pdu,
    read_write_request_pdu,
    rtu_bits_per_char,
    rtu_frame,
    rtu_tick_frames,
    rtu_transaction_wire_time_s,
    write_request_pdu,
)
from mrctl.io.modbus.link import (
    DEFAULT_OPEN_TIMEOUT_S,
    DEFAULT_RTU_BAUD,
    DEFAULT_TCP_PORT,
    DEFAULT_TCP_TIMEOUT_S,
    DEFAULT_WATCHDOG_MS,
    ModbusLink,
)
from mrctl.io.modbus.rtu import ModbusRtuLink
from mrctl.io.modbus.tcp import ModbusTcpLink
from mrctl.io.modbus.transport import open_serial_port

__all__ = [
    "FC_READ_HOLDING",
    "FC_READ_INPUT",
    "FC_WRITE_MULTIPLE",
    "FC_READ_WRITE",
    "EXCEPTION_NAMES",
    "DEFAULT_TCP_PORT",
    "DEFAULT_RTU_BAUD",
    "DEFAULT_TCP_TIMEOUT_S",
    "DEFAULT_WATCHDOG_MS",
    "DEFAULT_OPEN_TIMEOUT_S",
    "ModbusLink",
    "ModbusTcpLink",
    "ModbusRtuLink",
    "crc16_modbus",
    "exception_name",
    "read_request_pdu",
    "write_request_pdu",
    "read_write_request_pdu",
    "mbap_frame",
    "rtu_frame",
    "decode_response_pdu",
    "decode_tcp_response",
    "decode_rtu_response",
    "rtu_tick_frames",
    "rtu_transaction_wire_time_s",
    "rtu_bits_per_char",
    "default_rtu_timeout_s",
    "open_serial_port",
]
