"""Desired-force laws: what force (N) the damper should produce now.

Called once per tick with the measurement (:class:`mrctl.laws.base.Measurement`);
returns F_des (N). A current law (usually an inverse law) then finds the
current for it.
"""

from __future__ import annotations

from mypy_extensions import mypyc_attr

from pathlib import Path
from typing import Any

from mrctl.laws.base import DemandLaw, LawContext, Measurement
from mrctl.model.excitation import Interpolator
from mrctl.util.csvtable import load_series
from mrctl.util.schema import FilePath, Num


@mypyc_attr(allow_interpreted_subclasses=True)
class Viscous(DemandLaw):
    """F_des = c_des·v, eq (13): make the MR damper behave as a viscous one."""

    name = "viscous"
    summary = "F_des = c_des·v, eq (13)"
    params = {"c_des": Num(min=0.0, max=1e5, doc="desired damping (N·s/m), eq (13)")}

    def __init__(self, c_des: float) -> None:
        self.c_des = float(c_des)

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "Viscous":
        return cls(cfg.c_des)

    def force(self, m: Measurement) -> float:
        return self.c_des * m.v


@mypyc_attr(allow_interpreted_subclasses=True)
class ConstantForce(DemandLaw):
    """F_des = F (N), whatever the motion (identification, friction tests)."""

    name = "constant"
    summary = "a constant force"
    params = {"F_N": Num(min=-1e4, max=1e4, doc="desired force (N)")}

    def __init__(self, F_N: float) -> None:
        self.F_N = float(F_N)

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "ConstantForce":
        return cls(cfg.F_N)

    def force(self, m: Measurement) -> float:
        return self.F_N


@mypyc_attr(allow_interpreted_subclasses=True)
class FromFile(DemandLaw):
    """F_des(t) from a CSV with columns ``t,F_des`` (s, N), linearly interpolated
    and held at the ends."""

    name = "file"
    summary = "F_des(t) from a CSV file"
    params = {"path": FilePath(doc="CSV with columns t,F_des (s, N)")}

    def __init__(self, path: str | Path) -> None:
        data = load_series(path, ("t", "F_des"))
        self._f = Interpolator(data["t"], data["F_des"])

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "FromFile":
        return cls(cfg.path)

    def force(self, m: Measurement) -> float:
        return self._f(m.t)
