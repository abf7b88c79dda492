#!/usr/bin/env python3
"""How low can `closed` go by shaping the current around velocity reversals? A bound, not a law.

On the Bouc–Wen bench the residual error of ``closed`` sits in the ~25 ms
after each velocity reversal. This script imposes a fixed current profile on
the law's command over a window of its reversal bins (the ticks relative to
the law's own reversal detection, as its reversal tables index them; the
same profile on every reversal from the second on, mirrored per direction),
inside the slew bound and [0, I_max], the law deciding everywhere else. With
``--search`` it looks for the profile (piecewise linear between knots) that
minimises the scenario's force NRMSE by Nelder–Mead, i.e. *knowing the plant*
through simulation. No law that learns from the load cell does better in
that window than the profile it would converge to, so the result bounds
what learning the post-reversal current can reach.

Measured 2026-11-23 (docs/inverse-laws.md, "Designs measured and not kept"),
bins −8..63: ``bouc_wen`` c_des 250 0.762 % (``closed`` 0.822 %; the 3x
target is 0.753 %), ``bouc_wen_displacement_only`` c_des 250 0.909 %
(``closed`` 1.054 %; the 3x target is 0.780 %).

    python bench/reversal_oracle.py [--scenario bouc_wen_c250] [--search] [--evals 900] [--set KEY=VALUE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.robust_scenarios import DIR, _experiment, parse_sets  # noqa: E402
from mrctl.laws.closed import ClosedLoopInverse  # noqa: E402
from mrctl.offline.simulate import simulate  # noqa: E402

#: bins of the profile, relative to the law's reversal detection (negative: predicted, before it)
LO, HI = -8, 64
#: the knots of the piecewise-linear profile (bins) and the best profiles found (A), per scenario
KNOTS = (-8, 6, 8, 10, 12, 14, 16, 18, 20, 23, 27, 32, 40, 50, 63)
BEST = {
    "bouc_wen_c250": (0.0, 0.0, 0.083, 0.195, 0.299, 0.421, 0.294, 0.151, 0.058, 0.115, 0.109, 0.109, 0.12,
                      0.139, 0.14),
    "bouc_wen_displacement_only_c250": (0.0, 0.0, 0.061, 0.162, 0.261, 0.418, 0.295, 0.181, 0.105, 0.102, 0.116,
                                        0.105, 0.123, 0.137, 0.146),
}


class _Imposed(ClosedLoopInverse):
    """``closed`` with its command replaced by ``profile`` in the window (slew-bounded)."""

    profile: list[float] = []

    def current(self, m, F_des):  # type: ignore[no-untyped-def]
        I = super().current(m, F_des)
        b = self._hist[self._hpos]
        if b >= 0 and self.reversals >= 1:
            j = b % 64 - 8
            if LO <= j < HI:
                step, Ip = self.max_step_A, m.I_cmd
                I = min(max(self.profile[j - LO], Ip - step, 0.0), Ip + step, self.I_max)
                self.I_prev = I
        return I


def nrmse(scenario: str, knots_A: np.ndarray | None, sets: dict | None = None) -> float:
    exp = _experiment(DIR / f"{scenario}.yaml", inverse={"law": "closed", **sets} if sets else None)
    if knots_A is not None:
        exp.law.__class__ = _Imposed
        _Imposed.profile = [float(v) for v in np.interp(np.arange(LO, HI), KNOTS, np.clip(knots_A, 0.0, 0.6))]
    return 100.0 * simulate(exp, 4.0).summary["force_nrmse"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bouc_wen_c250", help="a file of config/experiments/robust/ (no .yaml)")
    ap.add_argument("--search", action="store_true", help="Nelder-Mead from the stored (or a plain) profile")
    ap.add_argument("--evals", type=int, default=900, help="simulations per search")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of the closed law (e.g. horizon_ticks=0)")
    a = ap.parse_args()
    try:
        sets = parse_sets(a.set)
    except ValueError as exc:
        ap.error(str(exc))
    x0 = np.array(BEST.get(a.scenario, (0.0, 0.0, 0.05, 0.15, 0.25, 0.35, 0.3, 0.2, 0.1, 0.11, 0.12, 0.12, 0.12,
                                         0.13, 0.13)))
    from mrctl.util.schema import ConfigError

    try:
        plain = nrmse(a.scenario, None, sets)
    except ConfigError as exc:  # a --set key or value the closed law does not take
        raise SystemExit(str(exc)) from None
    print(f"{a.scenario}: closed {plain:.3f} %, with the profile {nrmse(a.scenario, x0, sets):.3f} %")
    if a.search:
        from scipy.optimize import minimize

        t0 = time.perf_counter()
        r = minimize(lambda x: nrmse(a.scenario, x, sets), x0, method="Nelder-Mead",
                     options={"maxfev": a.evals, "xatol": 0.002, "fatol": 2e-5, "adaptive": True})
        print(f"searched: {r.fun:.3f} % ({time.perf_counter() - t0:.0f} s)")
        print("knots", KNOTS)
        print("profile (A)", tuple(round(float(v), 3) for v in np.clip(r.x, 0.0, 0.6)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
