"""The law guard of the offline loops: one tick of the demand and current
laws, where a law that raises or returns NaN/inf is a fault, not a crash.

``mrctl simulate`` runs two per-tick loops (the shaker's in
:mod:`mrctl.offline.simulate`, benches that move with the damper in
:mod:`mrctl.offline.bench_sim`); both call this, so a law misbehaves the same
way in either and as it does under ``mrctl run`` (docs/laws.md). The daemon's
controller has its own guard because it also times the call against the
tick's budget and hands the fault to the safety supervisor.
"""

from __future__ import annotations

import math

from mrctl.laws.base import CurrentLaw, DemandLaw, LawFault, Measurement, NonFiniteOutput, clamp_current


class GuardedLaws:
    """``step(m)`` → the current (A) to command this tick. After a fault
    (``fault`` set) it returned 0 A and the run is to end at that tick."""

    __slots__ = ("_demand", "_current", "_applied", "demand_name", "law_name", "I_max", "F_des", "fault")

    def __init__(self, law: CurrentLaw, demand: DemandLaw | None, I_max: float, law_name: str,
                 demand_name: str = "") -> None:
        self._demand = demand.force if demand is not None else None
        self._current, self._applied = law.current, law.applied
        self.law_name, self.demand_name = law_name, demand_name
        self.I_max = I_max
        self.F_des = math.nan  #: this tick's demand (N); NaN without a demand law
        self.fault: LawFault | None = None

    def step(self, m: Measurement) -> float:
        """Demand, then current, clamped to [0, I_max]; the law is told
        (``applied``) only when the clamp changed its output."""
        Fd = math.nan
        who = self.demand_name
        try:  # zero cost on the good path (3.11)
            demand = self._demand
            if demand is not None:
                Fd = demand(m)
                if Fd - Fd != 0.0:  # NaN or inf
                    raise NonFiniteOutput(f"F_des = {Fd!r}")
            who = self.law_name
            I = self._current(m, Fd)
            if I - I != 0.0:
                raise NonFiniteOutput(f"I = {I!r}")
            Ic = clamp_current(I, self.I_max)
            if Ic != I:
                self._applied(Ic)
        except NonFiniteOutput as exc:
            self._failed("non-finite", who, m, str(exc))
            Ic = 0.0
        except Exception as exc:  # noqa: BLE001 - a law's failure is a fault, not a crash
            self._failed("raised", who, m, f"{type(exc).__name__}: {exc}")
            Ic = 0.0
        self.F_des = Fd
        return Ic

    def _failed(self, kind: str, who: str, m: Measurement, detail: str) -> None:
        self.fault = LawFault(kind, who, m.k, m.t, detail)
