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

    #: the bad-sample kinds (everything but DRIVER and LAW)
    SAMPLE = MISSING | LATE | STALE | NON_FINITE | OUT_OF_RANGE | DEVICE_STATUS


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

    @classmethod
    def from_config(cls, s: Any, dt: float) -> "SafetyConfig":
        """From the validated ``safety`` section, at tick period ``dt`` (s)."""
        return cls(
            I_max=s.I_max, max_slew_A_per_s=s.max_slew_A_per_s, hold_ticks=s.hold_ticks, max_age_s=s.max_age_s,
            x_range_m=s.x_range_m, v_range_mps=s.v_range_mps, F_range_N=s.F_range_N,
            require_force=s.require_force,
            status_fault_mask=int(Status.FAULTS) if s.fault_on_device_status else 0,
            auto_resume=s.auto_resume, resume_good_ticks=s.resume_good_ticks, dt_s=dt,
        )


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

    @property
    def bad(self) -> int:
        return (self.missing + self.late + self.stale + self.non_finite
                + self.out_of_range + self.device_status)

    def as_dict(self) -> dict[str, int]:
        d = asdict(self)
        d["bad"] = self.bad
        return d


# bit → label for the reason string (built only on a state change)
