#!/usr/bin/env python3
"""``mrctl simulate`` as a whole process: wall time, the loop's share, peak RSS, both builds.

What a user waits for is the process, not the loop: start-up, imports, the
loop, the run log's formatting and writing, the fsync. Each round runs, for
every duration and every build (and ``--tree`` another checkout, e.g. the
tree before streaming), ``mrctl simulate config/experiments/fig5_robust.yaml
--duration D --out TMP.csv`` as a fresh process, in turn, so all see the
same window of a shared machine; the figures are medians over rounds:

- whole: the process's wall time (s); loop: the loop time ``mrctl simulate``
  prints; whole / loop; compiled / pure, the ratio of whole times;
- peak RSS (MB), from ``wait4`` of that process (what ``/usr/bin/time -v``
  reports as "Maximum resident set size");
- the CSVs' SHA-256, the same for every build and tree of a duration.

Bytecode: an installed mrctl has its ``.pyc`` files (pip compiles them), so
the children run with the environment's ``PYTHONDONTWRITEBYTECODE`` removed
and one untimed run each first; ``--no-bytecode-cache`` keeps it as it is.

    python bench/simulate_process.py --rounds 5
    python bench/simulate_process.py --rounds 3 --durations 20,200,2000 --tree ../mrctl-before
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = "config/experiments/fig5_robust.yaml"
BUILDS = (("compiled", {}), ("pure", {"MRCTL_PURE_PYTHON": "1"}))
_LOOP = re.compile(r"ticks \(([0-9.]+) s simulated\) in ([0-9.]+) s")


def run_once(tree: Path, duration: float, extra: dict[str, str], out: Path, bytecode: bool) -> dict[str, float]:
    """One ``mrctl simulate`` of the tree at ``tree``, as a fresh process: wall, loop, peak RSS, CSV hash."""
    env = {k: v for k, v in os.environ.items() if k != "MRCTL_PURE_PYTHON"}
    if bytecode:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.update(extra)
    env["PYTHONPATH"] = str(tree)
    for p in (out, out.with_suffix(".json")):
        p.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "mrctl.cli", "simulate", CONFIG, "--duration", f"{duration:g}", "--out", str(out),
           "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    stdout, stderr = proc.stdout.read(), proc.stderr.read()
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: simulate --duration {duration:g} failed ({proc.returncode}): {stderr[-800:]}")
    m = _LOOP.search(stdout)
    if m is None:
        raise SystemExit(f"no loop time in: {stdout[:400]}")
    digest = hashlib.sha256()
    with open(out, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return {"whole": wall, "loop": float(m.group(2)), "rss_mb": usage.ru_maxrss / 1024.0, "sha": digest.hexdigest()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--durations", default="20,200,2000", help="simulated seconds, comma-separated")
    ap.add_argument("--tree", action="append", default=[], help="another checkout to measure in the same rounds")
    ap.add_argument("--builds", default="compiled,pure")
    ap.add_argument("--no-bytecode-cache", action="store_true", help="keep PYTHONDONTWRITEBYTECODE as it is")
    a = ap.parse_args()
    durations = [float(d) for d in a.durations.split(",")]
    trees = [("this", ROOT)] + [(Path(t).name, Path(t).resolve()) for t in a.tree]
    builds = [(name, env) for name, env in BUILDS if name in a.builds.split(",")]
    bytecode = not a.no_bytecode_cache
    results: dict[tuple[str, str, float], list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="mrctl-simproc-") as tmp:
        out = Path(tmp) / "run.csv"
        for tname, tree in trees:  # warm: the bytecode caches, the page cache
            for _, env in builds:
                run_once(tree, 0.5, env, out, bytecode)
        for r in range(a.rounds):
            for d in durations:
                for tname, tree in trees:
                    for bname, env in builds:
                        res = run_once(tree, d, env, out, bytecode)
                        results.setdefault((tname, bname, d), []).append(res)
                        print(f"round {r + 1} {tname:>10} {bname:>8} {d:>6g} s: whole {res['whole']:.3f} s, "
                              f"loop {res['loop']:.3f} s, RSS {res['rss_mb']:.0f} MB", file=sys.stderr, flush=True)
    med = statistics.median
    print(f"\n`mrctl simulate {CONFIG} --duration D --out RUN.csv`, medians of {a.rounds} rounds "
          f"(bytecode cache {'on' if bytecode else 'as the environment has it'}):\n")
    print("| tree | build | D (s) | whole (s) | loop (s) | whole / loop | peak RSS (MB) | compiled faster (whole) |")
    print("|---|---|---|---|---|---|---|---|")
    for tname, _ in trees:
        for d in durations:
            for bname, _ in builds:
                rs = results[(tname, bname, d)]
                ratio = ""
                if bname == "compiled" and (tname, "pure", d) in results:
                    ps = results[(tname, "pure", d)]
                    ratio = f"{med([p['whole'] / c['whole'] for c, p in zip(rs, ps)]):.2f}×"
                per_loop = [x["whole"] / x["loop"] for x in rs if x["loop"] > 0]
                print(f"| {tname} | {bname} | {d:g} | {med([x['whole'] for x in rs]):.3f} | "
                      f"{med([x['loop'] for x in rs]):.3f} | {f'{med(per_loop):.2f}' if per_loop else '-'} | "
                      f"{med([x['rss_mb'] for x in rs]):.0f} | {ratio} |")
    print()
    for d in durations:
        shas = {(t, b): {x["sha"] for x in results[(t, b, d)]} for t, _ in trees for b, _ in builds}
        same = len(set().union(*shas.values())) == 1
        print(f"--duration {d:g}: CSVs {'byte-identical across' if same else 'DIFFER between'} "
              f"{', '.join(f'{t}/{b}' for t, b in shas)}")
    for t, _ in trees:
        for b, _ in builds:
            if (t, b, 200.0) in results and (t, b, 2000.0) in results:
                r200 = med([x["rss_mb"] for x in results[(t, b, 200.0)]])
                r2000 = med([x["rss_mb"] for x in results[(t, b, 2000.0)]])
                print(f"{t}/{b}: peak RSS of 2000 s / 200 s = {r2000 / r200:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
