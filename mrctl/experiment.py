"""A validated config turned into live objects: the one place of name tables.

Every name a user can write in YAML maps to its class through a table:
excitation ``type`` (:data:`EXCITATIONS`), demand ``type`` and inverse
``law`` (:mod:`mrctl.laws.registry`), ``backend.type``
(:data:`mrctl.io.BACKENDS`), the simulated damper's ``plant.model.type``
(:data:`PLANTS`). ``mrctl simulate`` and ``mrctl run`` (and
``hil_sim``, for its bench) build what they need through here, so the same
YAML means the same objects everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from mrctl.config import ConfigError, Node
from mrctl.estimation import KinematicObserver, VelocityLead
from mrctl.io import link_class
from mrctl.io.base import Link
from mrctl.laws.base import CurrentLaw, DemandLaw, LawContext
from mrctl.laws.registry import current_laws, demand_laws
from mrctl.model import excitation as excitation_mod
from mrctl.model.bench import SimBench
from mrctl.model.boucwen import BoucWenPlant
from mrctl.model.params import LuGreParams
from mrctl.model.plant import DamperPlant, Sensors
from mrctl.util.csvtable import CsvError, load_series


def _excitation_file(c: Node) -> excitation_mod.Sampled:
    data = load_series(c.path, ("t", "x"))
    return excitation_mod.Sampled(data["t"], data["x"], data.get("v"))


#: excitation.type → profile
EXCITATIONS: dict[str, Callable[[Node], Any]] = {
    "sine": lambda c: excitation_mod.Sine(c.amplitude_m, c.frequency_hz, c.phase_rad),
    "chirp": lambda c: excitation_mod.Chirp(c.amplitude_m, c.f0_hz, c.f1_hz, c.sweep_s),
    "file": _excitation_file,
}


def make_excitation(c: Node) -> Any:
    """The shaker profile of an ``excitation`` section; a bad file is a ConfigError."""
    try:
        return EXCITATIONS[c.type](c)
    except (CsvError, ValueError) as e:
        raise ConfigError([f"excitation.path: {e}"]) from None


def make_sensors(s: Node, seed: int | None = None) -> Sensors | None:
    """Sensor model of a ``plant.sensors`` section, or None when it would be
    the identity (the fast path)."""
    keys = ("x_noise_m", "v_noise_mps", "F_noise_N", "x_lsb_m", "v_lsb_mps", "F_lsb_N")
    if not any(s.get(k) for k in keys):
        return None
    return Sensors(s.get("seed", 0) if seed is None else seed, *(s.get(k) for k in keys))


#: plant.model.type → the simulated damper (model node, LuGre set, dt, lag override)
PLANTS: dict[str, Callable[[Node | None, LuGreParams, float, float | None], Any]] = {
    "lugre": lambda m, params, dt, tau: DamperPlant(params, dt, tau),
    "bouc-wen": lambda m, params, dt, tau: BoucWenPlant(m.parameters, dt, tau, m.substeps),
}


def make_plant(model: Node | None, params: LuGreParams, dt: float, driver_tau_s: float | None = None) -> Any:
    """The damper ``plant.model`` names (None: LuGre with ``params``). Every
    plant has the interface of :class:`DamperPlant`: ``tick(v, I_cmd, x)``,
    ``I_applied``, ``F``, ``z``, ``tau_s``."""
    kind = "lugre" if model is None else model.type
    return PLANTS[kind](model, params, dt, driver_tau_s)


def make_sim_bench(params: LuGreParams, excitation: Any, dt: float, driver_tau_s: float | None = None,
                   sensors: Sensors | None = None, has_load_cell: bool = True, model: Node | None = None,
                   has_velocity: bool = True) -> SimBench:
    """The simulated bench (shaker + damper + driver + sensors) both the
    in-process link and ``hil_sim`` run; ``model`` is the validated
    ``plant.model`` section (None: LuGre with ``params``)."""
    return SimBench(params, excitation, dt, driver_tau_s, sensors, has_load_cell,
                    plant=make_plant(model, params, dt, driver_tau_s), has_velocity=has_velocity)


def make_observer(sensing: Node, dt: float) -> KinematicObserver | None:
    """The velocity observer of a ``sensing`` section; None for the DAQ's own velocity."""
    if sensing.velocity != "observer":
        return None
    return KinematicObserver(dt, sensing.x_noise_m, sensing.jerk_psd, sensing.v_noise_mps)


