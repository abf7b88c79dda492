"""Spencer et al.'s phenomenological MR-damper model (modified Bouc–Wen).

Source: B.F. Spencer Jr., S.J. Dyke, M.K. Sain, J.D. Carlson,
"Phenomenological model for magnetorheological dampers", J. Eng. Mech.
123(3), 1997, eqs (10)–(17). A damper model *structurally different* from
the LuGre model the inverse laws invert: a bench built on it tests a law
against model error it cannot describe with its own parameters.

Equations (x piston displacement, ẋ its velocity, y the internal
displacement of the series dashpot c1, z the Bouc–Wen evolutionary
variable, u the coil filter's output, i the commanded current)::

    F  = c1(u)·ẏ + k1·(x − x0)                                         (13)
    ẏ  = [α(u)·z + c0(u)·ẋ + k0·(x − y)] / (c0(u) + c1(u))             (12)
    ż  = −γ·|ẋ − ẏ|·z·|z|^(n−1) − β·(ẋ − ẏ)·|z|^n + A·(ẋ − ẏ)           (11)
    α(u) = αa + αb·u + αc·u²,  c0(u) = c0a + c0b·u,  c1(u) = c1a + c1b·u (14–16)
    u̇  = −η·(u − i)                                                    (17)

Spencer's laws (14)–(16) are linear in u (a voltage there); ``alpha_c``
(default 0) adds a quadratic term, because the RD-1097-01's yield force
grows quadratically at low current (Table I's eq 6). In this package u is a
current in A; the filter (17) is the plant's :class:`DriverLag` with
τ = 1/η.

Integration: the Bouc–Wen state is stiff. Near saturation
(|z| → (A/(γ+β))^(1/n)) ∂ż/∂z ≈ −n·(γ+β)·|ẋ−ẏ|·|z|^(n−1), plus the
coupling through ẏ, −A·α/(c0+c1): with the fitted RD-1097 set this is
of order 10⁴ s⁻¹, so explicit steps of 1 ms diverge. Each tick is split in
``substeps`` substeps, velocity and displacement interpolated linearly
between the ticks; z takes a linearly implicit (Rosenbrock–Euler) step
with its exact Jacobian (y frozen), z ← z + h·f/(1 − h·∂f/∂z), which is
L-stable, then y an implicit-Euler step with the new z. Tested against a
fine-tolerance implicit reference in ``tests/test_boucwen.py``.

Plain floats throughout (the hil_sim clock runs it at 1 kHz).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from mrctl.util.yamlfile import key_repr, short_repr

__all__ = ["BoucWenParams", "BoucWenModel", "SPENCER_1997", "bw_errors", "bw_params_from_mapping"]


@dataclass(frozen=True, slots=True)
class BoucWenParams:
    """The model's constants in SI units (z in m, so A is dimensionless)."""

    c0a: float  # N·s/m, viscous damping at large velocity
    c0b: float  # N·s/(m·A)
    c1a: float  # N·s/m, dashpot for the roll-off at low velocity
    c1b: float  # N·s/(m·A)
    k0: float  # N/m, stiffness at large velocity
    k1: float  # N/m, accumulator stiffness
    x0: float  # m, accumulator's initial displacement
    alpha_a: float  # N/m, Bouc–Wen gain
    alpha_b: float  # N/(m·A)
    gamma: float  # 1/m^n
    beta: float  # 1/m^n
    A: float  # dimensionless
    n: float  # dimensionless, sharpness of yield
    eta: float  # 1/s, coil filter: u̇ = −η·(u − i); 0 = ideal
    alpha_c: float = 0.0  # N/(m·A²), quadratic term of α (not in Spencer's eq 14)

    def alpha(self, u: float) -> float:
        return self.alpha_a + (self.alpha_b + self.alpha_c * u) * u

    def c0(self, u: float) -> float:
        return self.c0a + self.c0b * u

    def c1(self, u: float) -> float:
        return self.c1a + self.c1b * u

    @property
    def tau_s(self) -> float:
        """The coil filter's time constant 1/η (s); 0 for an ideal coil."""
        return 1.0 / self.eta if self.eta > 0.0 else 0.0

    def z_ultimate(self) -> float:
        """|z| under monotonic motion tends to (A/(γ+β))^(1/n) (m)."""
        return (self.A / (self.gamma + self.beta)) ** (1.0 / self.n)

    def check_range(self, I_max: float, samples: int = 101) -> list[str]:
        """Problems that make the model meaningless on [0, I_max] (empty if fine)."""
        problems: list[str] = []
        for name, fn in (("c0", self.c0), ("c1", self.c1), ("alpha", self.alpha)):
            worst = min(fn(I_max * k / (samples - 1)) for k in range(samples))
            if not worst > 0.0:
                problems.append(f"{name}(I) must stay > 0 for I in [0, {I_max:g}] A, but reaches {worst:.6g}")
        if not self.A > 0.0:
            problems.append(f"A must be > 0, got {self.A:g}")
        if not self.n >= 1.0:
            problems.append(f"n must be >= 1, got {self.n:g}")
        if not self.gamma >= abs(self.beta):
            problems.append(f"gamma must be >= |beta| (bounded hysteresis), got {self.gamma:g} and {self.beta:g}")
        if not self.gamma + self.beta > 0.0:
            problems.append("gamma + beta must be > 0")
        if not (self.k0 >= 0.0 and self.k1 >= 0.0 and self.eta >= 0.0):
            problems.append("k0, k1 and eta must be >= 0")
        return problems

    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    def with_overrides(self, **overrides: float) -> "BoucWenParams":
        return replace(self, **overrides)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


