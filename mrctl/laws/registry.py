"""The one table of law names: built-ins and plugins alike.

``demand.type`` names a :class:`~mrctl.laws.base.DemandLaw`, ``inverse.law``
a :class:`~mrctl.laws.base.CurrentLaw`. The config schema builds its choices
and per-law keys from these tables, so a law added here (or by a plugin) is
validated, documented and buildable with no other edit.
"""

from __future__ import annotations

from mrctl.laws.base import CurrentLaw, DemandLaw
from mrctl.laws.closed import ClosedLoopInverse
from mrctl.laws.demand import ConstantForce, FromFile, Viscous
from mrctl.laws.inverse import ConstantCurrent, PaperInverse, ScheduleCurrent, SmoothInverse

_DEMAND: dict[str, type[DemandLaw]] = {c.name: c for c in (Viscous, ConstantForce, FromFile)}
_CURRENT: dict[str, type[CurrentLaw]] = {c.name: c for c in (PaperInverse, SmoothInverse, ClosedLoopInverse,
                                                             ConstantCurrent, ScheduleCurrent)}


def demand_laws() -> dict[str, type[DemandLaw]]:
    """Every demand law by its YAML name (``demand.type``)."""
    return dict(_DEMAND)


def current_laws() -> dict[str, type[CurrentLaw]]:
    """Every current law by its YAML name (``inverse.law``)."""
    return dict(_CURRENT)
