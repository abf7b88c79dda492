#!/usr/bin/env python3
"""Semi-active laws on the simulated quarter car: ride comfort and road holding.

Runs ``mrctl simulate``'s closed loop (the same laws, plant and tick order
as ``mrctl run`` on the sim bench) on the lab-scale quarter car of
docs/quarter-car.md, for each law on each road:

- ``resonance``: a sine road at the body-mode frequency, 5 mm;
- ``sweep``: a sine sweep 0.5 → 15 Hz over 30 s, 2 mm;
- ``bump``: one 20 mm (1 − cos) bump, 0.5 m long, at 2 m/s;
- ``iso_C``: an ISO 8608 class C road at 10 m/s, heights scaled by 0.25.

Laws: passive-off (0 A), passive-on (I_max), skyhook (continuous, through
the smooth inverse law), skyhook on-off, groundhook (continuous), groundhook
on-off, clipped-optimal (LQR force + Dyke's switch on the load cell).
Figures: RMS body acceleration (comfort), RMS tyre deflection (road
holding), RMS stroke, each over t ≥ 2 s (the bump: the whole run).

    python bench/quarter_car.py                      # tables on stdout
    python bench/quarter_car.py --write-docs         # + docs/quarter-car.md's table, docs/img/quarter_car.png

Deterministic (no timing involved; the ISO road from seed 1).
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config import validate_experiment  # noqa: E402
from mrctl.experiment import build  # noqa: E402
from mrctl.model.quarter_car import QuarterCarParams  # noqa: E402
from mrctl.offline.simulate import simulate  # noqa: E402
from mrctl.util.gendoc import replace_block  # noqa: E402

QC = QuarterCarParams()
I_MAX = 0.6
SETTLE_S = 2.0

ROADS = {
    "resonance": ({"type": "sine", "amplitude_m": 0.005, "frequency_hz": round(QC.body_hz, 3)}, 12.0),
    "sweep": ({"type": "chirp", "amplitude_m": 0.002, "f0_hz": 0.5, "f1_hz": 15.0, "sweep_s": 30.0}, 30.0),
    "bump": ({"type": "bump", "height_m": 0.02, "length_m": 0.5, "speed_mps": 2.0, "at_s": 0.5}, 4.0),
    "iso_C": ({"type": "iso8608", "road_class": "C", "speed_mps": 10.0, "seed": 1, "scale": 0.25}, 30.0),
}

LAWS = {
    "passive-off": {"inverse": {"law": "constant", "current_A": 0.0}},
    "passive-on": {"inverse": {"law": "constant", "current_A": I_MAX}},
    "skyhook": {"demand": {"type": "skyhook", "c_sky": 2000.0}, "inverse": {"law": "smooth"}},
    "skyhook on-off": {"inverse": {"law": "skyhook_onoff"}},
    "groundhook": {"demand": {"type": "groundhook", "c_gnd": 2000.0}, "inverse": {"law": "smooth"}},
    "groundhook on-off": {"inverse": {"law": "groundhook_onoff"}},
    "clipped-optimal": {"demand": {"type": "lqr", "q_acc": 1.0, "q_tyre": 1e4, "r": 1e-4},
                        "inverse": {"law": "clipped_optimal"}},
}


def config(road: dict, duration_s: float, law: dict) -> dict:
    d = {"version": 1, "name": "quarter_car", "duration_s": duration_s, "rate_hz": 1000, "parameters": "table1",
         "excitation": road, "safety": {"I_max": I_MAX}, "backend": {"type": "sim"},
         "plant": {"bench": "quarter_car"}}
    d.update(copy.deepcopy(law))
    return d


def run_all(roads=ROADS, laws=LAWS) -> dict[tuple[str, str], dict]:
    """(road, law) → figures and the columns (for the figure)."""
    out = {}
    for rname, (road, dur) in roads.items():
        for lname, law in laws.items():
            exp = build(validate_experiment(config(road, dur, law), ROOT))
            res = simulate(exp, dur)
            assert res.fault is None, (rname, lname, res.fault)
            settle = 0.0 if rname == "bump" else SETTLE_S
            from mrctl.runlog.ride import ride_summary

            out[(rname, lname)] = {**ride_summary(res.columns, settle), "cols": res.columns}
    return out


def table(res: dict) -> str:
    lines = ["| road | law | RMS body accel (m/s²) | vs passive-off | vs passive-on | RMS tyre defl (mm) "
             "| vs passive-off | RMS stroke (mm) |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for rname in ROADS:
        off, on = res[(rname, "passive-off")], res[(rname, "passive-on")]
        for lname in LAWS:
            r = res[(rname, lname)]
            a, td = r["rms_a_sprung_mps2"], r["rms_tyre_defl_m"]
            lines.append(f"| {rname} | {lname} | {a:.3f} | {100 * (a / off['rms_a_sprung_mps2'] - 1):+.0f} % "
                         f"| {100 * (a / on['rms_a_sprung_mps2'] - 1):+.0f} % | {1e3 * td:.3f} "
                         f"| {100 * (td / off['rms_tyre_defl_m'] - 1):+.0f} % | {1e3 * r['rms_stroke_m']:.2f} |")
    return "\n".join(lines)


#: each law's look in every panel (Okabe & Ito's colour-blind-safe palette; a line style and a bar hatch
#: tell them apart in grey print too)
LOOK = {
    "passive-off": ("#000000", (0, (4, 2)), ""),
    "passive-on": ("#E69F00", "-", "//"),
    "skyhook": ("#0072B2", "-", ""),
    "skyhook on-off": ("#56B4E9", (0, (6, 1.5, 1.5, 1.5)), ".."),
    "groundhook": ("#009E73", (0, (1, 1)), "\\\\"),
    "groundhook on-off": ("#D55E00", (0, (8, 2)), "xx"),
    "clipped-optimal": ("#CC79A7", (0, (3, 1, 1, 1, 1, 1)), "--"),
}


def figure(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(2, 2, figsize=(12, 9), layout="constrained")
    ax = axes[0, 0]
    for lname, scale in (("passive-off", 0.1), ("passive-on", 1.0), ("skyhook", 1.0), ("clipped-optimal", 1.0)):
        c = res[("resonance", lname)]["cols"]
        m = (c["t"] >= 8.0) & (c["t"] <= 10.0)
        colour, ls, _ = LOOK[lname]
        ax.plot(c["t"][m], scale * c["a_sprung"][m], color=colour, ls=ls, lw=1.2,
                label=lname + (f" × {scale:g}" if scale != 1.0 else ""))
    ax.set(title=f"(a) sine road at the body resonance ({QC.body_hz:.2f} Hz, 5 mm)", xlabel="time (s)",
           ylabel="body acceleration (m/s²)")
    ax.legend(fontsize=8, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.14), frameon=False)
    ax = axes[0, 1]
    c_off = res[("sweep", "passive-off")]["cols"]
    f_t = 0.5 + (15.0 - 0.5) * c_off["t"] / 30.0
    win = 250
    for lname in ("passive-off", "passive-on", "skyhook"):
        c = res[("sweep", lname)]["cols"]
        a2 = np.convolve(c["a_sprung"] ** 2, np.ones(win) / win, mode="same")
        colour, ls, _ = LOOK[lname]
        ax.semilogy(f_t, np.sqrt(a2), color=colour, ls=ls, lw=1.0, label=lname)
    ax.set(title="(b) sine sweep 0.5 → 15 Hz, 2 mm (RMS over 0.25 s)", xlabel="road frequency (Hz)",
           ylabel="running RMS body acceleration (m/s²)")
    ax.legend(fontsize=8, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.14), frameon=False)
    for ax, key, what in ((axes[1, 0], "rms_a_sprung_mps2", "(c) ride comfort: RMS body acceleration"),
                          (axes[1, 1], "rms_tyre_defl_m", "(d) road holding: RMS tyre deflection")):
        names = list(LAWS)
        x = np.arange(len(ROADS))
        w = 0.8 / len(names)
        for i, lname in enumerate(names):
            vals = [res[(r, lname)][key] / res[(r, "passive-off")][key] for r in ROADS]
            colour, _, hatch = LOOK[lname]
            ax.bar(x + (i - len(names) / 2 + 0.5) * w, vals, w, color=colour, hatch=hatch, edgecolor="white",
                   lw=0.3, label=lname)
        ax.set_xticks(x, list(ROADS))
        ax.axhline(1.0, color="k", lw=0.6)
        ax.set(title=f"{what}, relative to passive-off", ylabel="× passive-off", xlabel="road")
    handles, labels = axes[1, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.suptitle(f"MR damper (RD-1097-01 model, I_max {I_MAX} A) in a lab-scale quarter car: m_s {QC.m_s_kg:g} kg, "
                 f"m_u {QC.m_u_kg:g} kg, k_s {QC.k_s_N_per_m:g} N/m, k_t {QC.k_t_N_per_m:g} N/m")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)


def write_docs(text: str) -> None:
    doc = ROOT / "docs" / "quarter-car.md"
    replace_block(doc, "<!-- BEGIN GENERATED: bench/quarter_car.py -->", "<!-- END GENERATED -->", text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write-docs", action="store_true",
                    help="rewrite docs/quarter-car.md's table and docs/img/quarter_car.png")
    args = ap.parse_args()
    res = run_all()
    text = table(res)
    print(text)
    if args.write_docs:
        figure(res, ROOT / "docs" / "img" / "quarter_car.png")
        write_docs(text)
        print("wrote docs/quarter-car.md and docs/img/quarter_car.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
