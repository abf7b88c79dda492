"""The law API: what a control law sees each tick, what it must return.

Every law, built in or a plugin, is a class on this API (ros2_control's
controllers-as-plugins):

- a :class:`DemandLaw` says what force the damper should produce now
  (``force(m) -> F_des`` in N);
- a :class:`CurrentLaw` decides the coil current (``current(m, F_des) -> I``
  in A, within [0, I_max]); an :class:`InverseLaw` is a current law that
  inverts a damper model to produce ``F_des``; a direct current law (on-off
  skyhook, clipped-optimal) ignores it.

Both receive the whole sample as one :class:`Measurement`, updated in place
by the controller every tick (no allocation per tick). A law keeps its own
state, declares the keys of its YAML section as schema fields (``params``:
validated with key paths, listed by ``docs/config.md`` and ``mrctl check``),
and is built by :meth:`Law.from_config`.

These classes are compiled with mypyc (mrctl/build.py) and allow
interpreted subclasses, so a plugin subclasses them as ordinary Python. They
are not ``abc.ABC`` (isinstance checks on compiled ABCs share one cache):
the registry refuses a class that leaves ``force`` or ``current``
unimplemented.

In the 1 kHz path a law must not block, sleep, do I/O or log, allocate
what it can avoid, or use numpy scalars (plain floats are ~10x faster per
call). A law that raises or returns NaN is a safety fault: 0 A. The rules
and what happens then are in docs/laws.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Mapping

from mypy_extensions import mypyc_attr

from mrctl.model.params import LuGreParams

__all__ = [
    "Measurement",
    "LawContext",
    "Law",
    "DemandLaw",
    "CurrentLaw",
    "InverseLaw",
    "LawFault",
    "NonFiniteOutput",
    "clamp_current",
]


def clamp_current(I: float, I_max: float) -> float:
    """Clamp to [0, I_max] (A); NaN → 0 A, the safe side. Branches, no min/max
    calls: it runs every tick."""
    if I > 0.0:
        return I if I < I_max else I_max
    return 0.0  # negative, zero, or NaN


@mypyc_attr(allow_interpreted_subclasses=True)
class Measurement:
    """The whole sample a law sees at one tick (SI units).

    One instance per run, rewritten in place by the controller before the
    laws are called: read its fields during the call, copy what you need
    to keep. ``channels`` holds extra named channels a DAQ or bench provides
    (e.g. a quarter-car's sprung-mass velocity), also updated in place."""

    __slots__ = ("k", "t", "x", "v", "F", "I_applied", "I_cmd", "status", "channels")

    def __init__(self, k: int = 0, t: float = 0.0, x: float = 0.0, v: float = 0.0, F: float = math.nan,
                 I_applied: float = math.nan, I_cmd: float = 0.0, status: int = 0,
                 channels: dict[str, float] | None = None) -> None:
        self.k = k  #: tick index
        self.t = t  #: time (s), k·dt
        self.x = x  #: displacement (m)
        self.v = v  #: velocity (m/s), measured or estimated
        self.F = F  #: load-cell force (N); NaN without a load cell
        self.I_applied = I_applied  #: current the driver reports applied (A); NaN if unknown
        self.I_cmd = I_cmd  #: current commanded on the previous tick (A)
        self.status = status  #: device status bits (mrctl.io.base.Status)
        self.channels: dict[str, float] = {} if channels is None else channels

    def __repr__(self) -> str:
        return (f"Measurement(k={self.k}, t={self.t}, x={self.x}, v={self.v}, F={self.F}, "
                f"I_applied={self.I_applied}, I_cmd={self.I_cmd}, status={self.status}, channels={self.channels})")


@dataclass(frozen=True)
class LawContext:
    """What a law is built with besides its own YAML section."""

    params: LuGreParams  #: the damper model's parameter set (``parameters``)
    I_max: float  #: current limit (A), ``safety.I_max``
    dt: float  #: tick period (s)
    base_dir: Path = Path(".")  #: directory of the config file (relative paths)
    channels: tuple[str, ...] = ()  #: extra channels the link provides
    extra: Mapping[str, Any] = field(default_factory=dict)  #: bench facts a law may use (e.g. masses)


@mypyc_attr(allow_interpreted_subclasses=True)
class Law:
    """What every law shares: a name, a parameter schema, a lifecycle."""

    #: the name written in YAML (``demand.type`` or ``inverse.law``)
    name: ClassVar[str] = ""
    #: schema fields of the law's YAML section (:mod:`mrctl.util.schema`), by key
    params: ClassVar[Mapping[str, Any]] = {}
    #: one line for the reference docs
    summary: ClassVar[str] = ""
    #: extra channels (``Measurement.channels`` keys) the law reads; a link
    #: that does not provide them is refused at start-up (a plugin may set it per instance)
    channels: ClassVar[tuple[str, ...]] = ()
    #: False for a semi-active law, whose demanded force is clipped or saturated by design
    #: (skyhook, groundhook, LQR, the on-off laws): a run's force tracking and its share at
    #: I_max are then not judged by default (docs/config.md, acceptance)
    tracks_force: ClassVar[bool] = True

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "Law":
        """Build from the validated section ``cfg`` (attribute access to the
        keys of :attr:`params`). Default: ``cls(ctx, **those keys)``."""
        return cls(ctx, **{k: cfg.get(k) for k in cls.params})  # type: ignore[call-arg]

    @classmethod
    def check(cls, cfg: Any, ctx: LawContext) -> list[str]:
        """Problems across keys, or with the context (e.g. a current above
        I_max), each naming its key relative to the section. Default: none."""
        return []

    def reset(self, I0: float = 0.0) -> None:
        """Start over (a new run, or a hot swap: ``I0`` is the current the
        coil carries now, so a new law starts from it without a step)."""

    def notices(self) -> list[str]:
        """What the law has to tell the user about the run so far (e.g. it
        ran without an input it uses), one line each. A law must not print
        or log from the 1 kHz path: it sets a counter there, and the daemon
        (after the run) and ``mrctl simulate`` ask here. Default: none."""
        return []


@mypyc_attr(allow_interpreted_subclasses=True)
class DemandLaw(Law):
    """Decides the force the damper should produce."""

    def force(self, m: Measurement) -> float:
        """Desired force (N) at this tick. Every demand law implements it."""
        raise NotImplementedError(f"{type(self).__name__}.force")


@mypyc_attr(allow_interpreted_subclasses=True)
class CurrentLaw(Law):
    """Decides the coil current (A). Must return a value in [0, I_max]."""

    #: False: the law decides the current itself (F_des is NaN when no demand is configured)
    needs_demand: ClassVar[bool] = False
    I_max: float

    def current(self, m: Measurement, F_des: float) -> float:
        """Current (A) in [0, I_max] for this tick. Every current law implements it."""
        raise NotImplementedError(f"{type(self).__name__}.current")

    def applied(self, I: float) -> None:
        """The current actually commanded (after safety), when it differs
        from what :meth:`current` returned: the law's state follows it."""


@mypyc_attr(allow_interpreted_subclasses=True)
class InverseLaw(CurrentLaw):
    """A current law that makes the damper produce the demanded force."""

    needs_demand = True


@mypyc_attr(native_class=False)
class NonFiniteOutput(ArithmeticError):
    """A law returned NaN or inf: raised and caught by the law guard within a tick."""


@dataclass(frozen=True)
class LawFault:
    """What went wrong with a law, recorded at the tick it happened (the
    controller and ``mrctl simulate`` report it after the run)."""

    kind: str  #: "raised", "non-finite" or "slow"
    law: str  #: the law's YAML name
    k: int  #: tick index
    t: float  #: time (s)
    detail: str  #: the exception, the value, or the time taken

    def __str__(self) -> str:
        what = {"raised": "raised", "non-finite": "returned a non-finite value",
                "slow": "was too slow"}.get(self.kind, self.kind)
        return f"law fault: {self.law} {what} at tick {self.k} (t = {self.t:.3f} s): {self.detail}; 0 A"
