"""Desired-force laws: what force (N) the damper should produce now.

Called once per tick with time (s), displacement (m) and velocity (m/s);
returns F_des (N). The inverse law then finds the current for it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from mrctl.model.excitation import Interpolator, load_series


class Demand(Protocol):
    name: str

    def force(self, t: float, x: float, v: float) -> float:
        """Desired force (N)."""
        ...


class Viscous:
    """F_des = c_des·v, eq (13): make the MR damper behave as a viscous one."""

    name = "viscous"

    def __init__(self, c_des: float) -> None:
        self.c_des = float(c_des)

    def force(self, t: float, x: float, v: float) -> float:
        return self.c_des * v


class ConstantForce:
    """F_des = F (N), whatever the motion (identification, friction tests)."""

    name = "constant"

    def __init__(self, F_N: float) -> None:
        self.F_N = float(F_N)

    def force(self, t: float, x: float, v: float) -> float:
        return self.F_N


class FromFile:
    """F_des(t) from a CSV with columns ``t,F_des`` (s, N), linearly interpolated
    and held at the ends."""

    name = "file"

    def __init__(self, path: str | Path) -> None:
        data = load_series(path, ("t", "F_des"))
        self._f = Interpolator(data["t"], data["F_des"])

    def force(self, t: float, x: float, v: float) -> float:
        return self._f(t)
