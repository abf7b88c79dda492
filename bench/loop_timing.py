#!/usr/bin/env python3
"""Benchmark the fixed-rate loop's wait strategies against cyclictest.

Why: the loop's wake-up lateness is only meaningful next to what the machine
itself can do, so for each strategy the loop runs for ``--seconds`` while
``cyclictest`` (C, same period, same scheduling class) runs **in the same
window** and sees the same noise. The report gives, per strategy: lateness
p50/p99/p99.9/max (µs), compute p99, overruns/skipped deadlines, the CPU the
loop process burned (``time.process_time`` delta / wall time, in % of one
core; cyclictest is a child process and not included), context switches,
and cyclictest's p50/p99/max with the ratio loop p99 / cyclictest p99.

    python bench/loop_timing.py --seconds 5 --json out.json
    python bench/loop_timing.py --rt-prio 80 --mlock --timer-slack-ns 1
    python bench/loop_timing.py --tick mypkg.mymod:make_tick   # real controller

``--tick MODULE:FACTORY`` names a callable ``FACTORY(period_s) -> tick`` (or
``(tick, background)``, see ``FixedRateLoop(background=)``) with
``tick(k, now_ns) -> bool``; from Python call :func:`run_bench` with
``tick_factory=``. The default tick is a plain-float LuGre-style model step
plus a PI current law (~a few µs), optionally padded by ``--tick-cost-us``.
``--tick-work-us W`` runs a tick of fixed float work instead, W µs back to
back: what this machine makes of a tick of that cost, the baseline to read
a real tick's compute p99 against.

cyclictest comes from the Debian package rt-tests
(``apt-get install -y rt-tests``); without it the loop columns are still
reported.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mrctl.daemon import rt  # noqa: E402
from mrctl.daemon.loop import WAIT_STRATEGIES, FixedRateLoop  # noqa: E402
from mrctl.daemon.timing import TimingStats  # noqa: E402

TickFactory = Callable[[float], Callable[[int, int], object]]

CYCLICTEST_HIST_MAX_US = 10_000


def lugre_like_tick(period_s: float, extra_cost_us: float = 0.0) -> Callable[[int, int], object]:
    """A controller-shaped tick: synthetic sensor, LuGre z-update, PI current, clamp.

    Stands in for the real controller until it is plugged in via --tick.
    """
    st = {"z": 0.0, "i_a": 0.0, "integ": 0.0}
    sigma0, sigma1, sigma2, fc, fs, vs = 2.0e5, 3.0e3, 800.0, 300.0, 450.0, 0.02
    kp, ki, i_max = 0.004, 2.0, 2.0
    pad_ns = int(extra_cost_us * 1e3)
    clock = time.perf_counter_ns

    def tick(k: int, now_ns: int) -> bool:
        t0 = clock() if pad_ns else 0
        t = k * period_s
        v = 0.3 * math.sin(2 * math.pi * 2.0 * t)  # "sensor" velocity, m/s
        f_ref = 400.0 * math.sin(2 * math.pi * 2.0 * t + 0.3)
        i = st["i_a"]
        g = (fc + 0.5 * fc * i) + (fs - fc) * math.exp(-((v / vs) ** 2))
        a = sigma0 * abs(v) / g
        x = a * period_s
        z = st["z"]
        if x < 1e-8:
            z = z + v * period_s
        else:
            e = math.exp(-x)
            z = z * e + v * (1.0 - e) / a
        zdot = v - a * z
        f = sigma0 * z + sigma1 * zdot + sigma2 * v * (1.0 + i)
        err = f_ref - f
        integ = st["integ"] + err * period_s
        cmd = kp * err + ki * integ * 1e-3
        cmd = 0.0 if cmd < 0.0 else (i_max if cmd > i_max else cmd)
        st["z"], st["i_a"], st["integ"] = z, cmd, integ
        if pad_ns:
            while clock() - t0 < pad_ns:
                pass
        return True

    return tick


def fixed_work_tick(period_s: float, work_us: float) -> Callable[[int, int], object]:
    """A tick of fixed *work*: the same number of plain-float iterations every
    tick, that many as take ``work_us`` back to back (calibrated here, median
    of 200 timings). The baseline for a real tick's p99: unlike
    ``--tick-cost-us``, which pads to a wall-clock time and so hides any
    preemption shorter than the pad, it shows what the machine does to a
    tick of this cost when the loop paces it (caches and the vCPU cooling
    while it sleeps, preemption). Its working set is tiny, a real tick's is
    not: read it as a lower bound."""
    exp = math.exp

    def body(n: int) -> float:
        s, x = 0.0, 1.0001
        for _ in range(n):
            s += x * 1.5 - exp(-x)
        return s

    clock, m, times = time.perf_counter_ns, 1000, []
    for _ in range(200):
        t0 = clock()
        body(m)
        times.append(clock() - t0)
    times.sort()
    n = max(1, round(work_us * 1e3 * m / times[len(times) // 2]))

    def tick(k: int, now_ns: int) -> bool:
        body(n)
        return True

    return tick


def load_tick_factory(spec: str) -> TickFactory:
    """'package.module:callable' -> callable."""
    mod, _, attr = spec.partition(":")
    if not attr:
        raise SystemExit(f"--tick wants MODULE:FACTORY, got {spec!r}")
    return getattr(importlib.import_module(mod), attr)


# ------------------------------------------------------------------ cyclictest


def cyclictest_path() -> str | None:
    return shutil.which("cyclictest")


def start_cyclictest(
    seconds: float, rate_hz: float, prio: int | None, histfile: str
) -> subprocess.Popen[str] | None:
    """Start cyclictest for the same window; None if not installed.

    Not pinned: pinned to the loop's CPU it would compete with a spinning loop.
    """
    exe = cyclictest_path()
    if exe is None:
        return None
    interval_us = max(1, round(1e6 / rate_hz))
    loops = max(1, round(seconds * rate_hz))
    cmd = [exe, "-m", "-q", "-i", str(interval_us), "-l", str(loops),
           "-h", str(CYCLICTEST_HIST_MAX_US), f"--histfile={histfile}"]
    if prio:
        cmd += ["-p", str(prio)]  # SCHED_FIFO, like the loop; default is SCHED_OTHER
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def parse_cyclictest_hist(text: str) -> dict[str, Any]:
    """Parse a cyclictest -h histogram (1 thread) into p50/p99/p99.9/max µs.

    Bucket b counts wake-ups with latency in [b, b+1) µs; overflows (beyond
    the histogram) are placed at the reported max.
    """
    counts: dict[int, int] = {}
    overflows = 0
    max_us: int | None = None
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        if line.startswith("#"):
            key, _, val = line[1:].partition(":")
            key = key.strip().lower()
            fields = val.split()
            if key == "max latencies" and fields:
                max_us = int(fields[0])
            elif key == "histogram overflows" and fields:
                overflows = int(fields[0])
            continue
        parts = line.split()
        if len(parts) >= 2 and parts[0].isdigit():
            c = int(parts[1])
            if c:
                counts[int(parts[0])] = c
    total = sum(counts.values()) + overflows
    if total == 0:
        return {"samples": 0}
    if max_us is None:
        max_us = max(counts) if counts else CYCLICTEST_HIST_MAX_US

    def pct(q: float) -> float:
        need = math.ceil(q / 100.0 * total)
        cum = 0
        for b in sorted(counts):
            cum += counts[b]
            if cum >= need:
                return float(b)
        return float(max_us)

    return {"samples": total, "p50_us": pct(50), "p99_us": pct(99), "p999_us": pct(99.9),
            "max_us": float(max_us), "overflows": overflows}


def finish_cyclictest(
    proc: subprocess.Popen[str] | None, histfile: str, timeout_s: float
) -> dict[str, Any] | None:
    if proc is None:
        return None
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        return {"error": "cyclictest timed out"}
    text = Path(histfile).read_text() if os.path.exists(histfile) else out
    res = parse_cyclictest_hist(text)
    if proc.returncode != 0 or not res.get("samples"):
        res["error"] = f"cyclictest rc={proc.returncode}: {err.strip()[-300:]}"
    return res


# ------------------------------------------------------------------ bench


def run_strategy(
    strategy: str,
    seconds: float,
    rate_hz: float,
    tick_factory: TickFactory,
    spin_margin_s: float,
    rt_settings: rt.RtSettings,
    use_cyclictest: bool,
) -> dict[str, Any]:
    """One strategy, with cyclictest alongside; returns a flat result row."""
    stats = TimingStats(capacity=max(1, int(seconds * rate_hz) + 16))
    loop = FixedRateLoop(rate_hz, wait=strategy, spin_margin_s=spin_margin_s, stats=stats)
    made = tick_factory(loop.period_ns * 1e-9)
    # a factory may return (tick, background): e.g. the recorder's idle-time formatting
    tick, loop.background = made if isinstance(made, tuple) else (made, None)
    with tempfile.TemporaryDirectory() as tmp:
        histfile = os.path.join(tmp, "hist.txt")
        proc = (start_cyclictest(seconds, rate_hz, rt_settings.fifo_priority, histfile)
                if use_cyclictest else None)
        with rt.rt_applied(rt_settings) as rt_results:
            ru0 = resource.getrusage(resource.RUSAGE_SELF)
            cpu0, wall0 = time.process_time(), time.perf_counter()
            n = loop.run(tick, duration_s=seconds)
            cpu1, wall1 = time.process_time(), time.perf_counter()
            ru1 = resource.getrusage(resource.RUSAGE_SELF)
        ct = finish_cyclictest(proc, histfile, timeout_s=seconds + 30)
    d = stats.summary()
    wall = wall1 - wall0
    row: dict[str, Any] = {
        "strategy": strategy,
        "rate_hz": rate_hz,
        "seconds": round(wall, 3),
        "ticks": n,
        **{k: v for k, v in d.items() if k != "ticks"},
        "cpu_s": round(cpu1 - cpu0, 4),
        "cpu_pct_of_core": round(100.0 * (cpu1 - cpu0) / wall, 1) if wall > 0 else None,
        "vol_ctx_switches": ru1.ru_nvcsw - ru0.ru_nvcsw,
        "invol_ctx_switches": ru1.ru_nivcsw - ru0.ru_nivcsw,
        "rt": [str(r) for r in rt_results],
        "cyclictest": ct,
    }
    if ct and ct.get("p99_us") and d.get("lateness_p99_us") is not None:
        row["ratio_p99_loop_over_cyclictest"] = round(d["lateness_p99_us"] / ct["p99_us"], 2)
    else:
        row["ratio_p99_loop_over_cyclictest"] = None
    return row


def run_bench(
    seconds: float = 10.0,
    rate_hz: float = 1000.0,
    strategies: tuple[str, ...] = WAIT_STRATEGIES,
    tick_factory: TickFactory = lugre_like_tick,
    spin_margin_s: float = 3e-4,
    rt_settings: rt.RtSettings | None = None,
    use_cyclictest: bool = True,
) -> list[dict[str, Any]]:
    """Run every strategy in turn; the lead plugs the real tick via ``tick_factory``."""
    if rt_settings is None:
        rt_settings = rt.RtSettings(gc_freeze=True, gc_disable=True)
    if use_cyclictest and cyclictest_path() is None:
        print("cyclictest not found: install it with `apt-get install -y rt-tests`; "
              "continuing without it", file=sys.stderr)
        use_cyclictest = False
    return [run_strategy(s, seconds, rate_hz, tick_factory, spin_margin_s, rt_settings,
                         use_cyclictest) for s in strategies]


def child_env(**extra: str) -> dict[str, str]:
    """This process's environment for a bench child, without ``MRCTL_PURE_PYTHON``
    (the child runs the compiled build unless ``extra`` sets it), plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k != "MRCTL_PURE_PYTHON"}
    env.update(extra)
    return env


