"""Laws that misbehave after ``after_ticks`` good ticks, named in test configs as
``bad_laws:Raises`` etc. (module:Class; tests/test_law_guard.py)."""

from __future__ import annotations

import math
import time

from mrctl.laws.base import CurrentLaw, DemandLaw, LawContext, Measurement
from mrctl.util.schema import Num

_AFTER = {"after_ticks": Num(default=200, integer=True, min=0, doc="good ticks before misbehaving")}


class _Bad(CurrentLaw):
    params = _AFTER

    def __init__(self, ctx: LawContext, after_ticks: int) -> None:
        self.I_max = ctx.I_max
        self.after = after_ticks
        self.n = 0

    def reset(self, I0: float = 0.0) -> None:
        self.n = 0

    def current(self, m: Measurement, F_des: float) -> float:
        self.n += 1
        return self.bad() if self.n > self.after else 0.2

    def bad(self) -> float:
        raise NotImplementedError


class Raises(_Bad):
    def bad(self) -> float:
        raise RuntimeError("boom from a plugin")


class ReturnsNaN(_Bad):
    def bad(self) -> float:
        return math.nan


class Spins(_Bad):
    """Computes (burns the loop thread's CPU) for 5 ms per call."""

    def bad(self) -> float:
        end = time.thread_time() + 0.005
        while time.thread_time() < end:
            pass
        return 0.2


class Sleeps(_Bad):
    """Waits 5 ms per call without computing: what preemption looks like to a law."""

    def bad(self) -> float:
        time.sleep(0.005)
        return 0.2


class ExitsProcess(_Bad):
    def bad(self) -> float:
        raise SystemExit(0)


class GeneratorExits(_Bad):
    def bad(self) -> float:
        raise GeneratorExit


class Interrupts(_Bad):
    def bad(self) -> float:
        raise KeyboardInterrupt


class CtrlC(_Bad):
    """The user's Ctrl-C arriving while the law computes: SIGINT to this
    process, handled inside this call (the loop after the kill gives the
    interpreter its chance to run the handler here, not after the return)."""

    def bad(self) -> float:
        import os
        import signal

        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(100_000):
            pass
        return 0.2


class ReturnsComplex(_Bad):
    def bad(self) -> float:
        return complex(0.2, 0.0)  # type: ignore[return-value]


class ReturnsArray(_Bad):
    def bad(self) -> float:
        import numpy as np

        return np.array([0.2])  # type: ignore[return-value]


class AppliedRaises(_Bad):
    """Asks for more than I_max after ``after_ticks``; told the clamped value, it raises."""

    def bad(self) -> float:
        return 2.0 * self.I_max

    def applied(self, I: float) -> None:
        raise RuntimeError("applied() lost its state")


class DemandRaises(DemandLaw):
    params = _AFTER

    def __init__(self, ctx: LawContext, after_ticks: int) -> None:
        self.after = after_ticks
        self.n = 0

    def force(self, m: Measurement) -> float:
        self.n += 1
        if self.n > self.after:
            raise ZeroDivisionError("demand divided by zero")
        return 10.0 * m.v


class NeedsChannel(CurrentLaw):
    channels = ("v_sprung",)

    def __init__(self, ctx: LawContext) -> None:
        self.I_max = ctx.I_max

    def current(self, m: Measurement, F_des: float) -> float:
        return 0.0


class NotALaw:
    pass


class BadParams(CurrentLaw):
    params = {"gain": 3.0}

    def current(self, m: Measurement, F_des: float) -> float:
        return 0.0


class RaisesOnBuild(CurrentLaw):
    @classmethod
    def from_config(cls, cfg, ctx):
        raise RuntimeError("cannot build me")

    def current(self, m: Measurement, F_des: float) -> float:
        return 0.0
