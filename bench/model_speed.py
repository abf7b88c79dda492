#!/usr/bin/env python3
"""Per-tick compute cost of the inverse laws and the plant, and `simulate` speed.

Targets (issue 2): inverse law < 10 µs per tick at p99, `simulate` ≥ 200×
real time, in plain CPython. The machine is shared and noisy, so:

- per-call times are taken over a replayed Fig 5 trajectory (realistic
  branches), each call timed with perf_counter_ns, the timer's own cost
  (median of an empty timed call) subtracted; p50/p99 over all calls;
- every figure is repeated (``--repeat``) and the median repeat reported;
- a fixed pure-Python baseline (a loop of 4001 exp/mul, like one simulated
  tick's float work) is timed in the same run, and results are also given
  as ratios to it, so runs on a busier machine remain comparable.

Usage: python bench/model_speed.py [--repeat 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config import load_experiment  # noqa: E402
from mrctl.experiment import build  # noqa: E402
from mrctl.laws.base import Measurement  # noqa: E402
from mrctl.laws.inverse import PaperInverse, SmoothInverse  # noqa: E402
from mrctl.model.params import TABLE_I  # noqa: E402
from mrctl.model.plant import DamperPlant  # noqa: E402
from mrctl.offline.simulate import simulate  # noqa: E402

DT = 1e-3
N = 4001


def trajectory() -> list[tuple[float, float]]:
    """(v, F_des) of the Fig 5 scenario, c_des = 500 N·s/m."""
    w = 2 * math.pi
    return [(0.01 * w * math.cos(w * k * DT), 500.0 * 0.01 * w * math.cos(w * k * DT)) for k in range(N)]


def timer_overhead_ns() -> float:
    pc = time.perf_counter_ns
    samples = []
    for _ in range(20000):
        t0 = pc()
        samples.append(pc() - t0)
    return statistics.median(samples)


def percentiles(samples_ns: list[int], overhead_ns: float) -> dict[str, float]:
    s = sorted(samples_ns)
    def q(p):
        return max(s[min(len(s) - 1, int(p * len(s)))] - overhead_ns, 0.0) / 1000.0
    return {"p50_us": q(0.50), "p99_us": q(0.99), "max_us": max(s[-1] - overhead_ns, 0) / 1000.0}


def time_law(make, traj, overhead) -> dict[str, float]:
    law = make()
    pc = time.perf_counter_ns
    cur = law.current
    m = Measurement()
    out = []
    for v, Fd in traj:
        m.v = v
        t0 = pc()
        cur(m, Fd)
        out.append(pc() - t0)
    return percentiles(out, overhead)


def time_plant(traj, overhead) -> dict[str, float]:
    plant = DamperPlant(TABLE_I, DT)
    law = SmoothInverse(TABLE_I, 0.6, DT)
    currents = [law.current(Measurement(v=v), Fd) for v, Fd in traj]
    pc = time.perf_counter_ns
    tick = plant.tick
    out = []
    for (v, _), I in zip(traj, currents):
        t0 = pc()
        tick(v, I)
        out.append(pc() - t0)
    return percentiles(out, overhead)


def baseline_us() -> float:
    """A fixed float workload of about one tick's size, run 4001 times (µs per iteration)."""
    exp = math.exp
    t0 = time.perf_counter()
    acc = 0.0
    for k in range(N):
        x = k * 1e-4
        acc += exp(-x) * 1.0001 + exp(-2 * x) * 0.5 + x * x
    return (time.perf_counter() - t0) / N * 1e6


def sim_speed(config: str) -> float:
    exp = build(load_experiment(ROOT / "config" / "experiments" / config))
    return simulate(exp, 4.0).summary["realtime_factor"]


def median_of(results: list[dict[str, float]]) -> dict[str, float]:
    return {k: statistics.median(r[k] for r in results) for k in results[0]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", help="write the figures as JSON")
    args = ap.parse_args()
    traj = trajectory()
    overhead = timer_overhead_ns()
    res: dict[str, object] = {"timer_overhead_ns": overhead, "python": sys.version.split()[0]}
    laws = {"paper": lambda: PaperInverse(TABLE_I, 0.6, DT), "smooth": lambda: SmoothInverse(TABLE_I, 0.6, DT)}
    for name, make in laws.items():
        res[f"law_{name}"] = median_of([time_law(make, traj, overhead) for _ in range(args.repeat)])
    res["plant_tick"] = median_of([time_plant(traj, overhead) for _ in range(args.repeat)])
    res["baseline_us_per_iter"] = statistics.median(baseline_us() for _ in range(args.repeat))
    for cfg in ("fig5_paper.yaml", "fig5.yaml"):
        res[f"simulate_{cfg}"] = statistics.median(sim_speed(cfg) for _ in range(args.repeat))
    base = res["baseline_us_per_iter"]
    print(f"python {res['python']}, timer overhead {overhead:.0f} ns (subtracted), median of {args.repeat} repeats")
    print(f"baseline: {base:.3f} µs per iteration (fixed float workload; ratios below are x baseline)")
    print(f"{'per tick':22s} {'p50 µs':>8s} {'p99 µs':>8s} {'max µs':>8s} {'p50/base':>9s}")
    for key in ("law_paper", "law_smooth", "plant_tick"):
        r = res[key]
        print(f"{key:22s} {r['p50_us']:8.2f} {r['p99_us']:8.2f} {r['max_us']:8.1f} {r['p50_us'] / base:9.2f}")
    for cfg in ("fig5_paper.yaml", "fig5.yaml"):
        f = res[f"simulate_{cfg}"]
        print(f"simulate {cfg:18s} {f:6.0f}x real time  ({1000.0 / f:.2f} µs per tick, {1000.0 / f / base:.1f}x baseline)")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
