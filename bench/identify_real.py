#!/usr/bin/env python3
"""Identify every shipped dataset (``config/datasets/*.yaml``) and print the tables.

The data are real measurements from other labs, read from ``../shared/data``
(never copied into mrctl): a dataset whose files are not on this machine is
skipped with the reason. Per dataset:

- broadband (NEES): held-out force NRMSE per record for the shipped model
  and for the comparisons the docs quote: without the inertia term, without
  the input lag (the command applied at once), and both; fitted τ;
- constant input (Labcontrol): per record and level (with its stroke and
  frequency), with the offset and stiffness and without; per level the median and range over its records,
  with the per-level Θ and with the final laws (6)–(11);
- the time of the shipped fit: median of ``--repeat`` runs, with the
  machine it ran on (identification is single-threaded numpy).

Usage: python bench/identify_real.py [--data-dir /work/shared/data] [--repeat 3] [--only NAME] [--figures DIR]
[--json OUT] [--ablation]
(``--ablation``: each optional model term of the description off, and broadband each alone: the ablation
table of docs/identification.md.)
(``--figures docs/img`` redraws the documentation's figures.)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config.dataset import load_dataset  # noqa: E402
from mrctl.errors import MrctlError  # noqa: E402
from mrctl.offline.identify import identify_dataset  # noqa: E402

DATASETS = ROOT / "config" / "datasets"


def machine() -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    cpu = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()}: {os.cpu_count()} CPU(s) {cpu}, Python {platform.python_version()}, load {load:.2f}"


DATA_DIR: str | None = None  # --data-dir


def run(path: Path, **kw):
    t0 = time.perf_counter()
    try:
        res = identify_dataset(path, allow_outside=True, data_dir=DATA_DIR, **kw)  # the shipped descriptions point at ../shared/data
    except MrctlError as exc:
        return None, str(exc).splitlines()[0], time.perf_counter() - t0
    return res, None, time.perf_counter() - t0


def model_speed(res, n: int = 14900, repeat: int = 5) -> dict:
    """One simulation over n samples: the plant's plain-float tick loop against the
    batched scan for one parameter set and for a Jacobian's batch (value + 17 columns)."""
    from mrctl.model.plant import DamperPlant
    from mrctl.offline.identify.bbmodel import PHYS, SpanData, from_params, simulate

    rng = np.random.default_rng(0)
    dt = 1e-3
    t = np.arange(n) * dt
    v = 0.2 * np.sin(2 * np.pi * 7 * t) + 0.1 * np.sin(2 * np.pi * 23 * t)
    x = np.cumsum(v) * dt
    u = np.repeat(rng.choice([0.0, res.input_range[1]], n // 50 + 1), 50)[:n]
    sp = SpanData(u, v, x, np.zeros(n), dt)
    P = from_params(res.params, *res.input_range)
    batch = np.repeat(P[None, :], len(PHYS) + 1, axis=0)

    def best(fn):
        ts = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return 1e3 * min(ts)

    def loop():
        plant = DamperPlant(res.params, dt)
        tick = plant.tick
        for vk, uk, xk in zip(v.tolist(), u.tolist(), x.tolist()):
            tick(vk, uk, xk)

    out = {"samples": n, "plain_loop_ms": best(loop),
           "batched_one_ms": best(lambda: simulate(P[None, :], sp, *res.input_range)),
           "batched_jacobian_ms": best(lambda: simulate(batch, sp, *res.input_range)), "rows": batch.shape[0]}
    print(f"  one simulation over {n} samples (best of {repeat}): plant tick loop {out['plain_loop_ms']:.0f} ms, "
          f"batched scan {out['batched_one_ms']:.1f} ms, a batch of {out['rows']} (value + Jacobian) "
          f"{out['batched_jacobian_ms']:.0f} ms ({out['rows'] * out['plain_loop_ms'] / out['batched_jacobian_ms']:.0f}x "
          "the loop)")
    return out


#: the optional model terms (docs/identification.md, "Model terms"), as the description's model: flags
TERMS = ("lag_fall", "sigma1_v", "hysteresis")


def _timed(path: Path, **kw):
    """run() with the process's CPU time beside the wall time (identification is single-threaded:
    on a loaded machine the CPU time is the fit's own)."""
    c0 = time.process_time()
    res, err, wall = run(path, **kw)
    return res, err, wall, time.process_time() - c0


def broadband(path: Path, ds, repeat: int, out: dict, ablation: bool = False) -> object:
    shipped = {k: bool(ds.model.get(k)) for k in ("offset", "stiffness", "lag", "inertia") + TERMS}
    variants = [("shipped", {})]
    on = [t for t in TERMS if shipped[t]]
    if ablation:  # each optional term on and off, the others as shipped; then none of them
        variants += [(f"without {t}", {t: False}) for t in on]
        variants += [(f"only {t}", {u: u == t for u in on}) for t in on]
        variants.append(("none of " + ", ".join(on), {t: False for t in on}))
    if shipped["inertia"]:
        variants.append(("no inertia term", {"inertia": False}))
    variants += [("no input lag", {"lag": False, "lag_fall": False, "inertia": False})]
    rows, first = [], None
    times = []
    cpu = []
    for name, model in variants:
        res, err, dt, dc = _timed(path, model=model)
        if name == "shipped":
            first = res
            times.append(dt)
            cpu.append(dc)
            for _ in range(repeat - 1):
                _, _, dt, dc = _timed(path)
                times.append(dt)
                cpu.append(dc)
        if res is None:
            rows.append({"variant": name, "error": err})
            continue
        rows.append({"variant": name, "tau_ms": 1e3 * res.params.tau_input, "inertia_kg": res.inertia_kg,
                     "terms": res.params.extras(), "time_s": dt, "cpu_s": dc,
                     "holdout": {s.record: s.nrmse for s in res.holdout},
                     "fit": {s.record: s.nrmse for s in res.train}})
    print(f"\n{ds.name} (broadband; model as shipped: {', '.join(k for k, v in shipped.items() if v)})")
    recs = list(rows[0].get("holdout", {}))
    print(f"  {'variant':<34} {'tau (ms)':>9} {'m (kg)':>7} " + " ".join(f"{r + ' held out':>20}" for r in recs)
          + f" {'cpu (s)':>8}  terms")
    for r in rows:
        if "error" in r:
            print(f"  {r['variant']:<34} refused: {r['error']}")
            continue
        terms = ", ".join(f"{k} {v:.4g}" for k, v in r["terms"].items())
        print(f"  {r['variant']:<34} {r['tau_ms']:9.2f} {r['inertia_kg']:7.2f} "
              + " ".join(f"{100 * r['holdout'].get(k, float('nan')):19.2f}%" for k in recs)
              + f" {r['cpu_s']:8.1f}  {terms}")
    print(f"  time of the shipped fit: median {statistics.median(times):.1f} s wall, {statistics.median(cpu):.1f} s "
          f"CPU of {len(times)} (wall min {min(times):.1f}, max {max(times):.1f})")
    out[ds.name] = {"protocol": "broadband", "variants": rows, "time_s": times, "cpu_s": cpu}
    if first is not None:
        out[ds.name]["model_speed"] = model_speed(first)
    return first


def constant_input(path: Path, ds, repeat: int, out: dict, ablation: bool = False) -> object:
    res, err, dt, dc = _timed(path)
    runs = [(dt, dc)] + [_timed(path)[2:] for _ in range(repeat - 1)]
    times, cpu = [r[0] for r in runs], [r[1] for r in runs]
    plain, perr, _ = run(path, model={"offset": False, "stiffness": False, "hysteresis": False})  # LuGre alone
    if res is None:
        print(f"\n{ds.name}: refused: {err}")
        out[ds.name] = {"error": err}
        return None
    no_off = {(s.record, s.level): s.nrmse for s in (plain.holdout if plain else [])}
    print(f"\n{ds.name} (constant input; held-out force NRMSE per record, the second half of its steady cycles)")
    print(f"  {'record':<16} {'level':>7} {'stroke':>8} {'freq':>6} {'offset':>8} {'written':>8} {'paper':>8} "
          f"{'table':>8} {'no offset':>10}")
    for s in res.holdout:
        nf = no_off.get((s.record, s.level))
        print(f"  {s.record:<16} {s.level:7.4g} {1e3 * s.stroke_m:5.1f} mm {s.frequency_hz:6.3f} "
              f"{100 * s.nrmse:7.2f}% {100 * s.nrmse_laws:7.2f}% "
              f"{100 * s.nrmse_paper:7.2f}% {100 * (s.nrmse_table or float('nan')):7.2f}% "
              + (f"{100 * nf:9.2f}%" if nf is not None else f"{'refused' if perr else '-':>10}"))
    levels = sorted({s.level for s in res.holdout})
    per_level = []
    print(f"\n  per level ({res.unit}): median [min–max] over its records")
    ch = res.details["laws_choice"]
    print(f"  written laws: {ch['laws']} (fit.laws: {ch['asked']})")
    print(f"  {'level':>7} {'records':>7} {'with offset':>20} {'written set':>20} {'paper laws':>20} "
          f"{'table laws':>20} {'ratio':>6} {'no offset':>20} {'beats':>6}")
    for lv in levels:
        a = [s.nrmse for s in res.holdout if s.level == lv]
        b = [s.nrmse_laws for s in res.holdout if s.level == lv]
        bp = [s.nrmse_paper for s in res.holdout if s.level == lv]
        bt = [s.nrmse_table for s in res.holdout if s.level == lv and s.nrmse_table is not None]
        c = [no_off[(s.record, s.level)] for s in res.holdout if s.level == lv and (s.record, s.level) in no_off]

        def f(x):
            return f"{100 * statistics.median(x):5.2f} [{100 * min(x):.2f}–{100 * max(x):.2f}]" if x else "-"

        beats = bool(c) and max(a) < min(c)
        ratio = statistics.median(b) / statistics.median(a)
        per_level.append({"level": lv, "records": len(a), "median": statistics.median(a), "min": min(a),
                          "max": max(a), "median_laws": statistics.median(b), "written_laws": ch["laws"],
                          "median_paper": statistics.median(bp), "median_table": statistics.median(bt) if bt else None,
                          "written_over_per_level": ratio,
                          "median_no_offset": statistics.median(c) if c else None, "beats_no_offset": beats})
        print(f"  {lv:7.4g} {len(a):7d} {f(a):>20} {f(b):>20} {f(bp):>20} {f(bt):>20} {ratio:6.2f} {f(c):>20} "
              f"{'yes' if beats else 'NO':>6}")
    loo = ch["leave_level_out_nrmse"]
    print("  each interior level predicted from the other levels' fits (leave one level out), mean NRMSE: "
          + "; ".join(f"{lv} V paper {100 * loo['paper'][lv]:.2f} % table {100 * loo['table'].get(lv, float('nan')):.2f} %"
                      for lv in loo["paper"]))
    p = res.params
    print(f"  final set: F_offset {p.F_offset:.4g} N, k_x {p.k_x:.4g} N/m, {p.extras() or 'no optional terms'}; "
          f"time median {statistics.median(times):.1f} s wall, {statistics.median(cpu):.1f} s CPU of {len(times)}")
    out[ds.name] = {"protocol": "constant_input", "holdout": [s.as_dict() for s in res.holdout],
                    "no_offset": {f"{k[0]}@{k[1]}": v for k, v in no_off.items()}, "per_level": per_level,
                    "time_s": times, "cpu_s": cpu, "no_offset_error": perr, "laws_choice": ch}
    if ablation:
        out[ds.name]["ablation"] = _level_ablation(path, ds, res)
    return res


def _level_ablation(path: Path, ds, res) -> list[dict]:
    """Each optional term of the description off, then all of them: per level the median held-out
    NRMSE, per-level fit and written set, the leave-one-level-out scores and the time."""
    on = [t for t in TERMS if ds.model.get(t)]
    variants = [("shipped", res)] + [(f"without {t}", _timed(path, model={t: False})[0]) for t in on]
    if len(on) > 1:
        variants.append(("none of " + ", ".join(on), _timed(path, model={t: False for t in on})[0]))
    rows = []
    print("\n  ablation: held-out NRMSE per level, median over its records (per-level fit / written set); "
          "leave one level out (table, paper)")
    for name, r in variants:
        if r is None:
            print(f"  {name:<28} refused")
            continue
        levels = sorted({s.level for s in r.holdout})
        per = {lv: (statistics.median([s.nrmse for s in r.holdout if s.level == lv]),
                    statistics.median([s.nrmse_laws for s in r.holdout if s.level == lv])) for lv in levels}
        loo = r.details["laws_choice"]["leave_level_out_nrmse"]
        print(f"  {name:<28} " + "  ".join(f"{lv:g}: {100 * a:.2f}/{100 * b:.2f}" for lv, (a, b) in per.items())
              + "  LOO " + "; ".join(f"{k}: table {100 * loo['table'][k]:.2f} paper {100 * v:.2f}"
                                     for k, v in loo["paper"].items()) + f"  ({r.time_s:.1f} s)")
        rows.append({"variant": name, "per_level": {f"{lv:g}": v for lv, v in per.items()}, "leave_level_out": loo,
                     "terms": r.params.extras(), "time_s": r.time_s})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=1, help="runs of each shipped fit for the time (median)")
    ap.add_argument("--only", help="only the dataset with this name")
    ap.add_argument("--figures", help="write each shipped fit's figures here (NAME.png, the summary; "
                                      "NAME-detail.png and NAME-conditions.png, constant input: every level, "
                                      "NRMSE against stroke and frequency)")
    ap.add_argument("--json", help="write every number to this JSON file")
    ap.add_argument("--data-dir", help="where the shared data are (over each description's data_dir:)")
    ap.add_argument("--ablation", action="store_true",
                    help="also fit with each optional model term off (and, broadband, each alone)")
    args = ap.parse_args()
    global DATA_DIR
    DATA_DIR = args.data_dir
    print(machine())
    out: dict = {"machine": machine()}
    for path in sorted(DATASETS.glob("*.yaml")):
        try:
            ds = load_dataset(path, data_dir=args.data_dir, allow_outside=True)
        except MrctlError as exc:
            print(f"\n{path.name}: skipped: {str(exc).splitlines()[0]}")
            continue
        if args.only and ds.name != args.only:
            continue
        fn = broadband if ds.protocol == "broadband" else constant_input
        res = fn(path, ds, max(1, args.repeat), out, args.ablation)
        if args.figures and res is not None:
            from mrctl.offline.identify_figure import make_identification_figure

            fig = Path(args.figures) / f"{ds.name}.png"
            fig.parent.mkdir(parents=True, exist_ok=True)
            pages = [(fig, False)] + ([(fig.with_name(f"{ds.name}-detail.png"), True)]  # broadband: the
                                      if ds.protocol == "constant_input" else [])  # summary has every record
            for path, detail in pages:
                make_identification_figure(res, path, dpi=80, force=True, detail=detail)  # the docs' figures
                try:  # a palette PNG: a third of the size, for the docs
                    from PIL import Image

                    Image.open(path).convert("RGB").quantize(colors=64).save(path, optimize=True)
                except ImportError:
                    pass
                print(f"  wrote {path} ({path.stat().st_size // 1024} kB)")
            if ds.protocol == "constant_input":
                from mrctl.offline.identify_figure import make_conditions_figure

                cfig = fig.with_name(f"{ds.name}-conditions.png")
                make_conditions_figure(res, cfig, dpi=80, force=True)
                print(f"  wrote {cfig} ({cfig.stat().st_size // 1024} kB)")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
