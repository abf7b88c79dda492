"""Semi-active suspension laws: skyhook, groundhook, clipped-optimal.

Sign conventions (docs/quarter-car.md): the damper's stroke x = x_s − x_u
(extension positive) and rate v = v_s − v_u are the sample's ``x`` and
``v``; the damper's force F has the sign of v and acts −F on the body, +F
on the wheel. A semi-active damper can only dissipate: it can produce a
force F only where F·v > 0.

Which laws give a force and which a current:

``skyhook`` (demand)
    F_des = c_sky·v_s where v_s·v > 0, else 0: the force of a damper to
    the sky, where the MR damper can give it. Pair with an inverse law
    (``smooth``) for the current.
``groundhook`` (demand)
    F_des = −c_gnd·v_u where v_u·v < 0, else 0: the wheel's damper to
    the ground (road holding).
``skyhook_onoff``, ``groundhook_onoff`` (current, decide it directly)
    I_on where the condition above holds, else I_off; no demand needed.
``lqr`` (demand)
    F_des = −K·[x_s − x_u, v_s, x_u − x_r, v_u], K the LQR gain of the
    quarter car (Dyke et al. 1996's optimal force); K is solved once at
    construction (scipy), the tick is four products.
``clipped_optimal`` (current, needs a demand)
    Dyke et al. 1996's switch: I_on if (F_des − F)·F > 0 else 0, with F the
    load cell's force: the current goes up while the measured force is
    below the desired one with the same sign. Needs the load cell (F NaN →
    0 A). With ``demand: {type: lqr}`` it is clipped-optimal control.
"""

from __future__ import annotations

from typing import Any

from mypy_extensions import mypyc_attr

from mrctl.errors import DependencyMissing
from mrctl.laws.base import CurrentLaw, DemandLaw, LawContext, Measurement
from mrctl.model.quarter_car import QuarterCarParams
from mrctl.util.schema import Num

_I_ON = Num(default=None, optional=True, min=0.0, doc="current when on (A); null = safety.I_max")
_I_OFF = Num(default=0.0, min=0.0, doc="current when off (A)")


@mypyc_attr(allow_interpreted_subclasses=True)
class Skyhook(DemandLaw):
    """Clipped continuous skyhook: F_des = c_sky·v_s where v_s·v > 0, else 0."""

    tracks_force = False  # semi-active: saturation and clipping are its nature

    name = "skyhook"
    summary = "F_des = c_sky·v_sprung where the damper can give it (ride comfort); channel v_sprung"
    params = {"c_sky": Num(min=0.0, max=1e5, doc="skyhook damping (N·s/m)")}
    channels = ("v_sprung",)

    def __init__(self, c_sky: float) -> None:
        self.c = float(c_sky)

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "Skyhook":
        return cls(cfg.c_sky)

    def force(self, m: Measurement) -> float:
        vs = m.channels["v_sprung"]
        return self.c * vs if vs * m.v > 0.0 else 0.0


@mypyc_attr(allow_interpreted_subclasses=True)
class Groundhook(DemandLaw):
    """Clipped continuous groundhook: F_des = −c_gnd·v_u where v_u·v < 0, else 0."""

    tracks_force = False  # semi-active: saturation and clipping are its nature

    name = "groundhook"
    summary = "F_des = −c_gnd·v_unsprung where the damper can give it (road holding); channel v_unsprung"
    params = {"c_gnd": Num(min=0.0, max=1e5, doc="groundhook damping (N·s/m)")}
    channels = ("v_unsprung",)

    def __init__(self, c_gnd: float) -> None:
        self.c = float(c_gnd)

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "Groundhook":
        return cls(cfg.c_gnd)

    def force(self, m: Measurement) -> float:
        vu = m.channels["v_unsprung"]
        return -self.c * vu if vu * m.v < 0.0 else 0.0


@mypyc_attr(allow_interpreted_subclasses=True)
class _OnOff(CurrentLaw):
    """I_on where the law's condition holds, else I_off; no demand."""

    tracks_force = False  # semi-active: saturation and clipping are its nature

    params = {"I_on_A": _I_ON, "I_off_A": _I_OFF}

    def __init__(self, I_on_A: float | None, I_off_A: float, I_max: float) -> None:
        self.I_on = float(I_max if I_on_A is None else I_on_A)
        self.I_off = float(I_off_A)
        self.I_max = float(I_max)
        if not 0.0 <= self.I_off <= self.I_on <= self.I_max:
            raise ValueError(f"need 0 <= I_off_A <= I_on_A <= I_max, got {self.I_off}, {self.I_on}, {self.I_max}")

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "_OnOff":
        return cls(cfg.I_on_A, cfg.I_off_A, ctx.I_max)

    @classmethod
    def check(cls, cfg: Any, ctx: LawContext) -> list[str]:
        on, off = cfg.get("I_on_A"), cfg.get("I_off_A")
        on = ctx.I_max if on is None else on
        if on > ctx.I_max:
            return [f"I_on_A: {on:g} A exceeds safety.I_max = {ctx.I_max:g} A"]
        if off > on:
            return [f"I_off_A: {off:g} A is above I_on_A = {on:g} A"]
        return []


@mypyc_attr(allow_interpreted_subclasses=True)
class SkyhookOnOff(_OnOff):
    """On-off skyhook: I_on where v_s·v > 0 (the damper can pull the body toward rest)."""

    name = "skyhook_onoff"
    summary = "I_on where v_sprung·v > 0, else I_off (decides the current); channel v_sprung"
    channels = ("v_sprung",)

    def current(self, m: Measurement, F_des: float) -> float:
        return self.I_on if m.channels["v_sprung"] * m.v > 0.0 else self.I_off


