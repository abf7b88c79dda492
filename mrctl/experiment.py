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
from mrctl.config.bench import quarter_car_params
from mrctl.config.laws import law_context as _law_context
from mrctl.errors import LinkFailure, MrctlError
from mrctl.estimation import KinematicObserver, VelocityLead
from mrctl.io import link_class_for
from mrctl.io.base import Link, LinkError
from mrctl.laws.base import CurrentLaw, DemandLaw, Law, LawContext
from mrctl.laws.registry import law_class
from mrctl.model import excitation as excitation_mod
from mrctl.model import road
from mrctl.model.bench import SimBench
from mrctl.model.boucwen import BoucWenPlant
from mrctl.model.quarter_car import QuarterCarBench, QuarterCarParams
from mrctl.model.params import LuGreParams
from mrctl.model.plant import DamperPlant, Sensors
from mrctl.util.csvtable import CsvError, load_series


def _excitation_file(c: Node) -> excitation_mod.Sampled:
    """t, x and v if there (a run log is one: its other columns are ignored,
    its missing samples skipped)."""
    data = load_series(c.path, ("t", "x"), optional=("v",), gaps_ok=True)
    out = excitation_mod.Sampled(data["t"], data["x"], data.get("v"))
    out.settle_s = float(c.get("settle_s") or 0.0)
    return out


#: excitation.type → profile
EXCITATIONS: dict[str, Callable[[Node], Any]] = {
    "sine": lambda c: excitation_mod.Sine(c.amplitude_m, c.frequency_hz, c.phase_rad),
    "chirp": lambda c: excitation_mod.Chirp(c.amplitude_m, c.f0_hz, c.f1_hz, c.sweep_s),
    "file": _excitation_file,
    "bump": lambda c: road.Bump(c.height_m, c.length_m, c.speed_mps, c.at_s),
    "iso8608": lambda c: road.ISO8608Road(c.road_class, c.speed_mps, c.seed, c.length_m, c.scale),
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
    keys = ("x_noise_m", "v_noise_mps", "F_noise_N", "x_lsb_m", "v_lsb_mps", "F_lsb_N", "F_offset_N")
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
                   has_velocity: bool = True, quarter_car: QuarterCarParams | None = None,
                   trajectory: tuple[list[float], list[float]] | None = None) -> SimBench | QuarterCarBench:
    """The simulated bench (shaker + damper + driver + sensors) both the
    in-process link and ``hil_sim`` run; ``model`` is the validated
    ``plant.model`` section (None: LuGre with ``params``); with
    ``quarter_car`` the damper sits in a quarter car and the excitation is
    the road (``plant.bench``); ``trajectory``: the shaker's motion computed
    up front (:class:`SimBench`)."""
    plant = make_plant(model, params, dt, driver_tau_s)
    if quarter_car is not None:
        return QuarterCarBench(params, excitation, dt, quarter_car, driver_tau_s, sensors, has_load_cell, plant,
                               has_velocity)
    return SimBench(params, excitation, dt, driver_tau_s, sensors, has_load_cell,
                    plant=plant, has_velocity=has_velocity, trajectory=trajectory)


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
    demand: DemandLaw | None
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

    def make_bench(self, trajectory: tuple[list[float], list[float]] | None = None) -> SimBench | QuarterCarBench:
        """The in-process simulated bench (backend sim; ``trajectory``: the
        shaker's motion by tick, computed up front)."""
        p = self.config.plant
        return make_sim_bench(self.plant_params, self.excitation, self.dt, p.driver_tau_s, self.make_sensors(),
                              p.sensors.load_cell, p.model, p.sensors.velocity, quarter_car_params(p), trajectory)

    @property
    def command_delay_ticks(self) -> int:
        """Ticks from a sample to its current at the driver, as ``mrctl simulate``
        models them (``plant.command_delay_ticks``): explicit, or 'auto' = 1 on
        an exchange link (the current computed from a sample goes out with the
        next tick's request), 0 on a split link (the in-process sim)."""
        d = self.config.plant.command_delay_ticks
        if d == "auto":
            return 0 if link_class_for(self.config.backend).split else 1
        return int(d)

    def make_observer(self) -> KinematicObserver | None:
        """The velocity observer (``sensing.velocity: observer``), None when off."""
        return make_observer(self.config.sensing, self.dt)

    def make_link(self) -> Link:
        """The link named by ``backend.type`` (the BACKENDS table)."""
        return link_class_for(self.config.backend).from_config(self.config.backend, self)

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
    return _law_context(config)