#: Spencer et al. 1997, Table 1 (their 3 kN prototype damper, u in volts), in SI.
SPENCER_1997 = BoucWenParams(
    c0a=2100.0, c0b=350.0, c1a=28300.0, c1b=295.0, k0=4690.0, k1=500.0, x0=0.143,
    alpha_a=14000.0, alpha_b=69500.0, gamma=3.63e6, beta=3.63e6, A=301.0, n=2.0, eta=190.0,
)


def bw_errors(data: dict[Any, Any]) -> list[str]:
    """Every problem of a mapping of the names above (unknown keys, values
    that are not finite numbers, the names missing: all but alpha_c are
    required), one line each, naming a key as :func:`key_repr` allows and a
    value as :func:`short_repr` does (a file's content is not echoed)."""
    known = BoucWenParams.names()
    errors = [f"{key_repr(k)}: unknown parameter (expected one of {', '.join(known)})" for k in data
              if k not in known]
    errors += [f"{k}: must be a finite number, got {short_repr(v)}" for k, v in data.items() if k in known
               and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)))]
    missing = [k for k in known if k not in data and k != "alpha_c"]
    if missing:
        errors.append(f"missing parameter(s): {', '.join(missing)}")
    return errors


def bw_params_from_mapping(data: Any) -> BoucWenParams:
    """A parameter set from a mapping of the names above (all but alpha_c required).

    Raises ``ValueError`` listing every problem (:func:`bw_errors`); the
    config layer adds the file and key path."""
    if not isinstance(data, dict):
        raise ValueError(f"must be a mapping of {', '.join(BoucWenParams.names())}")
    errors = bw_errors(data)
    if errors:
        raise ValueError("; ".join(errors))
    return BoucWenParams(**{k: float(v) for k, v in data.items()})


