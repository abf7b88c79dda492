#!/usr/bin/env python3
"""The 1 kHz loop while something beside it misbehaves: hostile SIGHUP
reloads, and eight status scrapers in a tight loop, each against a quiet
run of the same length.

Why: nothing beside the loop may stall it (issue 23, D2 and D5). Each run
is ``mrctl run`` on the simulated bench (``config/experiments/fig5.yaml``,
a separate process, as in production) for ``--seconds``; its sidecar gives
the loop's longest gap between tick starts, skipped deadlines and compute
p99 over the whole run. The daemon's own CPU time (``/proc/PID/stat``,
sampled every 50 ms until it exits; its reload children's apart) is the
figure a busy machine does not blur. Reload latency is the time from the SIGHUP to the daemon's
"reload ..." line on stderr.

    python bench/loop_under_attack.py --seconds 25 --rounds 2
    python bench/loop_under_attack.py --only reload --json out.json

Modes: ``quiet`` (nothing happens), ``reload`` (every 1.5 s one SIGHUP
with, in turn: an 860-byte alias bomb, a 2.6 MB config, a 60 KB config
of 15 000 wrong values, a plugin whose import hangs, one that raises
SystemExit, one that allocates 4 GiB, then a good config, which must be
applied), ``flood`` (8 threads of a separate process query the status
socket back to back for the whole run).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
FIG5 = (ROOT / "config" / "experiments" / "fig5.yaml").read_text()


def alias_bomb() -> str:
    """The 860-byte billion laughs of the hostile probe (9 levels of 9)."""
    text = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    prev = "a"
    for name in "bcdefghi":
        text += f"{name}: &{name} [{','.join(['*' + prev] * 9)}]\n"
        prev = name
    return text


PLUGINS = {
    "hangs_at_import.py": "import time\ntime.sleep(3600)\n",
    "exits_at_import.py": "raise SystemExit(0)\n",
    "eats_memory.py": "x = bytearray(4 << 30)\n",
}


def plugin_config(module: str) -> str:
    return FIG5.replace("law: smooth", f"law: '{module}:Law'")


#: (name, config text) written before each hostile SIGHUP, in order
HOSTILE_RELOADS: list[tuple[str, Callable[[], str]]] = [
    ("alias bomb (860 B)", lambda: FIG5 + alias_bomb()),
    ("2.6 MB config", lambda: FIG5 + "# " + "x" * (2_600_000) + "\n"),
    ("60 KB of wrong values", lambda: FIG5.replace("rate_hz: 1000", "rate_hz: [" + ",".join(["1e9"] * 15_000) + "]")),
    ("plugin import hangs", lambda: plugin_config("hangs_at_import")),
    ("plugin SystemExit at import", lambda: plugin_config("exits_at_import")),
    ("plugin allocates 4 GiB", lambda: plugin_config("eats_memory")),
    ("good config (c_des 700)", lambda: FIG5.replace("c_des: 500.0", "c_des: 700.0")),
]


@dataclass
class Daemon:
    """A running ``mrctl run`` and its stderr lines with their arrival times."""

    proc: subprocess.Popen
    cfg: Path
    sock: Path
    out: Path
    lines: list[tuple[float, str]] = field(default_factory=list)

    def wait_line(self, needle: str, after: float, timeout_s: float) -> float | None:
        """Arrival time of the first stderr line after ``after`` containing any of ``needle`` (``|``-separated)."""
        t_end = time.monotonic() + timeout_s
        keys = needle.split("|")
        while time.monotonic() < t_end:
            for t, line in list(self.lines):
                if t >= after and any(k in line for k in keys):
                    return t
            if self.proc.poll() is not None:
                return None
            time.sleep(0.005)
        return None


def run_daemon(workdir: Path, seconds: float, during: Callable[[Daemon], Any] | None = None,
               env: dict[str, str] | None = None, config: str = FIG5,
               extra_args: tuple[str, ...] = ()) -> dict[str, Any]:
    """One ``mrctl run`` of ``seconds`` on the sim bench; ``during(daemon)``
    runs once its status socket answers. Returns the exit code, the loop's
    timing from the sidecar, stderr, and what ``during`` returned."""
    workdir.mkdir(parents=True, exist_ok=True)
    for name, text in PLUGINS.items():
        (workdir / name).write_text(text)
    cfg, out, sock = workdir / "exp.yaml", workdir / "run.csv", workdir / "st.sock"
    for p in (out, out.with_suffix(".json")):
        p.unlink(missing_ok=True)
    cfg.write_text(config)
    e = dict(os.environ, PYTHONPATH=os.pathsep.join([str(workdir), str(ROOT)]), **(env or {}))
    proc = subprocess.Popen([sys.executable, "-m", "mrctl", "run", str(cfg), "--out", str(out), "--duration",
                             str(seconds), "--quiet", "--status-socket", str(sock), *extra_args],
                            cwd=workdir, env=e, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    d = Daemon(proc, cfg, sock, out)

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            d.lines.append((time.monotonic(), line.rstrip("\n")))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    cpu = {"own_s": None, "children_s": None}
    hz = os.sysconf("SC_CLK_TCK")

    def sample() -> None:  # the daemon's own CPU time and its reload children's, apart (/proc/PID/stat)
        while proc.poll() is None:
            try:
                f = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
                cpu["own_s"] = (int(f[11]) + int(f[12])) / hz
                cpu["children_s"] = (int(f[13]) + int(f[14])) / hz
            except (OSError, ValueError, IndexError):
                pass
            time.sleep(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t_end = time.monotonic() + 30
    while not sock.exists() and proc.poll() is None and time.monotonic() < t_end:
        time.sleep(0.01)
    result = during(d) if during is not None and proc.poll() is None else None
    try:
        proc.wait(timeout=seconds + 60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    reader.join(5)
    sampler.join(5)
    timing: dict[str, Any] = {}
    try:
        side = json.loads(out.with_suffix(".json").read_text())
        timing = side.get("summary", {}).get("timing", {})
    except (OSError, ValueError):
        pass
    return {"exit": proc.returncode, "timing": timing, "cpu_s": cpu["own_s"], "children_cpu_s": cpu["children_s"],
            "stderr": [line for _, line in d.lines],
            "during": result}


def hostile_reloads(d: Daemon, every_s: float = 1.5) -> list[dict[str, Any]]:
    """Each of :data:`HOSTILE_RELOADS` in turn: write, SIGHUP, wait for the answer."""
    out = []
    time.sleep(0.5)
    for name, make in HOSTILE_RELOADS:
        text = make()
        d.cfg.write_text(text)
        t0 = time.monotonic()
        d.proc.send_signal(signal.SIGHUP)
        t = d.wait_line("reload rejected|reload: new demand", t0, 20.0)
        answer = next((line for tt, line in d.lines if t is not None and tt == t), "none")
        answer = answer.split(f"{d.cfg}: ", 1)[-1] if "rejected" in answer else answer.split("mrctl: ", 1)[-1]
        out.append({"reload": name, "latency_s": None if t is None else round(t - t0, 3), "answer": answer[:160]})
        rest = every_s - (time.monotonic() - t0)
        if rest > 0:
            time.sleep(rest)
    return out


def flood(d: Daemon, scrapers: int = 8, seconds: float = 1e9) -> dict[str, Any]:
    """``scrapers`` threads of a separate process query the status socket back
    to back until the daemon ends; returns the queries answered."""
    code = f"""
