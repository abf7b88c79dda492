#!/usr/bin/env python3
"""Time the full twelve-current identification, and compare the optimisers.

Data: ``config/experiments/identify.yaml`` (Table I plant, 2 Hz / 8 mm sine,
0–0.55 A in 0.05 A steps, seeded load-cell and velocity noise) simulated to a
temporary run CSV and its sidecar, as ``mrctl simulate --out`` writes them
(:func:`mrctl.offline.simulate_log.simulate_logged`: the sidecar says the load
cell reads one tick late). Identified as ``mrctl identify RUN.csv`` does it:
:func:`mrctl.offline.identify.identify_runs`, the whole pipeline (the
description of the run CSV, reading, preparing, steady cycles per level, a Θ
fit per level, the laws, the leave-level-out choice of laws, held-out
scores). Target: < 60 s on the 2-core lab machine.

Parts:
1. ``identify_runs([csv])`` with the default optimiser: per-level fit time
   (``details.levels[].time_s``, median over ``--repeat`` runs) and the
   total (wall, median), split into the level fits and the rest of the
   pipeline; per level the model evaluations, the fitted cycles, the fit
   NRMSE, the load cell's noise floor and the held-out NRMSE;
2. ``--compare``: the same identification with each optimiser in
   ``METHODS`` (same data, same data-derived start grid): time, model
   evaluations (the start grids included), Σ Q over the levels relative to
   the best of the four, the worst held-out NRMSE (per-level Θ, and the
   written set's laws), the written Fc law's worst relative error against
   Table I over 0.05–0.55 A, and the median (over levels) relative errors of
   σ0 and σ1 against Table I; then robustness: each optimiser from
   ``--trials`` random starts per level (every Θ entry ×/÷ up to 3 from the
   level's data-derived start, σ1 = ±3·Fc/max|v|), one optimiser run each, no
   grid, no restarts, counting runs that reach the best Q (within 0.1 %).
   The fit windows are the pipeline's own: records → ``prepare`` →
   ``find_segments`` as ``levels.constant_input`` calls them, each
   level's windows and linear terms (offset, stiffness) as
   ``sine.fit_levels`` builds them, checked against the result (samples,
   and the fit NRMSE recomputed from Q);
3. cost of one model evaluation, vectorised scan vs a plain-float per-sample
   loop (the alternative the design rejected).

"Q" is recomputed on the rebuilt windows (the result keeps the fit NRMSE, not
the RMS residual); the total includes what the pipeline does besides the
fits (reading, preparing, scoring, the leave-level-out choice).

Usage: python bench/identify_speed.py [--repeat 3] [--compare] [--trials 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config import load_experiment  # noqa: E402
from mrctl.experiment import build  # noqa: E402
from mrctl.model.params import TABLE_I  # noqa: E402
from mrctl.offline.identify import METHODS, THETA_NAMES, identify_runs, theta_from_params  # noqa: E402
from mrctl.offline.identify.fit import _LINEAR, _optimise, _Problem  # noqa: E402
from mrctl.offline.identify.model import _model_batch, _Record, _window_record  # noqa: E402
from mrctl.offline.identify.prep import prepare  # noqa: E402
from mrctl.offline.identify.records import read_records  # noqa: E402
from mrctl.offline.identify.runs import load_runs  # noqa: E402
from mrctl.offline.identify.sine import _cluster_levels, _design, find_segments  # noqa: E402
from mrctl.offline.simulate import run_duration  # noqa: E402
from mrctl.offline.simulate_log import simulate_logged  # noqa: E402

CONFIG = ROOT / "config" / "experiments" / "identify.yaml"


def make_run(tmp: Path):
    """Simulate the config to ``tmp/identify.csv`` and its sidecar; the SimResult (part 3 uses its v_meas)."""
    exp = build(load_experiment(CONFIG))
    csv = tmp / "identify.csv"
    res, _verdict, code = simulate_logged(exp, run_duration(exp), str(csv), str(CONFIG))
    if code != 0:
        raise SystemExit(f"simulate {CONFIG}: exit code {code}")
    return csv, res


def _key(level: float) -> float:
    return round(float(level), 9)


def accuracy(res) -> dict[str, float]:
    """Worst relative error of Fc(I) of the written set vs Table I over 0.05–0.55 A,
    and of each per-level Θ entry vs Table I (median over levels)."""
    grid = np.linspace(0.05, 0.55, 51)
    fc = max(abs(res.params.Fc(i) - TABLE_I.Fc(i)) / TABLE_I.Fc(i) for i in grid)
    out = {"Fc_law_max_rel_err": fc}
    for j, k in enumerate(THETA_NAMES):
        errs = []
        for lv in res.details["levels"]:
            tr = theta_from_params(TABLE_I, lv["level"])[j]
            errs.append(abs(lv["theta"][k] - tr) / abs(tr))
        out[f"{k}_median_rel_err"] = float(np.median(errs))
    return out


def held_out(res) -> dict[float, float]:
    """Held-out NRMSE of each level's own Θ (the worst record at that level)."""
    out: dict[float, float] = {}
    for s in res.holdout:
        out[_key(s.level)] = max(out.get(_key(s.level), 0.0), s.nrmse)
    return out


