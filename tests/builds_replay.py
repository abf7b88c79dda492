"""Replays scripted samples through the controller and prints every row, bit for bit.

``python tests/builds_replay.py`` prints one JSON object: per case, each
tick's log row (the recorder's 15 values, as ``float.hex``) and the law
fault if one ended the run. tests/test_builds.py runs it under the
compiled build and under ``MRCTL_PURE_PYTHON=1`` and requires the two to
be equal: the compiled tick must compute what its source says.

The samples have what a real DAQ gives a controller: noise and
quantisation, a displacement-only channel set (the observer), missing
samples, a NaN, a repeated sequence number, a gap in the device's clock,
a sample out of range, ticks the loop skipped, and a reload of the laws
halfway.
"""

from __future__ import annotations

import json
import math
import random
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DT = 1e-3

#: (case name, demand section, inverse section, sensing section or None, channels)
CASES: list[tuple[str, dict[str, Any], dict[str, Any], dict[str, Any] | None]] = [
    ("paper", {"type": "viscous", "c_des": 500.0}, {"law": "paper"}, None),
    ("smooth", {"type": "viscous", "c_des": 500.0}, {"law": "smooth"}, None),
    ("smooth_lag", {"type": "viscous", "c_des": 800.0}, {"law": "smooth", "lag_s": 0.005}, None),
    ("closed", {"type": "viscous", "c_des": 500.0}, {"law": "closed"}, None),
    ("closed_observer", {"type": "viscous", "c_des": 250.0}, {"law": "closed"},
     {"velocity": "observer", "x_noise_m": 2e-6}),
    ("constant_force", {"type": "constant", "F_N": 12.0}, {"law": "smooth"}, None),
    ("constant_current", {"type": "viscous", "c_des": 500.0}, {"law": "constant", "current_A": 0.3}, None),
    ("schedule", {"type": "viscous", "c_des": 500.0},
     {"law": "schedule", "currents_A": [0.1, 0.4, 0.2], "step_s": 0.15}, None),
    ("skyhook", {"type": "skyhook", "c_sky": 600.0}, {"law": "smooth"}, None),
    ("groundhook_onoff", {"type": "viscous", "c_des": 500.0}, {"law": "groundhook_onoff"}, None),
    ("clipped_optimal", {"type": "lqr"}, {"law": "clipped_optimal"}, None),
    ("law_fault", {"type": "viscous", "c_des": 500.0}, {"law": "bad_laws:ReturnsNaN", "after_ticks": 300}, None),
    # laws: table (per-level Θ and bench terms interpolated) in the plant and the laws
    ("smooth_table", {"type": "viscous", "c_des": 500.0}, {"law": "smooth", "_parameters": "table"}, None),
    ("closed_table", {"type": "viscous", "c_des": 500.0}, {"law": "closed", "_parameters": "table"}, None),
    ("paper_table", {"type": "viscous", "c_des": 500.0}, {"law": "paper", "_parameters": "table"}, None),
    # the optional model terms (σ1(v), a rise and a fall lag, the hysteretic stiffness) in the laws
    ("paper_extras", {"type": "viscous", "c_des": 500.0}, {"law": "paper", "_parameters": "extras"}, None),
    ("smooth_extras", {"type": "viscous", "c_des": 500.0}, {"law": "smooth", "_parameters": "extras"}, None),
    ("closed_extras", {"type": "viscous", "c_des": 500.0}, {"law": "closed", "_parameters": "extras"}, None),
]

#: Table I with every optional term on, for the ``_parameters: extras`` cases
EXTRA_PARAMS: dict[str, Any] = {"sigma1_vd": 0.04, "tau_input": 0.004, "tau_input_fall": 0.012,
                                "k_hys_pos": 150.0, "k_hys_neg": 600.0, "x_hys": 0.004, "tau_field": 0.006}

#: a table set for the ``_parameters: table`` cases: Θ through 4 levels, with bench terms
TABLE_PARAMS: dict[str, Any] = {"laws": "table", "table": {
    "input": [0.0, 0.15, 0.35, 0.6], "Fc": [3.0, 12.0, 20.0, 26.0], "Fs": [2.5, 5.0, 9.0, 11.0],
    "sigma0": [9.0e4, 1.1e5, 1.4e5, 1.8e5], "sigma1": [-280.0, -100.0, 120.0, 400.0],
    "sigma2": [15.0, 30.0, 50.0, 75.0], "vs": [0.028, 0.026, 0.023, 0.018],
    "F_offset": [1.0, 1.5, 2.5, 2.0], "k_x": [0.0, 50.0, 100.0, 80.0]}}


