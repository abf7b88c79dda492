#!/usr/bin/env python3
"""The compiled tick against the interpreted one, side by side in one window.

Why alternate: on a shared VM the timing of one minute says little about the
next, so each round runs the compiled build and then the interpreted one
(``MRCTL_PURE_PYTHON=1``) back to back, and the figures are medians over
rounds of each, and the median of the per-round ratios.

Two measurements:

- ``--loop``: the paced loop (``bench/loop_timing.py``, hybrid wait, with
  cyclictest in the same window) running a real controller tick of
  ``bench/controller_tick.py`` (``make_tick_robust``: the closed law and the
  observer on a displacement-only sim bench; ``make_tick``: fig5's smooth
  law): compute p50/p99 of each build and cyclictest's p99 beside them;
- ``--simulate``: ``mrctl simulate config/experiments/fig5_robust.yaml``'s
  wall time in each build, and whether the two CSVs are byte-identical.

    python bench/builds.py --simulate --rounds 9
    python bench/builds.py --loop --rounds 6 --seconds 8
    python bench/builds.py --loop --ticks make_tick --rounds 6
    python bench/builds.py --loop --rounds 6 --tree ../mrctl-before   # + another checkout, e.g. before the core

Instruction counts (callgrind) are ``bench/law_instructions.py --tick
make_tick_robust_replay``, once per build.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from loop_timing import child_env, run_loop_timing

ROOT = Path(__file__).resolve().parents[1]
BUILDS = (("compiled", {}), ("pure Python", {"MRCTL_PURE_PYTHON": "1"}))


def loop_round(tick: str, seconds: float, extra: dict[str, str], root: Path = ROOT) -> dict[str, float]:
    """One paced run of ``tick`` (the bench scripts and mrctl of the tree at
    ``root``): compute p50/p99 (µs), skipped deadlines, cyclictest p99."""
    row = run_loop_timing(root, f"controller_tick:{tick}", seconds, child_env(**extra))
    ct = row.get("cyclictest") or {}
    return {"p50": row["compute_p50_us"], "p99": row["compute_p99_us"], "skipped": row.get("skipped_deadlines", 0),
            "ct_p99": ct.get("p99_us", float("nan"))}


def simulate_round(extra: dict[str, str], out: Path) -> float:
    """One ``mrctl simulate`` of fig5_robust: the loop's wall time (s) from the sidecar."""
    res = subprocess.run([sys.executable, "-m", "mrctl.cli", "simulate",
                          str(ROOT / "config" / "experiments" / "fig5_robust.yaml"), "--out", str(out), "--force"],
                         env=child_env(**extra), capture_output=True, text=True, timeout=600)
    if res.returncode != 0:
        raise SystemExit(f"simulate failed: {res.stderr[-1000:]}")
    return float(json.loads(out.with_suffix(".json").read_text())["summary"]["wall_s"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--loop", action="store_true", help="paced compute p99 of a controller tick")
    ap.add_argument("--simulate", action="store_true", help="mrctl simulate's wall time")
    ap.add_argument("--ticks", default="make_tick_robust,make_tick", help="bench/controller_tick.py factories")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=8.0, help="paced seconds per run")
    ap.add_argument("--tree", type=Path, help="--loop: also run the tick of this source tree (its own bench/ "
                                              "scripts, its mrctl on PYTHONPATH) in each round")
    a = ap.parse_args()
    if not (a.loop or a.simulate):
        ap.error("give --loop and/or --simulate")
    if a.simulate:
        walls: dict[str, list[float]] = {b: [] for b, _ in BUILDS}
        ratios, same = [], True
        with tempfile.TemporaryDirectory() as d:
            for _ in range(a.rounds):
                for name, extra in BUILDS:
                    walls[name].append(simulate_round(extra, Path(d) / f"{name[0]}.csv"))
                ratios.append(walls["pure Python"][-1] / walls["compiled"][-1])
                same = same and (Path(d) / "c.csv").read_bytes() == (Path(d) / "p.csv").read_bytes()
        print(f"mrctl simulate fig5_robust (4001 ticks), {a.rounds} alternating rounds:")
        for name in walls:
            print(f"  {name:12s} loop wall median {statistics.median(walls[name]) * 1e3:7.1f} ms")
        print(f"  speed-up (median of per-round ratios): {statistics.median(ratios):.1f}x; "
              f"CSVs byte-identical: {'yes' if same else 'NO'}")
    if a.loop:
        for tick in a.ticks.split(","):
            runs: list[tuple[str, dict[str, str], Path]] = [(n, e, ROOT) for n, e in BUILDS]
            if a.tree is not None:
                tree = a.tree.resolve()
                runs.append((f"tree {tree.name}", {"PYTHONPATH": str(tree), "MRCTL_PURE_PYTHON": "1"}, tree))
            rows: dict[str, list[dict[str, float]]] = {n: [] for n, _, _ in runs}
            for _ in range(a.rounds):
                for name, extra, root in runs:
                    rows[name].append(loop_round(tick, a.seconds, extra, root))
            print(f"{tick}: {a.rounds} alternating rounds of {a.seconds:g} s, hybrid wait")
            for name, rs in rows.items():
                med = {k: statistics.median(r[k] for r in rs) for k in ("p50", "p99", "skipped", "ct_p99")}
                p99s = ", ".join(f"{r['p99']:.0f}" for r in rs)
                print(f"  {name:12s} compute p50 {med['p50']:6.1f} us  p99 {med['p99']:6.1f} us (runs: {p99s})  "
                      f"skipped {med['skipped']:.0f}  cyclictest p99 {med['ct_p99']:.0f} us")
            for other in list(rows)[1:]:
                ratio = statistics.median(c["p99"] / p["p99"] for c, p in zip(rows["compiled"], rows[other]))
                print(f"  compute p99 compiled / {other} (median of per-round ratios): {ratio:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
