"""A quarter car on the road, with the MR damper between body and wheel.

Two masses (sprung: the body's share, unsprung: wheel and hub), the
suspension spring k_s and the damper between them, the tyre spring k_t
(and optional tyre damping c_t) between the wheel and the road x_r(t)::

    m_s·a_s = −k_s·(x_s − x_u) − F
    m_u·a_u =  k_s·(x_s − x_u) + F − k_t·(x_u − x_r) − c_t·(v_u − v_r)

F is the damper's force (:class:`~mrctl.model.plant.DamperPlant`, LuGre),
given the stroke x = x_s − x_u (extension positive) and its rate v; it has
the sign of v, so it pulls the body down while the damper extends. Positions
are from static equilibrium (gravity and the static spring load cancel).

Integrator: the linear part is discretised exactly (matrix exponential,
computed once) for the damper force held over the tick and the road
linear between ticks (a first-order hold), so the 2-DOF dynamics are
stable and exact at 1 ms whatever the masses; only the damper's coupling
is explicit (its force is evaluated once per tick at the tick's stroke and
rate, as the real plant's is sampled). Per tick: 4×6 plain-float products.

Tick protocol: the one of :class:`~mrctl.model.bench.SimBench` (the sim link
and hil_sim step either): ``begin_tick(k)``, ``sample()`` (the damper's x,
v and the load cell's last force), ``command(I)``. The extra channels a
law may read are in :attr:`QuarterCarBench.channels`, one dict updated in
place every tick (keys: :data:`CHANNELS`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from mrctl.model.params import LuGreParams
from mrctl.model.plant import DamperPlant, Sensors

#: the channels the quarter-car bench provides (SI units)
CHANNELS = ("x_sprung", "v_sprung", "a_sprung", "x_unsprung", "v_unsprung", "tyre_defl")


@dataclass(frozen=True)
class QuarterCarParams:
    """A lab-scale quarter car sized for the RD-1097-01 (docs/quarter-car.md)."""

    m_s_kg: float = 40.0  #: sprung mass
    m_u_kg: float = 5.0  #: unsprung mass
    k_s_N_per_m: float = 3500.0  #: suspension spring
    k_t_N_per_m: float = 25000.0  #: tyre stiffness
    c_t_Ns_per_m: float = 0.0  #: tyre damping

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not (math.isfinite(value) and (value >= 0.0 if name == "c_t_Ns_per_m" else value > 0.0)):
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")

    @property
    def body_hz(self) -> float:
        """Body-mode frequency (wheel fixed, suspension spring in series with the tyre)."""
        k = self.k_s_N_per_m * self.k_t_N_per_m / (self.k_s_N_per_m + self.k_t_N_per_m)
        return math.sqrt(k / self.m_s_kg) / (2.0 * math.pi)

    @property
    def wheel_hz(self) -> float:
        """Wheel-hop frequency (body fixed)."""
        return math.sqrt((self.k_s_N_per_m + self.k_t_N_per_m) / self.m_u_kg) / (2.0 * math.pi)

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Continuous (A, B_F, B_r) for the state [x_s, v_s, x_u, v_u] and the
        inputs F (damper force) and [x_r, v_r] (road)."""
        ms, mu, ks, kt, ct = self.m_s_kg, self.m_u_kg, self.k_s_N_per_m, self.k_t_N_per_m, self.c_t_Ns_per_m
        A = np.array([[0.0, 1.0, 0.0, 0.0],
                      [-ks / ms, 0.0, ks / ms, 0.0],
                      [0.0, 0.0, 0.0, 1.0],
                      [ks / mu, 0.0, -(ks + kt) / mu, -ct / mu]])
        BF = np.array([0.0, -1.0 / ms, 0.0, 1.0 / mu])
        Br = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [kt / mu, ct / mu]])
        return A, BF, Br