import sys, threading, time
sys.path.insert(0, {str(ROOT)!r})
from mrctl.daemon.status import query_status
n = [0]; stop = time.monotonic() + {seconds}
def go():
    while time.monotonic() < stop:
        try:
            query_status({str(d.sock)!r}, 2.0); n[0] += 1
        except Exception:
            if not __import__('os').path.exists({str(d.sock)!r}):
                return
ts = [threading.Thread(target=go, daemon=True) for _ in range({scrapers})]
[t.start() for t in ts]; [t.join() for t in ts]
print(n[0])
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    try:
        return {"queries": int(p.stdout.strip() or 0)}
    except ValueError:
        return {"queries": None, "error": p.stderr[-300:]}


def _r(v: Any) -> str:
    return "-" if v is None else f"{v:.0f}"


def figures(r: dict[str, Any]) -> dict[str, Any]:
    t = r["timing"]
    return {"exit": r["exit"], "cpu_s": r.get("cpu_s"), "children_cpu_s": r.get("children_cpu_s"),
            "longest_gap_us": t.get("longest_gap_us"),
            "skipped_deadlines": t.get("skipped_deadlines"), "compute_p99_us": t.get("compute_p99_us"),
            "lateness_p99_us": t.get("lateness_p99_us")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=25.0, help="length of each run (s); the reloads need ~20")
    ap.add_argument("--rounds", type=int, default=1, help="quiet/attack pairs")
    ap.add_argument("--only", choices=("reload", "flood"), help="one attack only")
    ap.add_argument("--json", help="write the raw results here")
    a = ap.parse_args(argv)
    results: dict[str, list[dict[str, Any]]] = {"quiet": [], "reload": [], "flood": []}
    latencies: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory(prefix="mrctl-attack-") as tmp:
        for rnd in range(a.rounds):
            results["quiet"].append(figures(run_daemon(Path(tmp) / f"q{rnd}", a.seconds)))
            if a.only in (None, "reload"):
                r = run_daemon(Path(tmp) / f"r{rnd}", a.seconds, hostile_reloads)
                results["reload"].append({**figures(r), "reloads": r["during"]})
                for x in r["during"] or []:
                    latencies.setdefault(x["reload"], []).append(x["latency_s"])
            if a.only in (None, "flood"):
                r = run_daemon(Path(tmp) / f"f{rnd}", a.seconds, flood)
                results["flood"].append({**figures(r), **(r["during"] or {})})
    print(f"# mrctl run, sim bench, fig5, {a.seconds:g} s per run, {a.rounds} round(s); "
          f"python bench/loop_under_attack.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print("| run | exit | daemon CPU (s) | its children's CPU (s) | longest gap (ms) | skipped deadlines | "
          "compute p99 (us) | lateness p99 (us) | extra |")
    print("|---|---|---|---|---|---|---|---|---|")
    for mode, rows in results.items():
        for i, row in enumerate(rows):
            gap = row["longest_gap_us"]
            extra = f"{row.get('queries')} status queries answered" if mode == "flood" else ""
            cpu, kids = row["cpu_s"], row["children_cpu_s"]
            print(f"| {mode} {i + 1} | {row['exit']} | {cpu if cpu is not None else float('nan'):.2f} | "
                  f"{kids if kids is not None else float('nan'):.2f} | "
                  f"{gap / 1e3 if gap is not None else float('nan'):.2f} | {row['skipped_deadlines']} | "
                  f"{_r(row['compute_p99_us'])} | {_r(row['lateness_p99_us'])} | {extra} |")
    if latencies:
        print("\n| hostile reload | latency (s), each round | answer (round 1) |")
        print("|---|---|---|")
        first = {x["reload"]: x["answer"] for x in results["reload"][0]["reloads"] or []}
        for name, ls in latencies.items():
            print(f"| {name} | {', '.join('-' if v is None else f'{v:.2f}' for v in ls)} | "
                  f"{first.get(name, '')[:90].replace('|', '/')} |")
    quiet_gap = statistics.median(r["longest_gap_us"] or 0 for r in results["quiet"]) if results["quiet"] else None
    for mode in ("reload", "flood"):
        if results[mode] and quiet_gap:
            worst = max(r["longest_gap_us"] or 0 for r in results[mode])
            print(f"\n{mode}: longest gap {worst / 1e3:.2f} ms = {worst / quiet_gap:.2f}x the quiet runs' median "
                  f"({quiet_gap / 1e3:.2f} ms)")
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
