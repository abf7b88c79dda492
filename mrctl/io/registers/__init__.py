"""Modbus register maps: entries and their checks (:mod:`.spec`), the map
and its blocks (:mod:`.map`), the bytes of the blocks (:mod:`.codec`).

The names below are the package's interface (the link, hil_sim, the
experiment schema and the tests import them from here).
"""

from mrctl.io.registers.codec import DATA_TYPES, ReadValues, WriteValues
from mrctl.io.registers.map import RegisterMap, default_register_map, validate_register_map
from mrctl.io.registers.spec import (
    DEFAULT_REGISTER_MAP,
    MAX_READ_REGISTERS,
    MAX_WRITE_REGISTERS,
    QUANTITIES,
    READ_QUANTITIES,
    TABLES,
    WORD_ORDERS,
    WRITE_QUANTITIES,
    Block,
    RegisterSpec,
)

__all__ = [
    "DATA_TYPES",
    "TABLES",
    "WORD_ORDERS",
    "READ_QUANTITIES",
    "WRITE_QUANTITIES",
    "QUANTITIES",
    "MAX_READ_REGISTERS",
    "MAX_WRITE_REGISTERS",
    "RegisterSpec",
    "Block",
    "ReadValues",
    "WriteValues",
    "RegisterMap",
    "default_register_map",
    "DEFAULT_REGISTER_MAP",
    "validate_register_map",
]
