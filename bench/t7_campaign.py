#!/usr/bin/env python3
"""The LabJack T7 HIL campaign: mrctl run over the emulated T7 against mrctl simulate.

Issue 34's figures. Day one once (``mrctl calibrate`` on the emulated bench at
rest), ``mrctl simulate`` of the calibrated experiment once, then ``--runs``
rounds, each a run with the device's time stamps (``backend.time_stamps:
device``, CORE_TIMER) and one with the host's (``host``), each against a fresh
``python -m hil_sim --device labjack_t7 --transport modbus-tcp`` (the
datasheet latency model of config/hil_labjack_t7_bench.yaml) with ``--truth``.
Per run: exit code, the rate it ran at, skipped deadlines, MBFB requests per
tick (the emulator's count), force NRMSE (load cell against F_des over t >= 1 s,
as ``mrctl simulate`` scores itself) and its ratio to simulate's, and the
observer's velocity error against the emulator's true velocity (rms over
t >= 1 s; each logged sample joined to the bench tick it was read from by its
CORE_TIMER, which the run logs as ``seq`` with either kind of time stamp).
Then the medians, the targets and the load average before and after.
``--firmware N``: beside it, N runs of config/experiments/firmware_host.yaml at
``--firmware-rate`` (1 kHz) against the reference firmware's host build
(firmware/README.md, built here with g++), with ``mrctl simulate`` of that file
at that rate (its plant is the Table I damper, the host build's is a stand-in).

    python bench/t7_campaign.py [--runs 8] [--seconds 4] [--firmware 8] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil_sim.testing.harness import HilSim, env  # noqa: E402
from mrctl.runlog.metrics import tracking_summary  # noqa: E402
from mrctl.runlog.read import read_run, read_sidecar  # noqa: E402

BENCH = ROOT / "config" / "hil_labjack_t7_bench.yaml"
EXPERIMENT = ROOT / "config" / "experiments" / "labjack_t7.yaml"
CORE_TIMER_HZ = 40e6  # the T7's CORE_TIMER: half its 80 MHz core clock
SETTLE_S = 1.0


def mrctl(*args: str, timeout: float = 120.0):
    import subprocess

    return subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=ROOT, env=env(), capture_output=True,
                          text=True, timeout=timeout)


def write_yaml(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


#: --set KEY=VALUE: dotted keys changed in the experiment (every run and simulate)
OVERRIDES: list[tuple[list[str], object]] = []


def experiment(tmp: Path, port: int, name: str, **changes) -> Path:
    data = yaml.safe_load(EXPERIMENT.read_text())
    for keys, value in OVERRIDES:
        node = data
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    data["backend"]["port"] = port
    backend = changes.pop("backend", {})
    data["backend"].update(backend)
    data.update(changes)
    return write_yaml(tmp / name, data)


def start_bench(tmp: Path, bench: Path, *extra: str) -> tuple[HilSim, int]:
    hil = HilSim("--config", str(bench), "--device", "labjack_t7", "--transport", "modbus-tcp",
                 "--bind", "127.0.0.1:0", *extra, workdir=tmp)
    return hil, int(hil.field("bind").rpartition(":")[2])


def load_cell_nrmse(path: Path) -> float:
    c = read_run(path)
    return tracking_summary(c["t"], c["F_des"], c["F"], c["I"], 0.6, SETTLE_S)["force_nrmse"]


def velocity_error(run: dict, truth: dict, bench_dt: float) -> dict:
    """The observer's velocity (``v``) against the bench's true velocity at the
    tick each sample was read from. The emulator stamps a sample with the
    CORE_TIMER of the bench tick it publishes, so CORE_TIMER / dt is that tick
    up to a constant; the constant is the shift that makes the logged x match
    the bench's measured x best (the T7's 1 LSB of noise is ~1 um, a tick off
    is ~60 um at this stroke)."""
    ok = np.isfinite(run["seq"]) & np.isfinite(run["v"])
    raw = run["seq"][ok].astype(np.int64)
    d = np.diff(raw)
    d[d < -(1 << 31)] += 1 << 32  # CORE_TIMER wraps every 107 s
    t_dev = (raw[0] + np.concatenate(([0], np.cumsum(d)))) / CORE_TIMER_HZ
    x, v, t = run["x"][ok], run["v"][ok], run["t"][ok]
    k_truth = truth["k"].astype(np.int64)
    n = int(k_truth.max()) + 1
    cols = {}
    for c in ("x", "v", "x_meas"):
        a = np.full(n, math.nan)
        a[k_truth] = truth[c]
        cols[c] = a
    base = np.floor(t_dev / bench_dt).astype(np.int64)
    best: tuple[float, int] | None = None
    for s in range(-int(base.min()), n - int(base.max())):
        e = x - cols["x_meas"][base + s]
        if np.isfinite(e).mean() < 0.9:
            continue
        r = float(np.nanstd(e))
        if best is None or r < best[0]:
            best = (r, s)
    if best is None:
        raise AssertionError("the run's samples do not fall in the truth log's ticks")
    k = base + best[1]
    w = (t >= t[0] + SETTLE_S) & np.isfinite(cols["v"][k])
    e = v[w] - cols["v"][k][w]
    return {"v_rms_mps": float(np.sqrt(np.mean(e * e))), "x_match_m": best[0], "rows": int(w.sum())}


def one_run(tmp: Path, cal: Path, stamps: str, seconds: float, i: int) -> dict:
    truth = tmp / f"truth-{stamps}-{i}.csv"
    hil, port = start_bench(tmp, BENCH, "--truth", str(truth))
    exp = experiment(tmp, port, f"exp-{stamps}.yaml", calibration=str(cal), duration_s=seconds,
                     backend={"time_stamps": stamps})
    out = tmp / f"run-{stamps}-{i}.csv"
    try:
        res = mrctl("run", str(exp), "--out", str(out), "--quiet", "--status-socket", str(tmp / "s.sock"))
    finally:
        hil.stop()
    r: dict = {"stamps": stamps, "exit": res.returncode}
    m = re.search(r"Running at (\d+(?:\.\d+)?) Hz instead", res.stderr)
    r["rate_hz"] = float(m.group(1)) if m else None
    if not out.exists() or res.returncode not in (0, 5):
        r["error"] = res.stderr.strip().splitlines()[-1] if res.stderr.strip() else f"exit {res.returncode}"
        return r
    side = read_sidecar(out)
    r["rate_hz"] = r["rate_hz"] or float(side["rate_hz"])
    timing = side["summary"]["timing"]
    r["ticks"] = timing["ticks"]
    r["skipped"] = timing["skipped_deadlines"]
    r["overruns"] = timing["overruns"]
    r["late_p99_us"] = timing["lateness_p99_us"]
    r["nrmse"] = load_cell_nrmse(out)
    r["verdict_reasons"] = side.get("verdict_reasons", [])
    counts = json.loads(truth.with_suffix(".json").read_text())["modbus"]["function_counts"]
    r["mbfb_per_exchange"] = counts.get("76", 0) / max(side["summary"]["link"]["exchanges"], 1)
    r.update(velocity_error(read_run(out), read_run(truth), 1.0 / yaml.safe_load(BENCH.read_text())["rate_hz"]))
    return r


def firmware_runs(tmp: Path, n: int, rate_hz: float, seconds: float) -> tuple[float, list[dict]]:
    """The reference firmware's host build at ``rate_hz``, ``n`` runs of firmware_host.yaml."""
    import shutil
    import subprocess

    gxx = shutil.which("g++")
    if gxx is None:
        raise SystemExit("--firmware: g++ builds the firmware's host program")
    fw, exe = ROOT / "firmware", tmp / "mrctl_fw_host"
    res = subprocess.run([gxx, "-std=c++17", "-O2", f"-I{fw / 'core'}", f"-I{fw / 'boards/teensy4/mrctl_teensy4'}",
                          *sorted(str(p) for p in (fw / "core").glob("*.cpp")), str(fw / "host" / "mrctl_fw_host.cpp"),
                          "-o", str(exe)], capture_output=True, text=True, timeout=300)
    if res.returncode != 0:
        raise SystemExit(f"--firmware: g++ failed: {res.stderr}")
    base = yaml.safe_load((ROOT / "config" / "experiments" / "firmware_host.yaml").read_text())
    base.update(rate_hz=rate_hz, duration_s=seconds)
    sim_cfg = write_yaml(tmp / "fw-sim.yaml", base)
    res = mrctl("simulate", str(sim_cfg), "--out", str(tmp / "fw-sim.csv"))
    if res.returncode not in (0, 5):
        raise SystemExit(f"--firmware: mrctl simulate failed: {res.stderr}")
    sim = load_cell_nrmse(tmp / "fw-sim.csv")
    runs = []
    for i in range(n):
        link = tmp / f"fw-tty-{i}"
        proc = subprocess.Popen([str(exe), "--link", str(link), "--rate-hz", f"{rate_hz:g}"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        ready = proc.stdout.readline() if proc.stdout is not None else ""
        data = dict(base, backend=dict(base["backend"], url=str(link)))
        cfg = write_yaml(tmp / f"fw-{i}.yaml", data)
        out = tmp / f"fw-run-{i}.csv"
        try:
            if not ready.startswith("mrctl_fw_host ready"):
                raise SystemExit(f"--firmware: the host build did not start: {ready!r}")
            res = mrctl("run", str(cfg), "--out", str(out), "--quiet", "--status-socket", str(tmp / "fw.sock"))
        finally:
            proc.terminate()
            fw_out, _ = proc.communicate(timeout=10)
        r: dict = {"round": i, "exit": res.returncode}
        m = re.search(r"Running at (\d+(?:\.\d+)?) Hz instead", res.stderr)
        if not out.exists() or res.returncode not in (0, 5):
            r["error"] = res.stderr.strip().splitlines()[-1] if res.stderr.strip() else f"exit {res.returncode}"
        else:
            side = read_sidecar(out)
            timing = side["summary"]["timing"]
            r.update(rate_hz=float(m.group(1)) if m else float(side["rate_hz"]), ticks=timing["ticks"],
                     skipped=timing["skipped_deadlines"], nrmse=load_cell_nrmse(out),
                     verdict_reasons=side.get("verdict_reasons", []))
            r["ratio"] = r["nrmse"] / sim
            late = re.search(r"late_ticks=(\d+)", fw_out or "")
            r["device_late_ticks"] = int(late.group(1)) if late else None
        runs.append(r)
        print("firmware " + (f"round {i}: exit {r['exit']}: {r.get('error')}" if "error" in r else
              f"round {i}: exit {r['exit']}, {r['rate_hz']:g} Hz, {r['ticks']} ticks, skipped {r['skipped']}, "
              f"host build late ticks {r['device_late_ticks']}, NRMSE {100 * r['nrmse']:.3f} % "
              f"(ratio {r['ratio']:.2f})" + "".join(f"; {w}" for w in r["verdict_reasons"])), flush=True)
    return sim, runs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--stamps", action="append", choices=("device", "host"),
                    help="which time stamps to run (default both, device first in each round)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change the experiment, e.g. --set sensing.x_noise_m=5e-6 (YAML value)")
    ap.add_argument("--firmware", type=int, default=0, metavar="N",
                    help="also N runs of firmware_host.yaml against the reference firmware's host build")
    ap.add_argument("--firmware-rate", type=float, default=1000.0)
    ap.add_argument("--keep", metavar="DIR", help="keep the logs, truth logs and calibration here")
    ap.add_argument("--json")
    a = ap.parse_args()
    for item in a.set:
        key, _, value = item.partition("=")
        OVERRIDES.append((key.split("."), yaml.safe_load(value)))
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="t7-campaign-") as d:
        tmp = Path(d)
        if a.keep:
            tmp = Path(a.keep)
            tmp.mkdir(parents=True, exist_ok=True)
        rest = yaml.safe_load(BENCH.read_text())
        rest["excitation"]["amplitude_m"] = 0.0
        hil, port = start_bench(tmp, write_yaml(tmp / "bench-rest.yaml", rest))
        try:
            res = mrctl("calibrate", str(experiment(tmp, port, "exp-cal.yaml")), "--out", str(tmp / "cal.yaml"))
        finally:
            hil.stop()
        if res.returncode != 0:
            print(f"mrctl calibrate failed: {res.stderr}")
            return 1
        cal = tmp / "cal.yaml"
        sim_exp = experiment(tmp, 5021, "exp-sim.yaml", calibration=str(cal), duration_s=a.seconds)
        res = mrctl("simulate", str(sim_exp), "--out", str(tmp / "sim.csv"))
        if res.returncode not in (0, 5):
            print(f"mrctl simulate failed: {res.stderr}")
            return 1
        sim = load_cell_nrmse(tmp / "sim.csv")
        print(f"mrctl simulate (calibrated, {a.seconds:g} s): force NRMSE {100 * sim:.3f} %; "
              f"target 1.2x = {120 * sim:.3f} %", flush=True)
        runs: list[dict] = []
        for i in range(a.runs):
            for stamps in a.stamps or ["device", "host"]:
                r = one_run(tmp, cal, stamps, a.seconds, i)
                r["round"] = i
                if "nrmse" in r:
                    r["ratio"] = r["nrmse"] / sim
                runs.append(r)
                print(fmt(r), flush=True)
        fw_sim, fw = firmware_runs(tmp, a.firmware, a.firmware_rate, a.seconds) if a.firmware else (math.nan, [])
    load1 = os.getloadavg()
    print(f"load average before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, "
          f"after {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    summary = {}
    for stamps in a.stamps or ["device", "host"]:
        rs = [r for r in runs if r["stamps"] == stamps]
        good = [r for r in rs if "nrmse" in r]
        s = {"runs": len(rs), "exit0": sum(r["exit"] == 0 for r in rs),
             "within_1.2x": sum(r.get("ratio", math.inf) <= 1.2 for r in rs)}
        for key in ("rate_hz", "skipped", "nrmse", "ratio", "v_rms_mps", "mbfb_per_exchange"):
            if good:
                s[f"median_{key}"] = statistics.median(r[key] for r in good)
        summary[stamps] = s
        if good:
            print(f"{stamps:6s}: exit 0 in {s['exit0']}/{s['runs']}, ratio <= 1.2 in {s['within_1.2x']}/{s['runs']}; "
                  f"median rate {s['median_rate_hz']:g} Hz, skipped {s['median_skipped']:g}, NRMSE "
                  f"{100 * s['median_nrmse']:.3f} % (ratio {s['median_ratio']:.2f}), velocity error "
                  f"{1e3 * s['median_v_rms_mps']:.3f} mm/s rms, MBFB requests per exchange "
                  f"{s['median_mbfb_per_exchange']:.3f}")
    if {"device", "host"} <= set(summary) and "median_v_rms_mps" in summary["host"]:
        pairs = [(d["v_rms_mps"], h["v_rms_mps"]) for d, h in zip(
            [r for r in runs if r["stamps"] == "device"], [r for r in runs if r["stamps"] == "host"])
            if "v_rms_mps" in d and "v_rms_mps" in h]
        ratios = [dv / hv for dv, hv in pairs]
        print(f"velocity error device/host, per round: {', '.join(f'{q:.2f}' for q in ratios)}; median "
              f"{statistics.median(ratios):.2f} (target <= 0.5); <= 0.5 in {sum(q <= 0.5 for q in ratios)}/"
              f"{len(ratios)}")
        summary["v_ratio_per_round"] = ratios
    if fw:
        good = [r for r in fw if "nrmse" in r]
        print(f"firmware host build at {a.firmware_rate:g} Hz: simulate NRMSE {100 * fw_sim:.3f} %; exit 0 in "
              f"{sum(r['exit'] == 0 for r in fw)}/{len(fw)}" + (
                  f"; median rate {statistics.median(r['rate_hz'] for r in good):g} Hz, skipped "
                  f"{statistics.median(r['skipped'] for r in good):g}, NRMSE "
                  f"{100 * statistics.median(r['nrmse'] for r in good):.3f} % (ratio "
                  f"{statistics.median(r['ratio'] for r in good):.2f})" if good else ""))
        summary["firmware"] = {"simulate_nrmse": fw_sim, "rate_hz": a.firmware_rate, "runs": fw}
    if a.json:
        Path(a.json).write_text(json.dumps({"simulate_nrmse": sim, "load_before": load0, "load_after": load1,
                                            "runs": runs, "summary": summary}, indent=2) + "\n")
    return 0


def fmt(r: dict) -> str:
    if "nrmse" not in r:
        return f"round {r['round']} {r['stamps']:6s}: exit {r['exit']}: {r.get('error')}"
    return (f"round {r['round']} {r['stamps']:6s}: exit {r['exit']}, {r['rate_hz']:g} Hz, {r['ticks']} ticks, "
            f"skipped {r['skipped']}, late p99 {r['late_p99_us']:.0f} us, MBFB/exchange "
            f"{r['mbfb_per_exchange']:.3f}, NRMSE {100 * r['nrmse']:.3f} % (ratio {r['ratio']:.2f}), "
            f"v error {1e3 * r['v_rms_mps']:.3f} mm/s rms")


if __name__ == "__main__":
    sys.exit(main())
