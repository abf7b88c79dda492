"""A validated config turned into live objects: the one table of names.

Every name a user can write in YAML (excitation ``type``, demand ``type``,
inverse ``law``) maps to its class here, so adding a law is one entry.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from mrctl.laws import demand as demand_mod
from mrctl.model import excitation as excitation_mod
from mrctl.config import ConfigError, Node
from mrctl.laws.inverse import ConstantCurrent, InverseLaw, PaperInverse, ScheduleCurrent, SmoothInverse
from mrctl.model.params import LuGreParams
from mrctl.model.plant import DamperPlant, Sensors

EXCITATIONS: dict[str, Callable[[Node], Any]] = {
    "sine": lambda c: excitation_mod.Sine(c.amplitude_m, c.frequency_hz, c.phase_rad),
    "chirp": lambda c: excitation_mod.Chirp(c.amplitude_m, c.f0_hz, c.f1_hz, c.sweep_s),
    "file": lambda c: excitation_mod.FromFile(c.path),
}

DEMANDS: dict[str, Callable[[Node], Any]] = {
    "viscous": lambda c: demand_mod.Viscous(c.c_des),
    "constant": lambda c: demand_mod.ConstantForce(c.F_N),
    "file": lambda c: demand_mod.FromFile(c.path),
}

LAWS: dict[str, Callable[[Node, LuGreParams, float, float], InverseLaw]] = {
    "paper": lambda c, p, I_max, dt: PaperInverse(p, I_max, dt),
    "smooth": lambda c, p, I_max, dt: SmoothInverse(p, I_max, dt, c.eps_N_per_A, c.max_slew_A_per_s),
    "constant": lambda c, p, I_max, dt: ConstantCurrent(c.current_A, I_max),
    "schedule": lambda c, p, I_max, dt: ScheduleCurrent(c.currents_A, c.step_s, I_max, dt),
}


@dataclass
class Experiment:
    """Everything one run needs, built from a config."""

    config: Node
    params: LuGreParams
    dt: float
    I_max: float
    excitation: Any
    demand: Any
    law: InverseLaw

    @property
    def name(self) -> str:
        return self.config.name or "run"

    @property
    def plant_params(self) -> LuGreParams:
        """The simulated damper's parameters: ``plant.parameters``, else the law's."""
        return self.config.plant.parameters or self.params

    def make_plant(self) -> DamperPlant:
        return DamperPlant(self.plant_params, self.dt, self.config.plant.driver_tau_s)

    def make_sensors(self) -> Sensors | None:
        """Sensor model, or None when it would be the identity (fast path)."""
        s = self.config.plant.sensors
        if not any(s.get(k) for k in ("x_noise_m", "v_noise_mps", "F_noise_N", "x_lsb_m", "v_lsb_mps", "F_lsb_N")):
            return None
        return Sensors(s.seed, s.x_noise_m, s.v_noise_mps, s.F_noise_N, s.x_lsb_m, s.v_lsb_mps, s.F_lsb_N)


def build(config: Node) -> Experiment:
    """Instantiate the experiment; file-loading errors become ConfigError."""
    dt = 1.0 / config.rate_hz
    I_max = config.safety.I_max
    try:
        exc = EXCITATIONS[config.excitation.type](config.excitation)
    except ValueError as e:
        raise ConfigError([f"excitation.path: {e}"]) from None
    try:
        dem = DEMANDS[config.demand.type](config.demand)
    except ValueError as e:
        raise ConfigError([f"demand.path: {e}"]) from None
    law = LAWS[config.inverse.law](config.inverse, config.parameters, I_max, dt)
    return Experiment(config, config.parameters, dt, I_max, exc, dem, law)