def expm(M: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring of a Taylor series (small,
    well-scaled matrices; no scipy in the model layer)."""
    norm = float(np.max(np.sum(np.abs(M), axis=1)))
    s = max(0, int(math.ceil(math.log2(norm))) + 1) if norm > 0.5 else 0
    X = M / (2.0 ** s)
    E = np.eye(M.shape[0])
    term = np.eye(M.shape[0])
    for n in range(1, 20):
        term = term @ X / n
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


def discretise(p: QuarterCarParams, dt: float) -> np.ndarray:
    """One-tick transition as a 4×(4+1+2+2) matrix: next state from
    [state, F (held), road u_k = (x_r, v_r), road change u_{k+1} − u_k]."""
    A, BF, Br = p.matrices()
    B = np.column_stack([BF, Br])  # inputs [F, x_r, v_r]
    n, m = 4, 3
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n] = A * dt
    M[:n, n:n + m] = B * dt
    M[n:n + m, n + m:] = np.eye(m)  # the inputs ramp by their change over the tick
    E = expm(M)
    Phi, G0, G1 = E[:n, :n], E[:n, n:n + m], E[:n, n + m:]
    return np.column_stack([Phi, G0, G1[:, 1:]])  # F is held: no ramp column for it


class QuarterCarBench:
    """The quarter car on a road profile, advanced tick by tick (SimBench's protocol)."""

    __slots__ = ("excitation", "plant", "sensors", "dt", "k", "kp", "I_cmd", "t", "x", "v", "F", "has_load_cell", "has_velocity",
                 "qc", "state", "u", "channels", "_T", "a_s", "_ms", "_ks")

    def __init__(self, params: LuGreParams, road, dt: float, qc: QuarterCarParams,
                 driver_tau_s: float | None = None, sensors: Sensors | None = None,
                 has_load_cell: bool = True, plant=None, has_velocity: bool = True) -> None:
        self.excitation = road  # the road profile x_r(t) (SimBench's name for the input)
        self.plant = DamperPlant(params, dt, driver_tau_s) if plant is None else plant
        self.sensors = sensors
        self.dt = dt
        self.has_load_cell = has_load_cell
        self.has_velocity = has_velocity
        self.qc = qc
        self._T = [list(map(float, row)) for row in discretise(qc, dt)]
        self._ms, self._ks = qc.m_s_kg, qc.k_s_N_per_m
        self.I_cmd = 0.0
        self.k = -1
        self.kp = -1
        self.t = self.x = self.v = self.F = self.a_s = 0.0
        self.u = (road.position(0.0), road.velocity(0.0))
        #: x_s, v_s, x_u, v_u at tick kp + 1; starts at rest on the road
        self.state = [self.u[0], 0.0, self.u[0], 0.0]
        self.channels: dict[str, float] = dict.fromkeys(CHANNELS, 0.0)

    def begin_tick(self, k: int) -> None:
        """Move to tick k; ticks skipped since the last command run on the held command."""
        while self.kp < k - 1:
            self._step_to(self.kp + 1)
        self.k = k
        self.t = k * self.dt
        self._publish()

    def _step_to(self, j: int) -> None:
        """Produce tick j's force (the state is at tick j) and integrate to j + 1."""
        self.k = j
        self.t = j * self.dt
        self._publish()
        self._force_and_step()

    def _publish(self) -> None:
        xs, vs, xu, vu = self.state
        self.x = xs - xu
        self.v = vs - vu
        xr = self.u[0]
        ch = self.channels
        ch["x_sprung"] = xs
        ch["v_sprung"] = vs
        ch["a_sprung"] = (-self._ks * (xs - xu) - self.F) / self._ms  # with the last force
        ch["x_unsprung"] = xu
        ch["v_unsprung"] = vu
        ch["tyre_defl"] = xu - xr

    def command(self, I_A: float) -> None:
        """Apply the driver input (A) at the present tick; non-finite or negative read as 0 A."""
        self.I_cmd = I_A if I_A > 0.0 and I_A < math.inf else 0.0
        if self.kp < self.k:
            self._force_and_step()

    def finish_tick(self) -> None:
        if self.kp < self.k:
            self._force_and_step()

    def _force_and_step(self) -> None:
        """The damper's force at this tick, then the state at the next one."""
        F = self.F = self.plant.tick(self.v, self.I_cmd, self.x)
        xs, vs, xu, vu = s = self.state
        self.a_s = (-self._ks * (xs - xu) - F) / self._ms
        self.kp = self.k
        t1 = (self.k + 1) * self.dt
        xr0, vr0 = self.u
        xr1, vr1 = self.excitation.position(t1), self.excitation.velocity(t1)
        dx, dv = xr1 - xr0, vr1 - vr0
        self.state = [r[0] * s[0] + r[1] * s[1] + r[2] * s[2] + r[3] * s[3] + r[4] * F + r[5] * xr0
                      + r[6] * vr0 + r[7] * dx + r[8] * dv for r in self._T]
        self.u = (xr1, vr1)

    @property
    def I_applied(self) -> float:
        return self.plant.I_applied

    def sample(self) -> tuple[float, float, float]:
        """Measured (x m, v m/s, F N) of the damper at the present tick: its
        stroke and rate, and the load cell's last completed force."""
        s = self.sensors
        if s is None:
            x, v, F = self.x, self.v, self.F
        else:
            x, v, F = s.x(self.x), s.v(self.v), s.F(self.F)
        return x, (v if self.has_velocity else math.nan), (F if self.has_load_cell else math.nan)
