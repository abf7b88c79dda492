"""Safety faults, reported while the run goes on (the monitor thread polls this).

The supervisor (:mod:`mrctl.core.safety`) acts within the tick: 0 A on a
fault. Saying so is slower work, so it happens here, off the loop, at the
monitor's 50 ms poll: each new entry into FAULT is reported once at error
priority (``<3>`` in the journal, :mod:`mrctl.util.journal`), with the
reason and the count; a recovery (``safety.auto_resume``) at notice
priority. A fault that comes and goes within one poll is still counted
(``faults_entered``), and reported with the last reason.
"""

from __future__ import annotations

from typing import Any, Callable

from mrctl.util.journal import CRIT, ERR, NOTICE


class FaultWatch:
    """Compares the supervisor's counters with what was last reported."""

    def __init__(self, sup: Any, report: Callable[[str, int], None], ticks: Callable[[], int]) -> None:
        self.sup = sup
        self.report = report
        self.ticks = ticks
        self.entered = 0
        self.resumes = 0
        self.latches = 0

    def check(self) -> None:
        c = self.sup.counters()
        if c.faults_entered > self.entered:
            new = c.faults_entered - self.entered
            self.entered = c.faults_entered
            # the last fault, also when it cleared (auto-resume) before this poll
            fault = self.sup.last_fault.name if self.sup.last_fault else "?"
            more = f" ({new} new faults since the last report)" if new > 1 else ""
            k = self.sup.last_fault_tick  # the tick the fault was entered at, as the law fault and the log say
            self.report(f"safety: FAULT {fault} at tick {k if k >= 0 else self.ticks()}: "
                        f"{self.sup.last_reason or 'no reason given'}; "
                        f"0 A commanded{more}; faults so far {self.entered}", ERR)
        if c.latches > self.latches:
            self.latches = c.latches
            cause = self.sup.latch_cause or "cleared already"
            self.report(f"safety: LATCHED ({cause}) at tick {self.sup.last_fault_tick}: 0 A, output disabled, until "
                        f"mrctl arm (latches so far {self.latches})", CRIT)
        if c.resumes > self.resumes:
            self.resumes = c.resumes
            self.report(f"safety: fault cleared, control resumed (resumes so far {self.resumes})", NOTICE)
