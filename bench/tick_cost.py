#!/usr/bin/env python3
"""CPU cost of one controller tick, unpaced: what the law guard adds.

Builds fig5 (or ``--config``) as ``mrctl run`` does, without the recorder,
and calls ``Controller.tick`` back to back on the in-process sim bench;
prints the median over ``--repeats`` of the mean time per tick (µs). Only
the public constructors are used, so the same script runs on an older tree
for a same-window baseline:

    python bench/tick_cost.py                              # this tree
    git archive 990f9e9 | tar -x -C /tmp/base
    PYTHONPATH=/tmp/base python bench/tick_cost.py --root /tmp/base
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", default=str(Path(__file__).resolve().parents[1]), help="the tree to import mrctl from")
    ap.add_argument("--config", help="experiment YAML (default: ROOT/config/experiments/fig5.yaml)")
    ap.add_argument("--ticks", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=15)
    a = ap.parse_args()
    sys.path.insert(0, a.root)
    from mrctl.config import load_experiment
    from mrctl.core.controller import Controller
    from mrctl.core.safety import SafetyConfig, SafetySupervisor
    from mrctl.experiment import build

    exp = build(load_experiment(a.config or Path(a.root) / "config" / "experiments" / "fig5.yaml"))
    link = exp.make_link()
    link.open()
    ctl = Controller(link, exp.law, exp.demand, SafetySupervisor(SafetyConfig.from_config(exp.config.safety, exp.dt)),
                     exp.dt)
    tick, clock = ctl.tick, time.perf_counter_ns
    means = []
    k = 0
    for _ in range(a.repeats):
        t0 = clock()
        for _ in range(a.ticks):
            tick(k, 0)
            k += 1
        means.append((clock() - t0) / a.ticks * 1e-3)
    import mrctl

    print(f"{Path(mrctl.__file__).parents[1]}: {statistics.median(means):.2f} us per tick "
          f"(median of {a.repeats} x {a.ticks} ticks; min {min(means):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
