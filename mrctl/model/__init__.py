"""Pure numerics of the LuGre MR-damper model: no I/O, plain floats per tick."""

from mrctl.model.lugre import LuGreModel
from mrctl.model.params import TABLE_I, LuGreParams

__all__ = ["LuGreModel", "LuGreParams", "TABLE_I"]
