"""The law guard of the offline loops: what a law that raises or returns
NaN/inf becomes, a :class:`LawFault` at 0 A instead of a crash.

``mrctl simulate`` runs two per-tick loops (the shaker's in
:mod:`mrctl.offline.simulate`, benches that move with the damper in
:mod:`mrctl.offline.bench_sim`). Each calls the laws inside its own
``try`` (a call per tick into a shared helper would cost ~7 % of
``simulate``'s speed, measured with callgrind) and hands what it caught
here, so a law misbehaves the same way in either and as it does under
``mrctl run`` (docs/laws.md). The daemon's controller has its own guard
because it also times the call against the tick's budget and hands the
fault to the safety supervisor.
"""

from __future__ import annotations

from mrctl.laws.base import LawFault, NonFiniteOutput


def law_fault(exc: Exception, who: str, k: int, t: float) -> LawFault:
    """The fault for ``exc``, caught around the call of law ``who`` at tick
    ``k`` (time ``t``, s): :class:`NonFiniteOutput` (raised by the loop on
    a NaN or inf) is ``non-finite``, anything else ``raised``."""
    if isinstance(exc, NonFiniteOutput):
        return LawFault("non-finite", who, k, t, str(exc))
    return LawFault("raised", who, k, t, f"{type(exc).__name__}: {exc}")