def _samples(n: int, seed: int) -> list[Any]:
    """Scripted samples: (seq, t_dev, x, v, F, status, I_applied), None = the read failed."""
    from mrctl.io.base import Sample, Status

    rng = random.Random(seed)
    status = int(Status.OUTPUT_ENABLED)
    out: list[Any] = []
    seq = 0
    for k in range(n):
        t = k * DT
        x = 0.01 * math.sin(2 * math.pi * t) + rng.gauss(0.0, 2e-6)
        x = round(x / 1e-6) * 1e-6  # a 1 um LVDT step
        v = 0.02 * math.pi * math.cos(2 * math.pi * t) + rng.gauss(0.0, 1e-3)
        F = 500.0 * v + 3.0 * math.copysign(1.0, v) + rng.gauss(0.0, 0.2)
        Ia = 0.3 + 0.1 * math.sin(7.0 * t)
        seq += 1
        if k in (120, 121, 400):
            out.append(None)  # the read failed (missing)
            continue
        if k == 200:
            x = math.nan  # a corrupt value
        if k == 300:
            seq -= 1  # the device repeated its last sample (stale)
        if k == 500:
            F = 1e9  # out of range
        if 600 <= k < 612:
            out.append(None)  # a dead link long enough for a FAULT, then auto-resume
            continue
        td = t + (0.003 if k >= 700 else 0.0)  # the device's clock jumps 3 ms (samples it did not send)
        out.append(Sample(seq & 0xFFFFFFFF, td, x, v, F, status, Ia))
    return out


class _Script:
    """An exchange-shaped link over scripted samples, with quarter-car channels."""

    def __init__(self, samples: list[Any]) -> None:
        from mrctl.io.base import Link, LinkError

        class ScriptLink(Link):
            kinds = ("script",)

            def __init__(self) -> None:
                super().__init__(timeout_s=1.0)
                self.i = 0
                self._open = False
                self.channels = {"v_sprung": 0.0, "v_unsprung": 0.0, "tyre_defl": 0.0}

            @classmethod
            def from_config(cls, cfg: Any, context: Any = None) -> "ScriptLink":
                raise NotImplementedError

            @property
            def is_open(self) -> bool:
                return self._open

            def _open_transport(self) -> None:
                self._open = True

            def _close_transport(self) -> None:
                self._open = False

            def describe(self) -> str:
                return "scripted samples"

            def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Any:
                s = samples[self.i % len(samples)]
                t = self.i * DT
                self.channels["v_sprung"] = 0.05 * math.cos(3.0 * t)
                self.channels["v_unsprung"] = 0.08 * math.sin(5.0 * t)
                self.channels["tyre_defl"] = 0.001 * math.sin(4.0 * t)
                self.i += 1
                if s is None:
                    raise LinkError("scripted missing sample")
                return s

            @property
            def true_force_N(self) -> float:
                return math.nan

        self.link = ScriptLink()


def _experiment(demand: dict[str, Any], inverse: dict[str, Any], sensing: dict[str, Any] | None) -> Any:
    from mrctl.config import validate_experiment
    from mrctl.experiment import build

    inverse = dict(inverse)
    params: Any = {"table": TABLE_PARAMS, "extras": EXTRA_PARAMS}.get(inverse.pop("_parameters", None), "table1")
    data: dict[str, Any] = {
        "version": 1, "name": "builds", "duration_s": 1.0, "rate_hz": 1000, "parameters": params,
        "excitation": {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0},
        "demand": demand, "inverse": inverse,
        "safety": {"I_max": 0.6, "max_slew_A_per_s": 200.0, "hold_ticks": 3, "auto_resume": True,
                   "resume_good_ticks": 5, "F_range_N": [-1000.0, 1000.0]},
        "plant": {"bench": "quarter_car"} if demand["type"] in ("skyhook", "lqr") or "onoff" in inverse["law"]
        or inverse["law"] == "clipped_optimal" else {},
        "backend": {"type": "sim"},
    }
    if sensing is not None:
        data["sensing"] = sensing
    return build(validate_experiment(data, ROOT))


def run_case(demand: dict[str, Any], inverse: dict[str, Any], sensing: dict[str, Any] | None,
             n: int = 1000) -> dict[str, Any]:
    from mrctl.core.controller import Controller
    from mrctl.core.safety import SafetyConfig, SafetySupervisor

    exp = _experiment(demand, inverse, sensing)
    link = _Script(_samples(n, seed=7)).link
    link.open()
    rows: list[list[str]] = []

    def record(*values: float) -> None:
        rows.append([float(v).hex() for v in values])

    now = [0]
    sup = SafetySupervisor(SafetyConfig.from_config(exp.config.safety, exp.dt))
    ctl = Controller(link, exp.law, exp.demand, sup, exp.dt, record=record, clock_ns=lambda: now[0],
                     cpu_clock_ns=lambda: now[0], observer=exp.make_observer())
    ctl.meas.channels = link.channels
    exp.law.reset()
    k = 0
    for i in range(n):
        if i == n // 2:  # a SIGHUP reload: fresh laws of the same experiment, taken at the tick boundary
            new = _experiment(demand, inverse, sensing)
            ctl.pending = (new.law, new.demand)
        if i in (250, 800):
            k += 2  # the loop skipped two deadlines
        if not ctl.tick(k, now[0]):
            break
        k += 1
        now[0] += 1_000_000
    fault = ctl.law_fault
    return {"rows": rows, "fault": None if fault is None else str(fault),
            "columns_zeroed": ["compute_us", "late_us"]}


def main() -> int:
    from mrctl.build import tick_build

    out = {"build": tick_build(), "cases": {name: run_case(d, i, s) for name, d, i, s in CASES}}
    json.dump(out, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "tests" / "plugins"))
    sys.exit(main())