class BoucWenModel:
    """The mechanical part, eqs (11)–(16), stepped once per tick.

    Tick protocol (the same as :class:`mrctl.model.lugre.LuGreModel`):
    ``advance(x, v, u, dt)`` integrates (y, z) from the previous tick to
    this one with u held and x, ẋ linear in between; ``force(x, v, u)``
    is the force now for the current u applied at this tick."""

    __slots__ = ("p", "y", "z", "x_prev", "v_prev", "substeps", "_u", "_al", "_c0", "_c1", "_pw")

    def __init__(self, params: BoucWenParams, substeps: int = 8) -> None:
        if substeps < 1:
            raise ValueError("substeps must be >= 1")
        self.p = params
        self.substeps = substeps
        self._pw = params.n - 1.0
        self.reset()
        self._set_current(0.0)

    def reset(self, x0: float = 0.0, v0: float = 0.0) -> None:
        self.y = x0
        self.z = 0.0
        self.x_prev = x0
        self.v_prev = v0

    def _set_current(self, u: float) -> None:
        p = self.p
        self._u = u
        self._al = p.alpha_a + (p.alpha_b + p.alpha_c * u) * u
        self._c0 = p.c0a + p.c0b * u
        self._c1 = p.c1a + p.c1b * u

    def advance(self, x: float, v: float, u: float, dt: float) -> None:
        """Move (y, z) from the previous tick to this one (u held)."""
        if u != self._u:
            self._set_current(u)
        p = self.p
        al, c0, c1, k0 = self._al, self._c0, self._c1, p.k0
        cs = c0 + c1
        kap = al / cs  # −∂(ẋ−ẏ)/∂z
        gam, bet, A, n, pw = p.gamma, p.beta, p.A, p.n, self._pw
        x0, v0 = self.x_prev, self.v_prev
        self.x_prev, self.v_prev = x, v
        y, z = self.y, self.z
        N = self.substeps
        h = dt / N
        dxs, dvs = (x - x0) / N, (v - v0) / N
        hb = 1.0 + h * k0 / cs
        hc = h / cs
        for j in range(N):
            s = j + 0.5
            xm = x0 + dxs * s
            vm = v0 + dvs * s
            r = (c1 * vm - al * z - k0 * (xm - y)) / cs  # ẋ − ẏ
            az = -z if z < 0.0 else z
            ar = -r if r < 0.0 else r
            zp = az if pw == 1.0 else az ** pw  # |z|^(n−1)
            zn = zp * az  # |z|^n
            # f = ż (eq 11) and J = ∂f/∂z with y frozen (r depends on z through ẏ)
            f = A * r - gam * ar * z * zp - bet * r * zn
            J = -A * kap - gam * ar * n * zp - bet * r * n * zp * (1.0 if z >= 0.0 else -1.0) + bet * kap * zn
            J += gam * kap * z * zp if r >= 0.0 else -gam * kap * z * zp
            if J < 0.0:  # stiff direction: linearly implicit step (L-stable)
                z += h * f / (1.0 - h * J)
            else:  # not stiff there: plain Euler
                z += h * f
            y = (y + hc * (al * z + c0 * vm + k0 * xm)) / hb
        self.y, self.z = y, z

    def force(self, x: float, v: float, u: float) -> float:
        """Force (N) at the present state for displacement x, velocity v, current u."""
        if u != self._u:
            self._set_current(u)
        p = self.p
        c1 = self._c1
        ydot = (self._al * self.z + self._c0 * v + p.k0 * (x - self.y)) / (self._c0 + c1)
        return c1 * ydot + p.k1 * (x - p.x0)


class BoucWenPlant:
    """Spencer's damper as the driver sees it: the plant interface of
    :class:`mrctl.model.plant.DamperPlant` (``tick(v, I_cmd, x)``,
    ``I_applied``, ``F``, ``z``, ``tau_s``), so :class:`SimBench`, the sim
    link, ``mrctl simulate`` and ``hil_sim`` all take it.

    The coil filter (eq 17) is a :class:`DriverLag` with τ = 1/η, or
    ``driver_tau_s`` when given (a bench key overrides the set's η)."""

    __slots__ = ("model", "driver", "dt", "I_applied", "F", "_started")

    def __init__(self, params: BoucWenParams, dt: float, driver_tau_s: float | None = None,
                 substeps: int = 8) -> None:
        from mrctl.model.plant import DriverLag

        self.model = BoucWenModel(params, substeps)
        self.driver = DriverLag(params.tau_s if driver_tau_s is None else driver_tau_s, dt)
        self.dt = dt
        self.I_applied = 0.0
        self.F = 0.0
        self._started = False

    @property
    def z(self) -> float:
        """The Bouc–Wen state z (m), for the logs."""
        return self.model.z

    @property
    def tau_s(self) -> float:
        """The coil filter's time constant in effect (s)."""
        return self.driver.tau_s(self.dt)

    def tick(self, v: float, I_cmd: float, x: float = 0.0) -> float:
        m = self.model
        if self._started:
            m.advance(x, v, self.I_applied, self.dt)
        else:
            self._started = True
            m.reset(x, v)
        I = self.driver.update(I_cmd)
        self.I_applied = I
        F = self.F = m.force(x, v, I)
        return F