def fit_windows(csv: Path, res) -> dict[float, _Record]:
    """Each level's fit record (warm-up + fit cycles of its segments, the linear terms), from the
    pipeline's own pieces with the settings ``res`` was identified with; checked against ``res``."""
    ds, _ = load_runs([csv])
    use = dict(res.settings["model"])
    warnings: list[str] = []
    spans, _ = prepare(read_records(ds), band_hz=ds.motion_band_hz, resample_hz=ds.resample_hz,
                       need_accel=use["inertia"], warnings=warnings, constant_input=True)
    segs = find_segments(spans, fraction=res.settings["holdout_fraction"], steady_tol=ds.fit.steady_tolerance,
                         min_cycles=ds.fit.min_cycles, warnings=warnings)
    groups = _cluster_levels([s for s in segs if s.cycles_fit > 0])
    recs: dict[float, _Record] = {}
    for level in sorted(groups):  # sine.fit_levels' windows and design matrix
        windows, Xs = [], []
        for s in groups[level]:
            sp = spans[s.span]
            windows.append((sp.v[s.w0:s.f1], sp.F[s.w0:s.f1], np.full(s.f1 - s.w0, sp.dt), s.f0 - s.w0))
            Xs.append(_design(sp, s.f0, s.f1, use))
        recs[_key(level)] = _window_record(windows, None if Xs[0] is None else np.vstack(Xs))
    levels = res.details["levels"]
    if sorted(recs) != sorted(_key(lv["level"]) for lv in levels):
        raise SystemExit(f"rebuilt windows: levels {sorted(recs)} differ from the result's")
    for lv in levels:
        rec = recs[_key(lv["level"])]
        q = level_q(rec, lv["theta"])
        nrmse = math.sqrt(q / rec.F.size) / float(np.ptp(rec.F))
        if rec.F.size != lv["samples"] or abs(nrmse - lv["nrmse_fit"]) > 1e-6 * lv["nrmse_fit"]:
            raise SystemExit(f"rebuilt windows at {lv['level']:g} A: {rec.F.size} samples, NRMSE {nrmse:.6g}; "
                             f"the pipeline fitted {lv['samples']}, NRMSE {lv['nrmse_fit']:.6g}")
    return recs


def _vmax(rec: _Record) -> float:
    return float(np.percentile(np.abs(rec.v[rec.fit]), 99.5))  # as fit._fit_one_current


def level_q(rec: _Record, theta: dict[str, float]) -> float:
    """Q (offset and stiffness projected out, as the fit) at a level's Θ."""
    th = np.array([theta[k] for k in THETA_NAMES])
    prob = _Problem(rec, th, _vmax(rec))
    return prob.cost(prob.p_start())


