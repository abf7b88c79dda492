"""Schema of the simulated bench's type and the road profiles (docs/quarter-car.md).

``plant.bench`` chooses what the simulated damper is mounted in: the
``shaker`` (the damper's stroke is the excitation, the paper's rig) or the
``quarter_car`` (the excitation is the road under a 2-DOF quarter car,
``plant.quarter_car``). The road profiles ``bump`` and ``iso8608`` are
excitation types beside sine, chirp (a sine sweep) and file.
"""

from __future__ import annotations

from typing import Any

from mrctl.model.quarter_car import CHANNELS, QuarterCarParams
from mrctl.model.road import ISO8608_GD0
from mrctl.util.schema import Node, Num, Section, Str

#: plant.bench → the extra channels that bench provides (the sim link hands them to the laws)
BENCH_CHANNELS: dict[str, tuple[str, ...]] = {"shaker": (), "quarter_car": CHANNELS}

_QC = QuarterCarParams()


def bench_fields() -> dict[str, Any]:
    """The ``plant`` keys of the bench type (``bench``, ``quarter_car``)."""
    return {
        "bench": Str(default="shaker", choices=tuple(BENCH_CHANNELS),
                     doc="shaker: the excitation is the damper's stroke; quarter_car: the excitation is the "
                         "road under a quarter car (plant.quarter_car, docs/quarter-car.md)"),
        "quarter_car": Section({
            "m_s_kg": Num(default=_QC.m_s_kg, min=0.0, min_exclusive=True, doc="sprung mass (kg)"),
            "m_u_kg": Num(default=_QC.m_u_kg, min=0.0, min_exclusive=True, doc="unsprung mass (kg)"),
            "k_s_N_per_m": Num(default=_QC.k_s_N_per_m, min=0.0, min_exclusive=True,
                               doc="suspension spring (N/m)"),
            "k_t_N_per_m": Num(default=_QC.k_t_N_per_m, min=0.0, min_exclusive=True, doc="tyre stiffness (N/m)"),
            "c_t_Ns_per_m": Num(default=_QC.c_t_Ns_per_m, min=0.0, doc="tyre damping (N·s/m)"),
        }, doc="the quarter car (plant.bench: quarter_car); laws such as lqr take the vehicle from here"),
    }


def road_excitations() -> dict[str, dict[str, Any]]:
    """Excitation variants for roads (also usable on the shaker)."""
    return {
        "bump": {
            "height_m": Num(min=-1.0, max=1.0, doc="bump height (m); negative = a pothole"),
            "length_m": Num(min=0.0, min_exclusive=True, max=1000.0, doc="bump length along the road (m)"),
            "speed_mps": Num(min=0.0, min_exclusive=True, max=100.0, doc="vehicle speed (m/s)"),
            "at_s": Num(default=0.5, min=0.0, doc="time the wheel reaches the bump (s)"),
        },
        "iso8608": {
            "road_class": Str(choices=tuple(ISO8608_GD0), doc="ISO 8608 road class (A best, H worst)"),
            "speed_mps": Num(min=0.0, min_exclusive=True, max=100.0, doc="vehicle speed (m/s)"),
            "seed": Num(default=0, integer=True, min=0, doc="random phases (same seed, same road)"),
            "length_m": Num(default=1000.0, min=1.0, max=1e5, doc="profile length, repeated after it (m)"),
            "scale": Num(default=1.0, min=0.0, max=10.0, doc="height scale (a lab-scale rig: e.g. 0.25)"),
        },
    }


def quarter_car_params(plant: Node | None) -> QuarterCarParams | None:
    """The quarter car a validated ``plant`` section describes, if its bench is one."""
    if plant is None or plant.get("bench") != "quarter_car":
        return None
    q = plant.quarter_car
    return QuarterCarParams(q.m_s_kg, q.m_u_kg, q.k_s_N_per_m, q.k_t_N_per_m, q.c_t_Ns_per_m)
