#!/usr/bin/env python3
"""What knowing the damper's own lag buys the inverse laws: a bench whose driver lags 3 ms and whose
field lags a further 10 ms behind the driver's current (the set's ``tau_field``).

A current monitor (``mrctl calibrate``) sees the driver's 3 ms; the force sees both. The laws run
fig5's scenario (1 Hz, 10 mm, viscous demand c_des) on Table I told, in their parameter set's lag:
nothing (0), the driver's lag alone (``tau_input`` 3 ms, what calibrate measures), the measured force
lag (``tau_input`` 3 ms + ``tau_field`` 10 ms, compensated as one 13 ms lag), and, for reference, a
bench without the field lag told the driver's 3 ms. Force NRMSE of the run and its largest current
step, per law and c_des.

Usage: python bench/force_lag.py [--laws closed,smooth] [--c 250,500,750] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config import load_yaml, validate_experiment  # noqa: E402
from mrctl.experiment import build  # noqa: E402
from mrctl.offline.simulate import simulate  # noqa: E402

EXP = ROOT / "config" / "experiments"
DRIVER_S, FIELD_S = 0.003, 0.010
#: (name, the plant's parameter overrides, the law's)
CASES = [
    ("no lag told", {"tau_field": FIELD_S}, {}),
    ("driver's lag told (3 ms)", {"tau_field": FIELD_S}, {"tau_input": DRIVER_S}),
    ("force lag told (3 + 10 ms)", {"tau_field": FIELD_S}, {"tau_input": DRIVER_S, "tau_field": FIELD_S}),
    ("bench without the field lag, 3 ms told", {}, {"tau_input": DRIVER_S}),
]


def run(law: str, c_des: float, plant: dict, told: dict) -> dict:
    data = load_yaml(EXP / "fig5.yaml")
    data["demand"]["c_des"] = c_des
    data["inverse"] = {"law": law}
    data["parameters"] = dict(told) or "table1"
    data["plant"] = {"driver_tau_s": DRIVER_S, "parameters": dict(plant) or "table1"}
    s = simulate(build(validate_experiment(data, EXP)), 4.0).summary
    return {"force_nrmse": s["force_nrmse"], "max_current_step_A": s["max_current_step_A"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--laws", default="closed,smooth")
    ap.add_argument("--c", default="250,500,750", help="c_des values (N·s/m)")
    ap.add_argument("--json")
    args = ap.parse_args()
    out = []
    cs = [float(c) for c in args.c.split(",")]
    print(f"{'law':<8} {'case':<40} " + " ".join(f"{'c=' + format(c, 'g'):>9}" for c in cs))
    for law in args.laws.split(","):
        for name, plant, told in CASES:
            row = [run(law, c, plant, told) for c in cs]
            out.append({"law": law, "case": name, "c_des": cs, "runs": row})
            print(f"{law:<8} {name:<40} " + " ".join(f"{100 * r['force_nrmse']:8.2f}%" for r in row))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