def part_timing(csv: Path, repeat: int) -> tuple[dict, object]:
    totals, per_level, fits, last = [], [], [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        last = identify_runs([csv])
        totals.append(time.perf_counter() - t0)
        per_level.append([lv["time_s"] for lv in last.details["levels"]])
        fits.append(sum(per_level[-1]))
    levels = last.details["levels"]
    lv_med = [statistics.median(ts[i] for ts in per_level) for i in range(len(levels))]
    total, fit_s = statistics.median(totals), statistics.median(fits)
    hold = held_out(last)
    col = last.settings["dataset"]["columns"]["force"]
    delay = col.get("delay_samples", 0) if isinstance(col, dict) else 0
    print(f"\n1. identify_runs([csv]), optimiser '{last.settings['method']}' (default), {len(levels)} levels, "
          f"laws '{last.details['laws_choice']['laws']}' (auto), load-cell delay {delay} sample(s) from the "
          f"sidecar, hold-out fraction {last.settings['holdout_fraction']:g}")
    print(f"   median of {repeat}: total {total:.2f} s (target < 60 s): level fits {fit_s:.2f} s, the rest "
          f"(read, prepare, laws, leave-level-out, scores) {total - fit_s:.2f} s")
    print(f"   {'I (A)':>6} {'time (s)':>9} {'nfev':>5} {'cycles':>6} {'NRMSE':>7} {'floor':>7} {'held-out':>8}")
    for lv, t in zip(levels, lv_med):
        h = hold.get(_key(lv["level"]), math.nan)
        print(f"   {lv['level']:6.3f} {t:9.3f} {lv['nfev']:5d} {lv['cycles']:6d} {100 * lv['nrmse_fit']:6.2f}% "
              f"{100 * lv['nrmse_noise_floor']:6.2f}% {100 * h:7.2f}%")
    acc = accuracy(last)
    print(f"   Fc ({last.params.laws} laws) vs Table I over 0.05-0.55 A: max error "
          f"{100 * acc['Fc_law_max_rel_err']:.2f} %")
    out = {"method": last.settings["method"], "laws": last.details["laws_choice"]["laws"], "total_s": totals,
           "level_fits_s": fits, "per_level_s": lv_med, "levels": [lv["level"] for lv in levels],
           "nfev": [lv["nfev"] for lv in levels], "nrmse_fit": [lv["nrmse_fit"] for lv in levels],
           "nrmse_noise_floor": [lv["nrmse_noise_floor"] for lv in levels],
           "nrmse_holdout": [hold.get(_key(lv["level"])) for lv in levels], "accuracy": acc}
    return out, last


def part_compare(csv: Path, trials: int, ref) -> dict:
    recs = fit_windows(csv, ref)
    print(f"\n2a. optimisers on the same data and starts (all {len(recs)} levels, identify_runs(method=...))")
    print(f"   {'method':<12} {'time (s)':>9} {'model evals':>12} {'sum Q / best':>13} {'max hold Θ':>10} "
          f"{'hold laws':>9} {'Fc law err':>10} {'σ0 med err':>10} {'σ1 med err':>10}")
    out: dict = {"same_start": {}, "random_starts": {}}
    results = {}
    for m in METHODS:
        t0 = time.perf_counter()
        res = identify_runs([csv], method=m)
        wall = time.perf_counter() - t0
        qs = {_key(lv["level"]): level_q(recs[_key(lv["level"])], lv["theta"]) for lv in res.details["levels"]}
        results[m] = (res, wall, qs)
    qbest = min(sum(qs.values()) for _, _, qs in results.values())
    for m, (res, wall, qs) in results.items():
        q = sum(qs.values())
        acc = accuracy(res)
        nfev = sum(lv["nfev"] for lv in res.details["levels"])
        hmax = max(s.nrmse for s in res.holdout)
        hlaws = max(s.nrmse_laws for s in res.holdout)
        print(f"   {m:<12} {wall:9.2f} {nfev:12d} {q / qbest:13.5f} {100 * hmax:9.2f}% {100 * hlaws:8.2f}% "
              f"{100 * acc['Fc_law_max_rel_err']:9.2f}% {100 * acc['sigma0_median_rel_err']:9.1f}% "
              f"{100 * acc['sigma1_median_rel_err']:9.1f}%")
        out["same_start"][m] = {"time_s": wall, "pipeline_time_s": res.time_s, "nfev": nfev, "Q_over_best": q / qbest,
                                "max_holdout_nrmse": hmax, "max_holdout_nrmse_laws": hlaws,
                                "laws": res.details["laws_choice"]["laws"], **acc}

    # robustness from random starts, per level, on the fit windows the pipeline used
    print(f"\n2b. robustness: {trials} random starts per level (each Θ entry ×/÷ up to 3 from the "
          "data-derived start, σ1 ± 3·Fc/max|v|), one optimiser run each, no grid, no restarts")
    rng = np.random.default_rng(1)
    stats = {m: {"ok": 0, "n": 0, "nfev": [], "time": []} for m in METHODS}
    for lv in ref.details["levels"]:
        k = _key(lv["level"])
        rec = recs[k]
        best = min(qs[k] for _, _, qs in results.values())
        vmax = _vmax(rec)
        start0 = np.array([lv["start"][n] for n in THETA_NAMES])
        for _ in range(trials):
            th = start0 * np.exp(rng.uniform(-math.log(3), math.log(3), 6))
            th[1] = rng.uniform(-3, 3) * start0[3] / vmax
            for m in METHODS:
                prob = _Problem(rec, th, vmax, linear=(m in _LINEAR))
                t0 = time.perf_counter()
                p, _ = _optimise(prob, m)
                wall = time.perf_counter() - t0
                q = prob.cost(p)
                s = stats[m]
                s["n"] += 1
                s["ok"] += int(q <= best * 1.001)
                s["nfev"].append(prob.nfev)
                s["time"].append(wall)
    print(f"   {'method':<12} {'reach best Q':>13} {'median evals':>13} {'median time (s)':>16}")
    for m, s in stats.items():
        print(f"   {m:<12} {s['ok']:>6d}/{s['n']:<6d} {statistics.median(s['nfev']):13.0f} "
              f"{statistics.median(s['time']):16.3f}")
        out["random_starts"][m] = {"reached_best": s["ok"], "trials": s["n"],
                                   "median_nfev": statistics.median(s["nfev"]),
                                   "median_time_s": statistics.median(s["time"])}
    return out


def _loop_force(theta, v, dt):
    """The rejected alternative: the per-sample model in plain floats, local bindings."""
    s0, s1, s2, Fc, Fs, vs = (float(x) for x in theta)
    exp = math.exp
    c = 1.0 / (vs * vs)
    dF = Fs - Fc
    vl = v.tolist()
    v0 = vl[0]
    z = math.copysign((Fc + dF * exp(-v0 * v0 * c)) / s0, v0)
    out = [0.0] * len(vl)
    vp = v0
    for k, vk in enumerate(vl):
        if k:
            vm = 0.5 * (vp + vk)
            a = s0 * abs(vm) / (Fc + dF * exp(-vm * vm * c))
            x = a * dt
            if x < 1e-8:
                z = z * (1.0 - x) + vm * dt * (1.0 - 0.5 * x)
            else:
                e = exp(-x)
                z = z * e + vm * (1.0 - e) / a
        g = Fc + dF * exp(-vk * vk * c)
        out[k] = s0 * z + s1 * (vk - s0 * abs(vk) * z / g) + s2 * vk
        vp = vk
    return out


def part_model_cost(run) -> dict:
    dt = 1e-3
    v = np.asarray(run["v_meas"][:2000], float)  # 4 periods of the 2 Hz stroke: a warm-up one + three
    th = theta_from_params(TABLE_I, 0.25)
    rec = _window_record([(v, np.zeros(v.size), np.full(v.size, dt), 500)])
    n = 200

    def timeit(fn) -> float:
        fn()
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        return (time.perf_counter() - t0) / n

    t_loop = timeit(lambda: _loop_force(th, v, dt))
    t_vec1 = timeit(lambda: _model_batch(th[None, :], rec))
    P7 = np.repeat(th[None, :], 7, axis=0)
    t_vec7 = timeit(lambda: _model_batch(P7, rec))
    F_loop = np.array(_loop_force(th, v, dt))[500:]
    F_vec = _model_batch(th[None, :], rec)[0]
    print(f"\n3. one model evaluation over {v.size} samples: plain-float loop {1e3 * t_loop:.2f} ms, "
          f"vectorised scan {1e3 * t_vec1:.2f} ms, a batch of 7 (value + FD Jacobian) {1e3 * t_vec7:.2f} ms "
          f"({7 * t_loop / t_vec7:.0f}x the loop); max |ΔF| {np.max(np.abs(F_loop - F_vec)):.1e} N")
    return {"loop_ms": 1e3 * t_loop, "vectorised_ms": 1e3 * t_vec1, "vectorised_batch7_ms": 1e3 * t_vec7}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--compare", action="store_true", help="compare the optimisers (adds ~1 min)")
    ap.add_argument("--trials", type=int, default=5, help="random starts per level in the comparison")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="identify_speed-") as tmp:
        t0 = time.perf_counter()
        csv, run = make_run(Path(tmp))
        print(f"data: {CONFIG.relative_to(ROOT)} simulated to a run CSV + sidecar in "
              f"{time.perf_counter() - t0:.2f} s ({run.ticks} samples)")
        import scipy.optimize  # noqa: F401  (import cost is not identification time)
        import scipy.signal  # noqa: F401

        timing, ref = part_timing(csv, args.repeat)
        out = {"timing": timing}
        if args.compare:
            out["compare"] = part_compare(csv, args.trials, ref)
        out["model_cost"] = part_model_cost(run.columns)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