@mypyc_attr(allow_interpreted_subclasses=True)
class GroundhookOnOff(_OnOff):
    """On-off groundhook: I_on where v_u·v < 0."""

    name = "groundhook_onoff"
    summary = "I_on where v_unsprung·v < 0, else I_off (decides the current); channel v_unsprung"
    channels = ("v_unsprung",)

    def current(self, m: Measurement, F_des: float) -> float:
        return self.I_on if m.channels["v_unsprung"] * m.v < 0.0 else self.I_off


@mypyc_attr(allow_interpreted_subclasses=True)
class ClippedOptimal(_OnOff):
    """Dyke et al. (1996): I_on if (F_des − F)·F > 0 else I_off, F the load cell."""

    name = "clipped_optimal"
    summary = "Dyke 1996: I_on while (F_des − F)·F > 0, F the load cell (with demand lqr: clipped-optimal)"
    needs_demand = True

    def current(self, m: Measurement, F_des: float) -> float:
        F = m.F
        return self.I_on if (F_des - F) * F > 0.0 else self.I_off  # NaN F (no load cell): off


_QC_KEYS = {
    "m_s_kg": "sprung mass (kg)", "m_u_kg": "unsprung mass (kg)",
    "k_s_N_per_m": "suspension stiffness (N/m)", "k_t_N_per_m": "tyre stiffness (N/m)",
}


def lqr_gain(qc: QuarterCarParams, q_acc: float, q_susp: float, q_tyre: float, r: float) -> list[float]:
    """LQR gain K (F = −K·q, q = [x_s − x_u, v_s, x_u − x_r, v_u]) minimising
    ∫ q_acc·a_s² + q_susp·(x_s − x_u)² + q_tyre·(x_u − x_r)² + r·F² dt."""
    try:
        import numpy as np
        from scipy.linalg import solve_continuous_are
    except ImportError:  # pragma: no cover - scipy ships with the test and identify extras
        raise DependencyMissing("the lqr law needs scipy: pip install 'mrctl[identify]'") from None
    ms, mu, ks, kt = qc.m_s_kg, qc.m_u_kg, qc.k_s_N_per_m, qc.k_t_N_per_m
    A = np.array([[0.0, 1.0, 0.0, -1.0], [-ks / ms, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0],
                  [ks / mu, 0.0, -kt / mu, 0.0]])
    B = np.array([[0.0], [-1.0 / ms], [0.0], [1.0 / mu]])
    Ca = np.array([[-ks / ms, 0.0, 0.0, 0.0]])  # a_s = Ca·q + Da·F
    Da = -1.0 / ms
    Q = q_acc * Ca.T @ Ca + np.diag([q_susp, 0.0, q_tyre, 0.0])
    N = q_acc * Ca.T * Da
    R = np.array([[r + q_acc * Da * Da]])
    P = solve_continuous_are(A, B, Q, R, s=N)
    K = np.linalg.solve(R, B.T @ P + N.T)
    return [float(k) for k in K.ravel()]


@mypyc_attr(allow_interpreted_subclasses=True)
class LQR(DemandLaw):
    """Optimal force of the quarter car (Dyke et al. 1996's primary controller)."""

    tracks_force = False  # semi-active: saturation and clipping are its nature

    name = "lqr"
    summary = ("F_des = −K·[x_s − x_u, v_s, x_u − x_r, v_u], K the quarter car's LQR gain; "
               "channels v_sprung, v_unsprung, tyre_defl")
    params = {
        **{k: Num(default=None, optional=True, min=0.0, min_exclusive=True, doc=f"{d}; null = plant.quarter_car's")
           for k, d in _QC_KEYS.items()},
        "q_acc": Num(default=1.0, min=0.0, doc="weight of the body's acceleration² ((m/s²)⁻²)"),
        "q_susp": Num(default=0.0, min=0.0, doc="weight of the suspension stroke² (m⁻²)"),
        "q_tyre": Num(default=1e4, min=0.0, doc="weight of the tyre deflection² (m⁻²)"),
        "r": Num(default=1e-4, min=0.0, min_exclusive=True, doc="weight of the damper force² (N⁻²)"),
    }
    channels = ("v_sprung", "v_unsprung", "tyre_defl")

    def __init__(self, K: list[float]) -> None:
        self.K = [float(k) for k in K]

    @staticmethod
    def _vehicle(cfg: Any, ctx: LawContext) -> tuple[QuarterCarParams | None, list[str]]:
        bench = ctx.extra.get("quarter_car")
        vals: dict[str, Any] = {k: cfg.get(k) if cfg.get(k) is not None else getattr(bench, k, None) for k in _QC_KEYS}
        missing = [f"{k}: needed (no plant.quarter_car to take it from)" for k, v in vals.items() if v is None]
        if missing:
            return None, missing
        return QuarterCarParams(**vals), []

    @classmethod
    def check(cls, cfg: Any, ctx: LawContext) -> list[str]:
        return cls._vehicle(cfg, ctx)[1]

    @classmethod
    def from_config(cls, cfg: Any, ctx: LawContext) -> "LQR":
        qc, errors = cls._vehicle(cfg, ctx)
        if qc is None:
            raise ValueError("; ".join(errors))
        return cls(lqr_gain(qc, cfg.q_acc, cfg.q_susp, cfg.q_tyre, cfg.r))

    def force(self, m: Measurement) -> float:
        ch = m.channels
        k0, k1, k2, k3 = self.K
        return -(k0 * m.x + k1 * ch["v_sprung"] + k2 * ch["tyre_defl"] + k3 * ch["v_unsprung"])
