"""The law guard: a law's call, checked, and what its failure becomes.

:class:`LawCall` calls the demand law and then the current law on one
measurement and raises if either fails: an exception (any, ``SystemExit``
and ``KeyboardInterrupt`` from a law too), a result that is not a real
number, or a NaN/inf. The daemon's controller (:mod:`mrctl.core.controller`,
which also times the call against the law's CPU budget) and the offline
loop (:mod:`mrctl.core.offline`) catch that and make it a
:class:`LawFault` at 0 A with :func:`law_fault`, so a law misbehaves the
same way under ``mrctl run`` and ``mrctl simulate`` (docs/laws.md).

Compiled with the tick (mrctl/build.py): the call is native for the
built-in laws and a Python call for a plugin.
"""

from __future__ import annotations

import math
from typing import Final

from mrctl.laws.base import CurrentLaw, DemandLaw, Law, LawFault, Measurement, NonFiniteOutput

NAN: Final = math.nan


def _short(value: object, limit: int = 200) -> str:
    """``str(value)`` cut to ``limit`` characters: a message must not carry a huge value."""
    text = str(value)
    return text if len(text) <= limit else text[:limit] + f"... ({len(text)} characters)"


def _real(value: object, what: str) -> float:
    """A law's result that is not a float, as the compiled build takes it: an
    int becomes a float, anything else (a complex, an array) raises. (Compiled,
    the law's declared ``-> float`` makes this check before we see the value.)"""
    if isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    raise TypeError(f"{what} = {_short(value)} is a {type(value).__name__}, not a float")


class LawCall:
    """Demand, then current law, on one measurement; raises on any failure.

    After a call, ``F_des`` is the demand's force (NaN without a demand law)
    and ``who`` the law that was being called (the one to blame if it raised)."""

    def __init__(self) -> None:
        self.F_des = NAN
        self.who: Law | None = None

    def run(self, law: CurrentLaw, demand: DemandLaw | None, m: Measurement) -> float:
        """The current law's output (A) for ``m``, finite; raises otherwise."""
        F_des = NAN
        self.F_des = NAN
        if demand is not None:
            self.who = demand
            F_des = demand.force(m)
            if not isinstance(F_des, float):  # interpreted only: compiled, unboxing checked it
                F_des = _real(F_des, "F_des")
            if F_des - F_des != 0.0:  # NaN or inf
                raise NonFiniteOutput(f"F_des = {F_des!r}")
            self.F_des = F_des
        self.who = law
        I = law.current(m, F_des)
        if not isinstance(I, float):
            I = _real(I, "I")
        if I - I != 0.0:
            raise NonFiniteOutput(f"I = {I!r}")
        return I


def law_name(who: Law | None) -> str:
    """The name a fault report gives a law: its YAML name, else its class's."""
    if who is None:
        return ""
    return who.name or type(who).__name__


def law_fault(exc: BaseException, who: str, k: int, t: float) -> LawFault:
    """The fault for ``exc``, caught around the call of law ``who`` at tick
    ``k`` (time ``t``, s): :class:`NonFiniteOutput` (raised on a NaN or inf)
    is ``non-finite``, anything else ``raised``."""
    if isinstance(exc, NonFiniteOutput):
        return LawFault("non-finite", who, k, t, str(exc))
    return LawFault("raised", who, k, t, f"{type(exc).__name__}: {_short(exc)}")