def make_laws(config: Node) -> tuple[DemandLaw | None, CurrentLaw]:
    """The demand (None when the file has none) and current laws a config
    names (built-ins and plugins, :mod:`mrctl.laws.registry`); a law that
    cannot be built is a ConfigError naming its section."""
    return (build_law("demand", config.demand, config) if config.get("demand") is not None else None,
            build_law("current", config.inverse, config))  # type: ignore[return-value]


def build_law(kind: str, node: Node, config: Node) -> Law:
    """One law from its validated section; whatever its constructor raises
    (a plugin's too) is a ConfigError naming the section, never a traceback."""
    section, key = ("demand", "type") if kind == "demand" else ("inverse", "law")
    name = node.get(key)
    try:
        law = law_class(kind, name).from_config(node, law_context(config))
    except (CsvError, KeyError, ValueError, TypeError, ArithmeticError, LookupError, OSError) as e:
        where = f"{section}.path" if isinstance(e, CsvError) else f"{section}.{key}"
        raise ConfigError([f"{where}: {name!r} cannot be built: {e}"]) from None
    except MrctlError:
        raise
    except (Exception, SystemExit, GeneratorExit) as e:  # noqa: BLE001 - a plugin's constructor may raise anything
        raise ConfigError([f"{section}.{key}: {name!r} cannot be built: {type(e).__name__}: {e}"]) from None
    if not isinstance(law, (DemandLaw if kind == "demand" else CurrentLaw)):
        raise ConfigError([f"{section}.{key}: {name!r}.from_config returned {type(law).__name__}, not a law"])
    return law


def try_reset(demand: DemandLaw | None, law: CurrentLaw) -> None:
    """Reset each law once as it is built, so that a ``reset()`` that raises
    (a plugin's) is a ConfigError naming the law (``mrctl check``, and
    ``mrctl run`` before the device is touched, exit 2), never an internal
    error at start-up. ``SystemExit`` and the like from a plugin count too;
    only a real Ctrl-C (KeyboardInterrupt) goes through."""
    for section, key, obj in (("demand", "type", demand), ("inverse", "law", law)):
        if obj is None:
            continue
        try:
            obj.reset()
        except MrctlError:
            raise
        except (Exception, SystemExit, GeneratorExit) as e:  # noqa: BLE001 - a plugin's reset may raise anything
            name = obj.name or type(obj).__name__
            raise ConfigError([f"{section}.{key}: {name!r}: reset() raised {type(e).__name__}: {str(e)[:200]}"]) from None


def check_channels(laws: tuple[Law | None, ...], provided: Any, what: str) -> None:
    """Refuse to start when a law reads a channel the link does not provide."""
    have = set(provided)
    for law, section in zip(laws, ("demand", "inverse")):
        missing = [c for c in getattr(law, "channels", ()) if c not in have]
        if law is not None and missing:
            raise ConfigError([f"{section}: the law {law.name or type(law).__name__!r} needs channel(s) "
                               f"{', '.join(missing)}; {what} provides {', '.join(sorted(have)) or 'none'}"])


def link_channels(exp: Experiment, link: Link) -> None:
    """At start-up, with the link open: ask the device for its extra channels
    when a law reads any (only then: an older device is not asked), and
    refuse the start (ConfigError, exit 2) if one is missing."""
    laws = (exp.demand, exp.law)
    if any(getattr(law, "channels", ()) for law in laws):
        try:
            link.request_channels()
        except (LinkError, OSError) as exc:
            raise LinkFailure(f"cannot ask the device for its channels: {exc}") from None
    check_channels(laws, getattr(link, "channels", {}), link.describe())


def build(config: Node) -> Experiment:
    """Instantiate the experiment; file-loading errors become ConfigError."""
    dt = 1.0 / config.rate_hz
    exc = make_excitation(config.excitation)
    dem, law = make_laws(config)
    try_reset(dem, law)
    return Experiment(config, config.parameters, dt, config.safety.I_max, exc, dem, law)
