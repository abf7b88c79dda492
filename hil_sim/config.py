"""Bench YAML → validated config for ``python -m hil_sim``.

Reuses mrctl's strict YAML loader and schema machinery (:mod:`mrctl.config`)
and the very same field specs for ``rate_hz``, ``parameters``, ``excitation``
and ``plant``, so a section copied from an experiment file means the same
thing here. Every error names its key path; all errors are collected.

The sensor-noise seed is the top-level ``seed`` (overridable with
``--seed``), not ``plant.sensors.seed``: one seed for the whole bench.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mrctl.util.schema import (
    Bool,
    ConfigError,
    Custom,
    Node,
    Num,
    Section,
    Str,
    validate_fields,
    load_yaml,
)
from mrctl.config import experiment_schema
from mrctl.config.bench import quarter_car_params
from mrctl.experiment import EXCITATIONS, make_sim_bench
from mrctl.model.bench import SimBench
from mrctl.model.params import LuGreParams
from mrctl.model.plant import Sensors
from mrctl.model.quarter_car import QuarterCarBench, QuarterCarParams

from hil_sim.faults import FaultSpec, check_fault_list, parse_fault_arg

__all__ = ["BenchConfig", "bench_schema", "load_bench_config", "validate_bench", "ConfigError"]

#: Largest current the simulated driver accepts (A); above → clamped + CURRENT_CLAMPED.
DEFAULT_I_MAX_A = 2.0
DEFAULT_WATCHDOG_MS = 50

_SENSOR_KEYS = ("x_noise_m", "v_noise_mps", "F_noise_N", "x_lsb_m", "v_lsb_mps", "F_lsb_N", "F_offset_N")


def bench_schema(base_dir: Path) -> dict[str, Any]:
    """The bench schema; relative file paths resolve against ``base_dir``."""
    exp = experiment_schema(base_dir)
    # the seed is top-level here, and so is load_cell (it sets the NO_LOAD_CELL status bit)
    sensors = {k: v for k, v in exp["plant"].fields["sensors"].fields.items() if k not in ("seed", "load_cell")}
    return {
        "version": exp["version"],
        "name": Str(default=None, optional=True),
        "description": Str(default=None, optional=True),
        "rate_hz": exp["rate_hz"],
        "duration_s": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=7 * 86400.0,
                          doc="stop after this many seconds; none = until SIGTERM/SIGINT"),
        "seed": Num(default=0, integer=True, min=0, doc="sensor-noise seed"),
        "parameters": exp["parameters"],
        "excitation": exp["excitation"],
        "plant": Section({
            "model": exp["plant"].fields["model"],
            "driver_tau_s": exp["plant"].fields["driver_tau_s"],
            "bench": exp["plant"].fields["bench"],
            "quarter_car": exp["plant"].fields["quarter_car"],
            "sensors": Section(sensors),
        }),
        "load_cell": Bool(default=True, doc="false: F is NaN and NO_LOAD_CELL is set"),
        "watchdog_ms": Num(default=DEFAULT_WATCHDOG_MS, integer=True, min=1, max=60000,
                           doc="device watchdog when the host asks for the default (SETPOINT watchdog_ms 0, Modbus)"),
        "I_max_A": Num(default=DEFAULT_I_MAX_A, min=0.0, min_exclusive=True, max=10.0,
                       doc="driver range: larger setpoints are clamped and flagged CURRENT_CLAMPED"),
        "faults": Custom(check_fault_list, default=None,
                         doc="scheduled faults: [{kind, at_s, for_s, ...}] (hil_sim/faults.py)"),
        "labjack_t7": Custom(_t7_check, default=None,
                             doc="--device labjack_t7: the bench's wiring to the emulated T7 (hil_sim/labjack_t7.py)"),
    }


def _t7_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    from hil_sim.labjack_t7 import t7_fields

    return validate_fields(t7_fields(), value, path)


@dataclass
class BenchConfig:
    """Everything the bench process needs, as live objects."""

    node: Node
    source: str | None
    rate_hz: float
    duration_s: float | None
    seed: int
    params: LuGreParams
    excitation: Any
    driver_tau_s: float | None
    sensor_kw: dict[str, float]
    load_cell: bool
    watchdog_ms: int
    I_max_A: float
    faults: list[FaultSpec] = field(default_factory=list)
    #: the quarter car the damper sits in (plant.bench: quarter_car), or None: the shaker
    quarter_car: QuarterCarParams | None = None
    #: the validated plant.model section (None: LuGre with ``params``)
    model: Node | None = None
    #: false: the DAQ measures displacement only (v reads NaN)
    has_velocity: bool = True
    #: the bench's wiring to an emulated LabJack T7 (``labjack_t7`` section), or None
    t7: Node | None = None

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    def make_bench(self) -> SimBench | QuarterCarBench:
        """The simulated bench, built as the in-process sim link builds its own
        (:func:`mrctl.experiment.make_sim_bench`): a plant model or bench added
        there is served over every transport."""
        return make_sim_bench(self.params, self.excitation, self.dt, self.driver_tau_s, self.make_sensors(),
                              self.load_cell, self.model, self.has_velocity, self.quarter_car)

    def make_sensors(self) -> Sensors | None:
        """Sensor model (seeded), or None when it would be the identity."""
        if not any(self.sensor_kw.values()):
            return None
        return Sensors(self.seed, **self.sensor_kw)

    def describe(self) -> dict[str, Any]:
        """JSON-able echo of the effective config (for the truth-log summary)."""
        d = self.node.to_dict()
        d["parameters"] = self.params.as_dict()
        d["seed"] = self.seed
        d["duration_s"] = self.duration_s
        d["source"] = self.source
        d["faults"] = [f.as_dict(self.rate_hz) for f in self.faults]
        return d


def validate_bench(data: Any, base_dir: Path, source: str | None = None,
                   seed: int | None = None, duration_s: float | None = None,
                   faults: list[str] | None = None, at_rest: bool = False) -> BenchConfig:
    """Validate parsed YAML (+ CLI overrides); raises ConfigError listing every problem.

    ``faults``: ``--fault`` texts (``KIND@AT_S+FOR_S[,param=value]``), added to
    the YAML's ``faults`` list; ``at_rest`` (``--at-rest``): the shaker holds
    still at x = 0, the bench ``mrctl calibrate`` needs, from any bench file."""
    if data is None:
        data = {}
    if at_rest and isinstance(data, dict):
        data = {**data, "excitation": {"type": "sine", "amplitude_m": 0.0, "frequency_hz": 1.0}}
    if not isinstance(data, dict):
        raise ConfigError([f"config: must be a mapping, got {type(data).__name__}"], source)
    node, errors = validate_fields(bench_schema(base_dir), data, "")
    exc = node.get("excitation")
    if not errors and exc is not None and exc.get("type") == "chirp" and exc.get("f0_hz") == exc.get("f1_hz"):
        errors.append("excitation.f1_hz: must differ from f0_hz (use type: sine for one frequency)")
    if seed is not None and seed < 0:
        errors.append(f"--seed: must be >= 0, got {seed}")
    if duration_s is not None and not (duration_s > 0 and math.isfinite(duration_s)):
        errors.append(f"--duration: must be a positive number of seconds, got {duration_s!r}")
    fault_specs: list[FaultSpec] = list(node.get("faults") or [])
    for i, text in enumerate(faults or ()):
        spec, errs = parse_fault_arg(text, i)
        errors += errs
        if spec is not None:
            fault_specs.append(spec)
    model = node.plant.get("model")
    if model is not None and model.get("type") == "bouc-wen" and model.get("parameters") is not None:
        errors += [f"plant.model.parameters: {e}" for e in model.parameters.check_range(float(node.I_max_A))]
    if errors:
        raise ConfigError(errors, source)
    try:
        excitation = EXCITATIONS[exc.type](exc)
    except ValueError as e:
        raise ConfigError([f"excitation.path: {e}"], source) from None
    s = node.plant.sensors
    return BenchConfig(
        node=node,
        source=source,
        rate_hz=float(node.rate_hz),
        duration_s=duration_s if duration_s is not None else node.duration_s,
        seed=seed if seed is not None else int(node.seed),
        params=node.parameters,
        excitation=excitation,
        driver_tau_s=None if node.plant.driver_tau_s is None else float(node.plant.driver_tau_s),
        sensor_kw={k: float(s.get(k)) for k in _SENSOR_KEYS},
        load_cell=bool(node.load_cell),
        watchdog_ms=int(node.watchdog_ms),
        I_max_A=float(node.I_max_A),
        faults=fault_specs,
        quarter_car=quarter_car_params(node.plant),
        model=node.plant.model,
        has_velocity=bool(s.velocity),
        t7=node.get("labjack_t7"),
    )


def load_bench_config(path: str | Path, seed: int | None = None,
                      duration_s: float | None = None, faults: list[str] | None = None,
                      at_rest: bool = False) -> BenchConfig:
    """Load and validate a bench YAML file (CLI overrides applied on top)."""
    p = Path(path)
    return validate_bench(load_yaml(p), p.parent, str(p), seed=seed, duration_s=duration_s, faults=faults,
                          at_rest=at_rest)

