#!/usr/bin/env python3
"""Time the full twelve-current identification, and compare the optimisers.

Data: ``config/experiments/identify.yaml`` simulated with ``mrctl.offline.simulate``
(Table I plant, 2 Hz / 8 mm sine, 0–0.55 A in 0.05 A steps of 2 s, seeded
load-cell and velocity noise). Target: < 60 s on the 2-core lab machine.

Parts:
1. ``identify`` as the CLI runs it (default optimiser), per-current time and
   total, median of ``--repeat`` runs;
2. ``--compare``: the same identification with each optimiser (trf,
   trf-bounds, lm, nelder-mead), from the same data-derived starts: model evaluations, time,
   final residual, and the accuracy against Table I; then robustness: each
   optimiser from ``--trials`` random starts (every parameter ×/÷ up to 3)
   per current, counting fits that reach the best Q (within 0.1 %);
3. cost of one model evaluation, vectorised scan vs a plain-float per-sample
   loop (the alternative the design rejected).

Usage: python bench/identify_speed.py [--repeat 3] [--compare] [--trials 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config import load_experiment  # noqa: E402
from mrctl.experiment import build  # noqa: E402
from mrctl.offline.identify import METHODS, THETA_NAMES, identify, theta_from_params  # noqa: E402
from mrctl.offline.identify.fit import _LINEAR, _optimise, _Problem  # noqa: E402
from mrctl.offline.identify.model import _model_batch, _window_record  # noqa: E402
from mrctl.model.params import TABLE_I  # noqa: E402
from mrctl.offline.simulate import run_duration, simulate  # noqa: E402

CONFIG = ROOT / "config" / "experiments" / "identify.yaml"


def make_run() -> dict[str, np.ndarray]:
    exp = build(load_experiment(CONFIG))
    return simulate(exp, run_duration(exp)).columns


def accuracy(res) -> dict[str, float]:
    """Worst relative error of Fc(I) of the fitted law vs Table I over 0.05–0.55 A,
    and of each per-current Θ entry vs Table I (median over currents)."""
    grid = np.linspace(0.05, 0.55, 51)
    fc = max(abs(res.params.Fc(i) - TABLE_I.Fc(i)) / TABLE_I.Fc(i) for i in grid)
    out = {"Fc_law_max_rel_err": fc}
    for j, k in enumerate(THETA_NAMES):
        errs = []
        for f in res.fits:
            tr = theta_from_params(TABLE_I, f.current)[j]
            errs.append(abs(f.theta[k] - tr) / abs(tr))
        out[f"{k}_median_rel_err"] = float(np.median(errs))
    return out


def part_timing(run, repeat: int) -> dict:
    totals, last = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        last = identify([run])
        totals.append(time.perf_counter() - t0)
    print(f"\n1. identify(), optimiser '{last.method}' (default), {len(last.fits)} currents, "
          f"median of {repeat}: total {statistics.median(totals):.2f} s (target < 60 s)")
    print(f"   {'I (A)':>6} {'time (s)':>9} {'nfev':>5} {'starts':>6} {'NRMSE':>7} {'floor':>7}")
    for f in last.fits:
        print(f"   {f.current:6.3f} {f.time_s:9.3f} {f.nfev:5d} {f.starts:6d} {100 * f.nrmse:6.2f}% "
              f"{100 * f.noise_nrmse:6.2f}%")
    acc = accuracy(last)
    print(f"   Fc law vs Table I over 0.05-0.55 A: max error {100 * acc['Fc_law_max_rel_err']:.2f} %")
    return {"method": last.method, "total_s": totals, "per_current_s": [f.time_s for f in last.fits],
            "nrmse": [f.nrmse for f in last.fits], "accuracy": acc}


def part_compare(run, trials: int) -> dict:
    print("\n2a. optimisers on the same data and starts (all twelve currents)")
    print(f"   {'method':<12} {'time (s)':>9} {'model evals':>12} {'sum Q / best':>13} {'max NRMSE':>10} "
          f"{'Fc law err':>10} {'σ0 med err':>10} {'σ1 med err':>10}")
    out: dict = {"same_start": {}, "random_starts": {}}
    results = {}
    for m in METHODS:
        t0 = time.perf_counter()
        res = identify([run], method=m)
        results[m] = (res, time.perf_counter() - t0)
    qbest = min(sum(f.rms_N ** 2 * f.samples for f in r.fits) for r, _ in results.values())
    for m, (res, wall) in results.items():
        q = sum(f.rms_N ** 2 * f.samples for f in res.fits)
        acc = accuracy(res)
        nfev = sum(f.nfev for f in res.fits)
        print(f"   {m:<12} {wall:9.2f} {nfev:12d} {q / qbest:13.5f} {100 * max(f.nrmse for f in res.fits):9.2f}% "
              f"{100 * acc['Fc_law_max_rel_err']:9.2f}% {100 * acc['sigma0_median_rel_err']:9.1f}% "
              f"{100 * acc['sigma1_median_rel_err']:9.1f}%")
        out["same_start"][m] = {"time_s": wall, "nfev": nfev, "Q_over_best": q / qbest,
                                "max_nrmse": max(f.nrmse for f in res.fits), **acc}

    # robustness from random starts, per current, on the fit windows identify used
    print(f"\n2b. robustness: {trials} random starts per current (each Θ entry ×/÷ up to 3 from the "
          "data-derived start, σ1 ± 3·Fc/max|v|), one optimiser run each, no grid, no restarts")
    rng = np.random.default_rng(1)
    ref = results["trf"][0]
    # rebuild the windows exactly as identify does: reuse its per-current data
    from mrctl.offline.identify.runs import _check_run, _segments, estimate_period  # noqa: E402
    c = _check_run(run, "run")
    T = estimate_period(c["t"], c["v"])
    dt = float(np.median(np.diff(c["t"])))
    recs = []
    for a, b in _segments(c["I"]):
        if (b - a) * dt < 2 * T:
            continue
        f0 = a + int(round(T / dt))
        w0 = a
        nper = math.floor((b - f0 + 0.5) * dt / T)
        f1 = min(f0 + int(round(nper * T / dt)), b)
        h = np.full(f1 - w0, dt)
        recs.append(_window_record([(c["v"][w0:f1], c["F"][w0:f1], h, f0 - w0)]))
    stats = {m: {"ok": 0, "n": 0, "nfev": [], "time": []} for m in METHODS}
    for fit, rec in zip(ref.fits, recs):
        best = fit.rms_N ** 2 * fit.samples
        th_best = np.array([fit.theta[k] for k in THETA_NAMES])
        vmax = float(np.percentile(np.abs(rec.v), 99.5))
        start0 = np.array([fit.theta0[k] for k in THETA_NAMES])
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
        _ = th_best
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
    v = np.asarray(run["v_meas"][:2000], float)  # warm-up + three periods, as one current's fit
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
    ap.add_argument("--compare", action="store_true", help="compare the optimisers (adds ~2 min)")
    ap.add_argument("--trials", type=int, default=5, help="random starts per current in the comparison")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    t0 = time.perf_counter()
    run = make_run()
    print(f"data: {CONFIG.relative_to(ROOT)} simulated in {time.perf_counter() - t0:.2f} s "
          f"({run['t'].size} samples)")
    import scipy.optimize  # noqa: F401  (import cost is not identification time)

    out = {"timing": part_timing(run, args.repeat)}
    if args.compare:
        out["compare"] = part_compare(run, args.trials)
    out["model_cost"] = part_model_cost(run)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