def run_loop_timing(tree: Path, tick: str, seconds: float, env: dict[str, str]) -> dict[str, Any]:
    """One paced run (hybrid wait, ``seconds``) of ``tick`` (``MODULE:FACTORY`` of the tree's
    bench/) by the ``bench/loop_timing.py`` of the source tree at ``tree``, in its own process
    with ``env``: its row (what ``--json`` writes)."""
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "rows.json"
        res = subprocess.run([sys.executable, str(tree / "bench" / "loop_timing.py"), "--tick", tick,
                              "--strategies", "hybrid", "--seconds", str(seconds), "--json", str(out)],
                             cwd=tree / "bench", env=env, capture_output=True, text=True, timeout=seconds * 10 + 120)
        if res.returncode != 0:
            raise SystemExit(f"{tree}: loop_timing failed: {res.stderr[-1500:]}")
        row: dict[str, Any] = json.loads(out.read_text())[0]
        return row


def _f(x: Any, nd: int = 1) -> str:
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def format_table(rows: list[dict[str, Any]]) -> str:
    """Fixed-width table of run_bench rows (times in µs)."""
    head = ("strategy", "late p50", "p99", "p99.9", "max", "comp p99", "overruns",
            "skipped", "CPU %", "ct p50", "ct p99", "ct max", "p99 ratio")
    lines = [" ".join(f"{h:>9}" for h in head)]
    for r in rows:
        ct = r.get("cyclictest") or {}
        vals = (r["strategy"], _f(r["lateness_p50_us"]), _f(r["lateness_p99_us"]),
                _f(r["lateness_p999_us"]), _f(r["lateness_max_us"]), _f(r["compute_p99_us"]),
                _f(r["overruns"]), _f(r["skipped_deadlines"]), _f(r["cpu_pct_of_core"]),
                _f(ct.get("p50_us"), 0), _f(ct.get("p99_us"), 0), _f(ct.get("max_us"), 0),
                _f(r["ratio_p99_loop_over_cyclictest"], 2))
        lines.append(" ".join(f"{v:>9}" for v in vals))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="run time per strategy (s)")
    ap.add_argument("--rate", type=float, default=1000.0, help="loop rate (Hz)")
    ap.add_argument("--strategies", default=",".join(WAIT_STRATEGIES))
    ap.add_argument("--spin-margin-us", type=float, default=300.0, help="hybrid margin (µs)")
    ap.add_argument("--tick", help="MODULE:FACTORY, FACTORY(period_s) -> tick(k, now_ns)")
    ap.add_argument("--tick-cost-us", type=float, default=0.0,
                    help="busy-pad the default tick to at least this compute time (µs)")
    ap.add_argument("--tick-work-us", type=float,
                    help="instead, a tick of fixed float work that takes this long back to back (µs): "
                         "the baseline for a real tick's p99")
    ap.add_argument("--rt-prio", type=int, help="SCHED_FIFO priority for loop and cyclictest")
    ap.add_argument("--mlock", action="store_true", help="mlockall the loop process")
    ap.add_argument("--cpus", help="pin the loop thread to these CPUs, e.g. 1 or 0,1")
    ap.add_argument("--timer-slack-ns", type=int, help="prctl timer slack for the loop thread")
    ap.add_argument("--no-gc-control", action="store_true", help="leave the GC alone")
    ap.add_argument("--no-cyclictest", action="store_true")
    ap.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    a = ap.parse_args(argv)

    strategies = tuple(s.strip() for s in a.strategies.split(",") if s.strip())
    for s in strategies:
        if s not in WAIT_STRATEGIES:
            ap.error(f"unknown strategy {s!r}; choose from {WAIT_STRATEGIES}")
    if a.tick and a.tick_work_us is not None:
        ap.error("--tick and --tick-work-us are two ticks: give one")
    if a.tick_work_us is not None and not 0.0 < a.tick_work_us < 1e6 / a.rate:
        ap.error(f"--tick-work-us must be > 0 and shorter than the period ({1e6 / a.rate:g} µs)")
    if a.tick:
        factory = load_tick_factory(a.tick)
    elif a.tick_work_us is not None:
        work = a.tick_work_us

        def factory(period_s: float) -> Callable[[int, int], object]:
            return fixed_work_tick(period_s, work)
    else:
        cost = a.tick_cost_us

        def factory(period_s: float) -> Callable[[int, int], object]:
            return lugre_like_tick(period_s, cost)

    settings = rt.RtSettings(
        fifo_priority=a.rt_prio,
        lock_memory=a.mlock,
        cpus=frozenset(int(c) for c in a.cpus.split(",")) if a.cpus else None,
        timer_slack_ns=a.timer_slack_ns,
        gc_freeze=not a.no_gc_control,
        gc_disable=not a.no_gc_control,
    )
    rows = run_bench(a.seconds, a.rate, strategies, factory, a.spin_margin_us * 1e-6,
                     settings, not a.no_cyclictest)
    print(f"rate {a.rate:g} Hz, {a.seconds:g} s per strategy, "
          f"{os.cpu_count()} CPUs; all times in µs; CPU % is of one core")
    for line in rows[0]["rt"]:
        print(" ", line)
    print(format_table(rows))
    for r in rows:
        ct = r.get("cyclictest") or {}
        if ct.get("error"):
            print(f"  {r['strategy']}: {ct['error']}", file=sys.stderr)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=2))
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
