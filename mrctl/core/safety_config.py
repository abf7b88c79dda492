"""What the safety supervisor is configured with and reports: its settings,
states, fault kinds and counters (the supervisor is :mod:`mrctl.core.safety`).

``Fault`` is also the legend of the run log's ``fault`` bit field.
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass
from typing import Any

from mrctl.io.base import Status


class SafetyState(enum.IntEnum):
    """Where the supervisor is; ``limit`` outputs 0 A in STARTING and FAULT."""

    STARTING = 0  #: no good sample yet (after construction or ``reset``): 0 A
    OK = 1  #: last sample was good; the law runs on it
    HOLDING = 2  #: bad sample(s) absorbed; the law runs on the last good one
    FAULT = 3  #: 0 A until auto-resume or ``reset()``
    LATCHED = 4  #: shown for a FAULT that waits for an explicit re-arm (``mrctl arm``): 0 A, output disabled


class Fault(enum.IntFlag):
    """Why the supervisor is (or went) into FAULT; bits OR over the bad run."""

    NONE = 0
    MISSING = 1 << 0  #: no sample this tick (read timeout / link error)
    LATE = 1 << 1  #: sample age exceeded ``max_age_s``
    STALE = 1 << 2  #: sequence number did not advance (mod 2**32)
    NON_FINITE = 1 << 3  #: NaN/inf in x or v (or F: inf always, NaN if required)
    OUT_OF_RANGE = 1 << 4  #: x, v or F outside the configured range
    DEVICE_STATUS = 1 << 5  #: sample.status has a bit of ``status_fault_mask``
    DRIVER = 1 << 6  #: the loop reported a current-driver failure (latched)
    LAW = 1 << 7  #: a control law raised, returned NaN/inf or was too slow (latched; docs/laws.md)
    ESTOP = 1 << 8  #: the E-stop / interlock input is open (``Status.ESTOP``): latched at once
    DEVICE_WATCHDOG = 1 << 9  #: the device's own watchdog acted (``Status.WATCHDOG_TRIPPED``): latched at once
    LATCHED = 1 << 10  #: the fault is latched: 0 A until ``mrctl arm`` (set beside its causes)

    #: the bad-sample kinds (everything but DRIVER, LAW and LATCHED)
    SAMPLE = MISSING | LATE | STALE | NON_FINITE | OUT_OF_RANGE | DEVICE_STATUS | ESTOP | DEVICE_WATCHDOG


def _range(r: tuple[float, float] | None, name: str) -> tuple[float, float]:
    if r is None:
        return (-math.inf, math.inf)
    lo, hi = (float(r[0]), float(r[1]))
    if not lo <= hi:  # also rejects NaN
        raise ValueError(f"{name}: need lo <= hi, got {r!r}")
    return (lo, hi)


@dataclass(frozen=True, slots=True)
class SafetyConfig:
    """Supervisor settings; validated on construction (a bad limit is a bug)."""

    I_max: float
    #: max |dI/dt| of the command (A/s); None = no slew limit
    max_slew_A_per_s: float | None = None
    #: consecutive bad ticks absorbed by reusing the last good sample (0 = none)
    hold_ticks: int = 5
    #: a sample older than this (s) is late; None = no age check
    max_age_s: float | None = None
    x_range_m: tuple[float, float] | None = None
    v_range_mps: tuple[float, float] | None = None
    F_range_N: tuple[float, float] | None = None
    #: True: F_N must be finite (a law that needs the load cell); False: NaN allowed
    require_force: bool = False
    #: sample.status bits that make a sample bad (e.g. ``int(Status.FAULTS)``); 0 = ignore
    status_fault_mask: int = 0
    #: leave FAULT after ``resume_good_ticks`` consecutive good samples; False = latched
    auto_resume: bool = False
    resume_good_ticks: int = 10
    #: tick period (s); the slew step is max_slew_A_per_s * dt_s per call
    dt_s: float = 1e-3
    #: sample.status bits that latch at once, with no hold (real links: ``Status.ESTOP |
    #: Status.WATCHDOG_TRIPPED``); 0 = none (the in-process bench)
    latch_status_mask: int = 0
    #: a run of bad samples with missing ones (no reply: a link loss) longer than this (ticks)
    #: latches even with ``auto_resume``; None = never (the in-process bench)
    latch_after_ticks: int | None = None
    #: an ``mrctl arm`` waits this many ticks for the cause to clear (a device's latch to take a
    #: CLEAR_FAULTS, a link to come back), then is refused naming the cause
    arm_wait_ticks: int = 500

    def __post_init__(self) -> None:
        if not (math.isfinite(self.I_max) and self.I_max > 0.0):
            raise ValueError(f"I_max: must be finite and > 0, got {self.I_max!r}")
        if self.max_slew_A_per_s is not None and not (
            math.isfinite(self.max_slew_A_per_s) and self.max_slew_A_per_s > 0.0
        ):
            raise ValueError(f"max_slew_A_per_s: must be finite and > 0 or None, got {self.max_slew_A_per_s!r}")
        if isinstance(self.hold_ticks, bool) or not isinstance(self.hold_ticks, int) or self.hold_ticks < 0:
            raise ValueError(f"hold_ticks: must be an int >= 0, got {self.hold_ticks!r}")
        if self.max_age_s is not None and not self.max_age_s > 0.0:
            raise ValueError(f"max_age_s: must be > 0 or None, got {self.max_age_s!r}")
        _range(self.x_range_m, "x_range_m")
        _range(self.v_range_mps, "v_range_mps")
        _range(self.F_range_N, "F_range_N")
        if (
            isinstance(self.resume_good_ticks, bool)
            or not isinstance(self.resume_good_ticks, int)
            or self.resume_good_ticks < 1
        ):
            raise ValueError(f"resume_good_ticks: must be an int >= 1, got {self.resume_good_ticks!r}")
        if not (math.isfinite(self.dt_s) and self.dt_s > 0.0):
            raise ValueError(f"dt_s: must be finite and > 0, got {self.dt_s!r}")
        if self.latch_after_ticks is not None and (isinstance(self.latch_after_ticks, bool) or not isinstance(
                self.latch_after_ticks, int) or self.latch_after_ticks < 1):
            raise ValueError(f"latch_after_ticks: must be an int >= 1 or None, got {self.latch_after_ticks!r}")
        if isinstance(self.arm_wait_ticks, bool) or not isinstance(self.arm_wait_ticks, int) or self.arm_wait_ticks < 1:
            raise ValueError(f"arm_wait_ticks: must be an int >= 1, got {self.arm_wait_ticks!r}")

    @classmethod
    def from_config(cls, s: Any, dt: float, real_link: bool = True) -> "SafetyConfig":
        """From the validated ``safety`` section, at tick period ``dt`` (s).
        ``real_link``: a device outside this process (serial, Modbus), where
        an E-stop, a device watchdog trip and a long link loss latch, and
        ``max_slew_A_per_s: auto`` is :data:`AUTO_SLEW_A_PER_S`; the
        in-process bench has none of these and no slew limit by default."""
        return cls(
            I_max=s.I_max, max_slew_A_per_s=resolve_slew(s.max_slew_A_per_s, real_link), hold_ticks=s.hold_ticks,
            max_age_s=s.max_age_s, x_range_m=s.x_range_m, v_range_mps=s.v_range_mps, F_range_N=s.F_range_N,
            require_force=s.require_force,
            status_fault_mask=int(Status.FAULTS) if s.fault_on_device_status else 0,
            auto_resume=s.auto_resume, resume_good_ticks=s.resume_good_ticks, dt_s=dt,
            latch_status_mask=LATCH_STATUS if real_link else 0,
            latch_after_ticks=max(1, round(s.latch_after_s / dt)) if real_link and s.latch_after_s is not None
            else None,
            arm_wait_ticks=max(1, round(ARM_WAIT_S / dt)),
        )


#: ``safety.max_slew_A_per_s: auto`` on a real link (A/s): what the inverse laws advertise
#: (0.05 A per tick at 1 kHz), full scale of a 0.6 A I_max in 12 ms, about the coil's own time constant
AUTO_SLEW_A_PER_S = 50.0
#: the device status bits that latch at once on a real link
LATCH_STATUS = int(Status.ESTOP | Status.WATCHDOG_TRIPPED)
#: how long ``mrctl arm`` waits for the cause of a latch to clear (s)
ARM_WAIT_S = 0.5


def resolve_slew(value: Any, real_link: bool) -> float | None:
    """``safety.max_slew_A_per_s`` as the supervisor takes it: a number, None
    (off: only by an explicit ``null``), or ``auto`` (:data:`AUTO_SLEW_A_PER_S`
    on a real link, off on the in-process bench, whose paper scenario steps)."""
    if value == "auto":
        return AUTO_SLEW_A_PER_S if real_link else None
    return None if value is None else float(value)


@dataclass(frozen=True, slots=True)
class SafetyCounters:
    """Run totals for the run log and status (a snapshot; cheap to pass around)."""

    good: int  #: good samples
    missing: int  #: bad samples by kind (each bad sample counts once, first kind found)
    late: int
    stale: int
    non_finite: int
    out_of_range: int
    device_status: int
    holds_used: int  #: bad ticks absorbed by the hold (no fault)
    longest_bad_run: int  #: most consecutive bad samples seen
    faults_entered: int  #: transitions into FAULT (samples or driver)
    ticks_in_fault: int  #: check_sample calls that returned None because of FAULT
    resumes: int  #: automatic recoveries (auto_resume)
    resets: int  #: reset() calls
    cmd_non_finite: int  #: NaN/inf currents handed to limit() (clamped)
    estop: int = 0  #: samples with the E-stop input open
    device_watchdog: int = 0  #: samples with the device's watchdog tripped
    latches: int = 0  #: faults that latched (waiting for mrctl arm)
    ticks_latched: int = 0  #: ticks spent latched
    arms: int = 0  #: re-arms (mrctl arm) that took
    arms_refused: int = 0  #: re-arms refused (the cause was still there)

    @property
    def bad(self) -> int:
        return (self.missing + self.late + self.stale + self.non_finite
                + self.out_of_range + self.device_status + self.estop + self.device_watchdog)

    def as_dict(self) -> dict[str, int]:
        d = asdict(self)
        d["bad"] = self.bad
        return d


# bit → label for the reason string (built only on a state change)