@dataclass
class Experiment:
    """Everything one run needs, built from a config."""

    config: Node
    params: LuGreParams
    dt: float
    I_max: float
    excitation: Any
    demand: DemandLaw
    law: CurrentLaw

    @property
    def name(self) -> str:
        return self.config.name or "run"

    @property
    def plant_params(self) -> LuGreParams:
        """The simulated damper's parameters: ``plant.parameters``, else the law's."""
        return self.config.plant.parameters or self.params

    def make_plant(self) -> Any:
        """The simulated damper (``plant.model``; DamperPlant's interface)."""
        p = self.config.plant
        return make_plant(p.model, self.plant_params, self.dt, p.driver_tau_s)

    def make_sensors(self) -> Sensors | None:
        """Sensor model, or None when it would be the identity (fast path)."""
        return make_sensors(self.config.plant.sensors)

    def make_bench(self) -> SimBench:
        """The in-process simulated bench (backend sim)."""
        p = self.config.plant
        return make_sim_bench(self.plant_params, self.excitation, self.dt, p.driver_tau_s, self.make_sensors(),
                              p.sensors.load_cell, p.model, p.sensors.velocity)

    def make_observer(self) -> KinematicObserver | None:
        """The velocity observer (``sensing.velocity: observer``), None when off."""
        return make_observer(self.config.sensing, self.dt)

    def make_link(self) -> Link:
        """The link named by ``backend.type`` (the BACKENDS table)."""
        return link_class(self.config.backend.type).from_config(self.config.backend, self)

    def make_lead(self, link: Link) -> VelocityLead | None:
        """Latency compensation (``latency.lead_s``): explicit, or 'auto' =
        1.5 ticks on exchange links (one request/reply per tick + the
        device's own tick), nothing on split links. None when off."""
        lead = self.config.latency.lead_s
        lead_s = (0.0 if link.split else 1.5 * self.dt) if lead == "auto" else float(lead)
        return VelocityLead(lead_s, self.dt) if lead_s > 0.0 else None

    def law_context(self) -> LawContext:
        return law_context(self.config)

    def at_rate(self, rate_hz: float) -> "Experiment":
        """The same experiment at another control rate: laws, demand and every
        tick count rebuilt for the new period (``link.on_infeasible: reduce_rate``)."""
        return build(self.config.replace(rate_hz=float(rate_hz)))


def law_context(config: Node) -> LawContext:
    """What laws are built with (file paths in their sections are already
    resolved against the config's directory by the schema)."""
    return LawContext(config.parameters, config.safety.I_max, 1.0 / config.rate_hz)


def make_laws(config: Node) -> tuple[DemandLaw, CurrentLaw]:
    """The demand and current laws a config names; a file that cannot be
    read is a ConfigError naming the key."""
    ctx = law_context(config)
    try:
        dem = demand_laws()[config.demand.type].from_config(config.demand, ctx)
    except (CsvError, ValueError) as e:
        raise ConfigError([f"demand.path: {e}"]) from None
    law = current_laws()[config.inverse.law].from_config(config.inverse, ctx)
    return dem, law  # type: ignore[return-value]


def build(config: Node) -> Experiment:
    """Instantiate the experiment; file-loading errors become ConfigError."""
    dt = 1.0 / config.rate_hz
    exc = make_excitation(config.excitation)
    dem, law = make_laws(config)
    return Experiment(config, config.parameters, dt, config.safety.I_max, exc, dem, law)
