#!/usr/bin/env python3
"""The daemon's run-log writer: its CPU per row, the recorder's per-tick cost,
and the loop's lateness beside CPU hogs, this tree against another in one window.

``mrctl run`` formats the log in the loop thread's idle time
(``Recorder.format_pending``) and a writer thread writes and fsyncs it
(docs/design.md, "Run log"); the formatting is the CPU the loop's
interpreter spends on the log. Each round measures, for this tree and each
``--tree`` (e.g. the tree before the compiled formatter), in turn:

- ``--cpu``: a Recorder as ``mrctl run`` makes it (``RUN_COLUMNS``,
  ``RUN_FORMATS``, ``defer_format=True``) fed ``--rows`` rows of a
  simulated fig5 run (late_us and compute_us filled as a live run has
  them); the loop thread's CPU time (``time.thread_time``) in
  ``format_pending`` per row, the writer thread's CPU time per row
  (its ``pthread_getcpuclockid`` clock: write and fsync), and
  ``Recorder.record`` per call (timeit, the fast path within a block);
- ``--formatter``: this tree's row formatter alone
  (:class:`mrctl.runlog.rowtext.RowFormatter`), C against its ``%`` twin,
  µs per 15-column row of a simulated fig5_robust log, 32 and 256 rows a call;
- ``--loop``: ``bench/loop_timing.py --tick controller_tick:make_tick
  --strategies hybrid`` of that tree (the real controller tick and its
  recorder at 1 kHz, cyclictest in the same window) while ``--hogs``
  CPU-bound processes run beside it: lateness p50/p99/p99.9, compute p99,
  skipped deadlines, cyclictest p99.

Medians over rounds, and the median of per-round ratios against the first
``--tree``.

    python bench/log_writer.py --cpu --rounds 7 --tree ../mrctl-before
    python bench/log_writer.py --formatter --rounds 7
    python bench/log_writer.py --loop --rounds 5 --seconds 8 --hogs 2 --tree ../mrctl-before
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from loop_timing import child_env, run_loop_timing

ROOT = Path(__file__).resolve().parents[1]

#: run in the measured tree (its own mrctl): prints one JSON line
CPU_PROBE = r"""
import json, statistics, sys, tempfile, time, timeit
from pathlib import Path
import numpy as np
from mrctl.config import load_experiment
from mrctl.experiment import build
from mrctl.daemon.recorder import Recorder
from mrctl.offline.simulate import log_columns, simulate
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS

n = int(sys.argv[1])
cols = log_columns(simulate(build(load_experiment("config/experiments/fig5.yaml")), 4.0))
rng = np.random.default_rng(0)
m = len(cols["t"])
cols = {c: np.asarray(v, float) for c, v in cols.items()}
cols["late_us"] = rng.integers(0, 60000, m) / 1000.0     # a live run's ns-resolution timings
cols["compute_us"] = rng.integers(2000, 90000, m) / 1000.0
base = [tuple(float(cols[c][i]) for c in RUN_COLUMNS) for i in range(m)]
rows = [tuple(v + (k // m) * 4.0 if c in ("t", "t_dev") else v + (k // m) * m if c in ("k", "seq") else v
              for c, v in zip(RUN_COLUMNS, base[k % m])) for k in range(n)]

with tempfile.TemporaryDirectory() as d:
    rec = Recorder(Path(d) / "run.csv", RUN_COLUMNS, {}, capacity_ticks=65536, fmt=RUN_FORMATS,
                   defer_format=True)
    fmt_cpu = 0
    far = time.monotonic_ns() + 10**12
    for r in rows:
        rec.record(*r)
        if rec._pending:
            t0 = time.thread_time_ns()
            rec.format_pending(far)
            fmt_cpu += time.thread_time_ns() - t0
    rec.flush()
    t0 = time.thread_time_ns()
    rec.format_pending(far)
    fmt_cpu += time.thread_time_ns() - t0
    clock = time.pthread_getcpuclockid(rec._w.thread.ident)
    deadline = time.monotonic() + 120
    while rec.stats()["rows_written"] < n and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(1.2)  # the writer's last fsync (flush_interval_s = 1)
    writer_cpu = time.clock_gettime_ns(clock)
    st = rec.close()
    assert st["rows_written"] == n and st["dropped_rows"] == 0, st
    size = (Path(d) / "run.csv").stat().st_size

    row = rows[100]
    per_call = []
    for _ in range(9):  # the hot path within one block: no hand-over
        r2 = Recorder(Path(d) / "t.csv", RUN_COLUMNS, {}, capacity_ticks=65536, block_ticks=40000,
                      flush_interval_s=100.0, rate_hz=1000.0, fmt=RUN_FORMATS, defer_format=True)
        rec2 = r2.record
        per_call.append(timeit.timeit(lambda: rec2(*row), number=30000) / 30000 * 1e6)
        r2.close()
        (Path(d) / "t.csv").unlink(); (Path(d) / "t.json").unlink()
print(json.dumps({"format_us_per_row": fmt_cpu / n / 1e3, "writer_us_per_row": writer_cpu / n / 1e3,
                  "record_us": statistics.median(per_call),
                  "bytes_per_row": size / n}))
"""

def formatter_round() -> dict[str, float]:
    """This tree's formatter, C and its '%' twin, µs per row (the median of 5 passes)."""
    import time
    from array import array

    sys.path.insert(0, str(ROOT))
    from mrctl.config import load_experiment
    from mrctl.experiment import build
    from mrctl.offline.simulate import log_columns, simulate
    from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS
    from mrctl.runlog.rowtext import RowFormatter

    cols = log_columns(simulate(build(load_experiment(ROOT / "config/experiments/fig5_robust.yaml")), 20.0))
    n = len(cols["t"])
    packed = array("d", [float(cols[c][i]) for i in range(n) for c in RUN_COLUMNS])
    out = {}
    for name, compiled in (("C", True), ("py", False)):
        f = RowFormatter(RUN_COLUMNS, RUN_FORMATS, use_compiled=compiled)
        if compiled and not f.compiled:
            raise SystemExit("the compiled formatter is not built here")
        for chunk in (32, 256):
            times = []
            for _ in range(5):
                t0 = time.perf_counter()
                for r in range(0, n - chunk + 1, chunk):
                    f.rows(packed, r, chunk)
                times.append((time.perf_counter() - t0) / (n - n % chunk) * 1e6)
            out[f"{name}_{chunk}"] = statistics.median(times)
    return out


HOG = "import time\nend = time.monotonic() + {s}\nx = 0.0\nwhile time.monotonic() < end:\n    x += 1.0\n"


def cpu_round(tree: Path, rows: int) -> dict[str, float]:
    res = subprocess.run([sys.executable, "-c", CPU_PROBE, str(rows)], cwd=tree,
                         env=child_env(PYTHONPATH=str(tree)), capture_output=True, text=True, timeout=900)
    if res.returncode != 0:
        raise SystemExit(f"{tree}: cpu probe failed: {res.stderr[-1500:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def loop_round(tree: Path, seconds: float, hogs: int) -> dict[str, float]:
    procs = [subprocess.Popen([sys.executable, "-c", HOG.format(s=seconds + 15)]) for _ in range(hogs)]
    try:
        row = run_loop_timing(tree, "controller_tick:make_tick", seconds, child_env(PYTHONPATH=str(tree)))
    finally:
        for p in procs:
            p.kill()
            p.wait()
    ct = row.get("cyclictest") or {}
    return {"late_p50": row["lateness_p50_us"], "late_p99": row["lateness_p99_us"],
            "late_p999": row["lateness_p999_us"], "compute_p99": row["compute_p99_us"],
            "skipped": row.get("skipped_deadlines", 0), "ct_p99": ct.get("p99_us", float("nan")),
            "cpu_pct": row.get("cpu_pct_of_core") or float("nan")}


def _table(title: str, keys: list[tuple[str, str]], results: dict[str, list[dict[str, float]]],
           trees: list[tuple[str, Path]]) -> None:
    med = statistics.median
    ref = trees[1][0] if len(trees) > 1 else None
    print(f"\n{title}\n")
    print("| tree | " + " | ".join(label for _, label in keys) + " |")
    print("|---|" + "---|" * len(keys))
    for name, _ in trees:
        rs = results[name]
        cells = []
        for key, _ in keys:
            vals = [r[key] for r in rs]
            cell = f"{med(vals):.3g} ({', '.join(f'{v:.3g}' for v in vals)})"
            if ref and name != ref and all(r[key] for r in results[ref]):
                ratio = med([a[key] / b[key] for a, b in zip(rs, results[ref]) if b[key]])
                cell += f"; ×{ratio:.2f}"
            cells.append(cell)
        print(f"| {name} | " + " | ".join(cells) + " |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cpu", action="store_true", help="the writer's CPU per row, record() per call")
    ap.add_argument("--loop", action="store_true", help="the loop's lateness beside --hogs CPU hogs")
    ap.add_argument("--formatter", action="store_true", help="this tree's formatter alone, C and '%%'")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--rows", type=int, default=100_000)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--hogs", type=int, default=2)
    ap.add_argument("--tree", action="append", default=[], help="another checkout, measured in the same rounds")
    a = ap.parse_args()
    trees = [("this", ROOT)] + [(Path(t).name, Path(t).resolve()) for t in a.tree]
    if a.cpu:
        results: dict[str, list[dict[str, float]]] = {n: [] for n, _ in trees}
        for r in range(a.rounds):
            for name, tree in trees:
                res = cpu_round(tree, a.rows)
                results[name].append(res)
                print(f"round {r + 1} {name}: {res}", file=sys.stderr, flush=True)
        _table(f"Run-log writer, {a.rows} rows of RUN_COLUMNS a run, {a.rounds} rounds: median (runs); × = "
               f"median of per-round ratios to {trees[1][0] if len(trees) > 1 else '-'}",
               [("format_us_per_row", "format in the loop's idle time, µs CPU/row"),
                ("writer_us_per_row", "writer thread (write, fsync), µs CPU/row"),
                ("record_us", "Recorder.record, µs/call"), ("bytes_per_row", "bytes/row")], results, trees)
    if a.loop:
        results = {n: [] for n, _ in trees}
        for r in range(a.rounds):
            for name, tree in trees:
                res = loop_round(tree, a.seconds, a.hogs)
                results[name].append(res)
                print(f"round {r + 1} {name}: {res}", file=sys.stderr, flush=True)
        _table(f"make_tick at 1 kHz (hybrid), {a.seconds:g} s beside {a.hogs} CPU hogs, {a.rounds} rounds: "
               f"median (runs)", [("late_p50", "lateness p50 µs"), ("late_p99", "lateness p99 µs"),
                                  ("late_p999", "lateness p99.9 µs"), ("compute_p99", "compute p99 µs"),
                                  ("skipped", "skipped deadlines"), ("ct_p99", "cyclictest p99 µs"),
                                  ("cpu_pct", "loop process CPU %")], results, trees)
    if a.formatter:
        results = {"this": [formatter_round() for _ in range(a.rounds)]}
        _table(f"Row formatter alone, µs per 15-column row, {a.rounds} rounds: median (runs)",
               [("C_32", "C, 32 rows a call"), ("C_256", "C, 256 rows a call"), ("py_32", "'%', 32 rows a call"),
                ("py_256", "'%', 256 rows a call")], results, [("this", ROOT)])
    if not (a.cpu or a.loop or a.formatter):
        ap.error("give --cpu, --formatter and/or --loop")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
