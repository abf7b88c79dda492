"""The figures a sweep keeps per point, from one offline simulation.

The summary figures are ``mrctl simulate``'s (mrctl/runlog/metrics.py, the
quarter car's ride figures); the rest are computed here from the same run
over the same window (t ≥ the excitation's settle time). The two
feasibility floors cost 13 more simulations each point (the damper's reach
at constant currents): bench/robust_scenarios.py's definitions.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

#: mrctl simulate's summary figures (the ride ones only on a quarter car: NaN elsewhere)
SUMMARY = ("force_nrmse", "force_rmse_N", "max_current_step_A", "share_at_zero", "share_at_I_max",
           "rms_a_sprung_mps2", "rms_tyre_defl_m", "rms_stroke_m", "ticks", "simulated_s", "window_start_s",
           "window_ticks", "realtime_factor")
#: computed here
DERIVED = ("peak_current_A", "rms_current_A", "ticks_at_I_max", "ticks_at_zero", "reach_floor", "noise_floor")
METRICS = SUMMARY + DERIVED
DEFAULT_METRICS = ("force_nrmse", "max_current_step_A", "peak_current_A", "rms_current_A", "ticks_at_I_max")
#: what each figure is (docs/sweeps.md)
METRIC_DOCS = {
    "force_nrmse": "RMS(F − F_des) / peak-to-peak of F_des over the window (mrctl simulate's force NRMSE)",
    "force_rmse_N": "RMS(F − F_des) over the window (N)",
    "max_current_step_A": "largest |I_k − I_k−1| over the window (A)",
    "share_at_zero": "share of the window's ticks at 0 A",
    "share_at_I_max": "share of the window's ticks at I_max (the clamp)",
    "rms_a_sprung_mps2": "quarter car: RMS body acceleration (m/s²); NaN on the shaker",
    "rms_tyre_defl_m": "quarter car: RMS tyre deflection (m)",
    "rms_stroke_m": "quarter car: RMS damper stroke (m)",
    "ticks": "ticks simulated (fewer than asked after a law fault)",
    "simulated_s": "simulated time (s)",
    "window_start_s": "start of the window the figures are over (s): the excitation's settle time",
    "window_ticks": "ticks in that window",
    "realtime_factor": "simulated time / wall time of the loop (a timing: differs run to run)",
    "peak_current_A": "largest commanded current over the window (A)",
    "rms_current_A": "RMS commanded current over the window (A)",
    "ticks_at_I_max": "ticks of the window at I_max (the clamp)",
    "ticks_at_zero": "ticks of the window at 0 A",
    "reach_floor": "RMS of F_des outside what the damper reaches at 13 constant currents, / peak-to-peak "
                   "(13 more simulations per point; bench/robust_scenarios.py)",
    "noise_floor": "white noise F_des carries (RMS second difference / √6), / peak-to-peak",
}
#: constant currents over [0, I_max] that span what the damper reaches
FLOOR_CURRENTS = 13


def _window(res: Any) -> np.ndarray:
    t = res.columns["t"]
    return t >= res.summary.get("window_start_s", t[0] if len(t) else 0.0)


def _peak(res: Any, exp: Any) -> float:
    I = res.columns["I"][_window(res)]
    return float(np.max(I)) if I.size else math.nan


def _rms(res: Any, exp: Any) -> float:
    I = res.columns["I"][_window(res)]
    return float(np.sqrt(np.mean(I * I))) if I.size else math.nan


def _ticks_at(top: bool) -> Callable[[Any, Any], float]:
    def f(res: Any, exp: Any) -> float:
        I = res.columns["I"][_window(res)]
        return float(np.sum(I >= exp.I_max - 1e-9) if top else np.sum(I <= 1e-9))
    return f


_COMPUTED: dict[str, Callable[[Any, Any], float]] = {
    "peak_current_A": _peak, "rms_current_A": _rms, "ticks_at_I_max": _ticks_at(True), "ticks_at_zero": _ticks_at(False),
}


def floors(config: dict[str, Any], base_dir: Path, res: Any, exp: Any, duration_s: float) -> tuple[float, float]:
    """(reach floor, noise floor) as fractions of F_des's peak-to-peak over t ≥ 1 s after the start.

    Reach: the bench at :data:`FLOOR_CURRENTS` constant currents over [0, I_max] with exact sensors; the RMS
    distance of F_des outside the band of those forces. Noise: the white noise F_des itself carries (RMS of
    its second difference / √6). No law does better than either."""
    from mrctl.config import validate_experiment
    from mrctl.experiment import build
    from mrctl.offline.simulate import simulate

    bands = []
    for i in range(FLOOR_CURRENTS):
        data = copy.deepcopy(config)
        data["inverse"] = {"law": "constant", "current_A": exp.I_max * i / (FLOOR_CURRENTS - 1)}
        if isinstance(data.get("plant"), dict):
            data["plant"].pop("sensors", None)
        data.pop("sensing", None)
        bands.append(simulate(build(validate_experiment(data, base_dir)), duration_s).columns["F"])
    F_des, t = res.columns["F_des"], res.columns["t"]
    n = min(len(F_des), *(len(b) for b in bands))
    F_des, t = F_des[:n], t[:n]
    lo, hi = np.min([b[:n] for b in bands], axis=0), np.max([b[:n] for b in bands], axis=0)
    w = t >= t[0] + 1.0
    p2p = float(np.ptp(F_des[w]))
    dist = np.maximum(0.0, np.maximum(lo - F_des, F_des - hi))[w]
    noise = float(np.std(np.diff(F_des[w], 2)) / math.sqrt(6.0))
    return float(np.sqrt(np.mean(dist * dist))) / p2p, noise / p2p


def compute(names: list[str], res: Any, exp: Any, config: dict[str, Any], base_dir: Path,
            duration_s: float) -> dict[str, float]:
    """The named figures of one run (NaN where a figure does not apply)."""
    out: dict[str, float] = {}
    for name in names:
        if name in _COMPUTED:
            out[name] = _COMPUTED[name](res, exp)
        elif name in ("reach_floor", "noise_floor"):
            if "reach_floor" not in out:
                out["reach_floor"], out["noise_floor"] = floors(config, base_dir, res, exp, duration_s)
        else:
            out[name] = float(res.summary.get(name, math.nan))
    return {n: out[n] for n in names}
