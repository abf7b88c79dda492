"""Measure a scenario from the logs it left: the daemon's run log and
sidecar, hil_sim's truth log and summary (what is measured: the package doc)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from hil_sim.faults import parse_fault_arg
from hil_sim.testing.fault_suite.scenario import ENABLED_BIT, RATE_HZ, REACTION_TICKS, WATCHDOG_TICKS, WD_BIT as TRIPPED_BIT, Scenario
from mrctl.core.safety_config import Fault

DEVICE_WATCHDOG_BIT = int(Fault.DEVICE_WATCHDOG)

__all__ = ["load_logs", "tick_accounting", "fault_window", "analyse", "analyse_process"]


def load_logs(workdir: Path, name: str = "run.csv") -> tuple[dict, dict, dict, dict]:
    """(run columns, sidecar, truth columns, truth summary); missing → {}."""
    from mrctl.daemon.recorder import read_run, read_sidecar

    from mrctl.errors import MrctlError

    def safe(f, *a):
        try:
            return f(*a)
        except (OSError, ValueError, MrctlError):  # a log the run never wrote (FileProblem: no such file)
            return {}

    run = safe(read_run, workdir / name)
    side = safe(read_sidecar, workdir / name)
    truth = safe(read_run, workdir / "truth.csv")
    tsum = safe(lambda p: json.loads(p.read_text()), workdir / "truth.json")
    return run, side, truth, tsum


def tick_accounting(run: dict, side: dict) -> dict[str, Any]:
    """Rows vs the loop's tick count, and the k column's jumps vs skipped deadlines."""
    out: dict[str, Any] = {"rows": int(len(run.get("k", ())))}
    summ = side.get("summary") or {}
    timing = summ.get("timing") or {}
    out["complete"] = side.get("complete")
    out["loop_ticks"] = timing.get("ticks")
    out["controller_ticks"] = summ.get("ticks")
    out["skipped_deadlines_sidecar"] = timing.get("skipped_deadlines")
    k = run.get("k")
    if k is not None and len(k):
        d = np.diff(k)
        out["k_monotonic"] = bool(np.all(d >= 1))
        out["k_jumps_skipped"] = int(np.sum(d - 1)) if len(d) else 0
        out["max_k_gap"] = int(d.max()) if len(d) else 0
    if out["loop_ticks"] is not None:
        out["ticks_lost"] = int(out["loop_ticks"]) - out["rows"]
    return out


def _first(mask: np.ndarray, start: int = 0) -> int | None:
    idx = np.flatnonzero(mask[start:])
    return int(idx[0]) + start if len(idx) else None


def _fault_made_misses(w: dict[str, Any]) -> bool:
    """The window lost clearly more samples than the rest of the run."""
    return w.get("missing_in_window", 0.0) > 2 * w.get("missing_outside_window", 0.0) + 0.05


def _zero_for_good(I_cmd: np.ndarray, j0: int, j1: int) -> int | None:
    """First index in [j0, j1) from which I_cmd is 0 up to j1 (None if never)."""
    seg = I_cmd[j0:j1]
    if not len(seg) or seg[-1] != 0.0:
        return None
    nz = np.flatnonzero(seg != 0.0)
    return j0 + (int(nz[-1]) + 1 if len(nz) else 0)


def _range_in(a: np.ndarray, mask: np.ndarray) -> list[float] | None:
    v = a[mask & np.isfinite(a)]
    return [round(float(v.min()), 4), round(float(v.max()), 4)] if len(v) else None


def _zero_by(status: int) -> str:
    """Who made a 0 A tick: the daemon's live setpoint (0 A, the output enabled,
    or disabled by its FAULT), or the device watchdog (no live setpoint:
    WATCHDOG_TRIPPED)."""
    return "watchdog" if status & TRIPPED_BIT else "daemon"


def fault_window(run: dict, truth: dict, k0: int, k1: int, rate_hz: float = RATE_HZ) -> dict[str, Any]:
    """Measure one fault window [k0, k1) (device ticks) in the two logs."""
    dt = 1.0 / rate_hz
    out: dict[str, Any] = {"k0": k0, "k1": k1}
    t_dev, I = run["t_dev"], run["I"]
    good = np.isfinite(t_dev)
    before = np.flatnonzero(good & (t_dev < (k0 - 0.5) * dt))
    if not len(before) or before[-1] + 1 >= len(I):
        out["valid"] = False
        out["why"] = "the daemon was not running when the fault started"
        return out
    i0 = int(before[-1]) + 1
    out["valid"] = True
    out["i0"] = i0
    out["daemon_k_at_fault"] = int(run["k"][i0])
    out["I_before_A"] = float(I[i0 - 1])
    fault_col = run["fault"]
    # the supervisor's 0 A (FAULT: the fault column is set), not the law's own
    # zeros (the fig5 law commands 0 A near every velocity zero crossing)
    after = np.flatnonzero(good & (t_dev >= (k1 - 0.5) * dt))
    ia = int(after[0]) if len(after) else len(I)
    z = _first((I == 0.0) & (fault_col != 0), i0)
    if z is not None and z > min(ia, i0 + REACTION_TICKS):
        # a FAULT this long after the first bad sample is not this fault's
        # reaction (that comes after hold_ticks): on the noisy box the link
        # itself drops runs of samples now and then. Reported, not counted.
        out["later_fault_after_ticks"] = z - i0
        z = None
    seq = run["seq"]
    win = slice(i0, ia)
    n_win = max(1, ia - i0)
    out["missing_in_window"] = round(float(np.isnan(seq[win]).sum()) / n_win, 3)
    n_out = max(1, len(seq) - n_win)
    out["missing_outside_window"] = round(float(np.isnan(seq).sum() - np.isnan(seq[win]).sum()) / n_out, 3)
    out["daemon_ticks_to_0A"] = None if z is None else z - i0
    out["daemon_fault_bits_at_0A"] = None if z is None else int(fault_col[z])
    out["daemon_faulted"] = z is not None
    out["daemon_I_range_in_window_A"] = _range_in(I, good & (t_dev >= (k0 - 0.5) * dt) & (t_dev < (k1 - 0.5) * dt))
    # samples after the fault, and recovery
    if len(after):
        r = _first(I > 0.0, ia)
        out["recovered"] = r is not None
        out["daemon_ticks_to_recover"] = None if r is None else r - ia
    else:
        out["recovered"] = False
        out["daemon_ticks_to_recover"] = None
    # the device
    k = truth["k"].astype(np.int64)
    I_cmd = truth["I_cmd"]
    status = truth["status"].astype(np.int64)
    pre = np.flatnonzero(k < k0)
    out["device_I_before_A"] = float(I_cmd[pre[-1]]) if len(pre) else None
    j0 = int(np.searchsorted(k, k0))
    inside = (k >= k0) & (k < k1)
    out["device_I_range_in_window_A"] = _range_in(I_cmd, inside)
    # 0 A at the device caused by the fault: the watchdog (no live setpoint), or
    # the daemon's FAULT setpoint; a 0 A the law commanded by itself is not one
    jz = _first((I_cmd == 0.0) & (((status & ENABLED_BIT) == 0) | (z is not None)), j0)
    if jz is not None and ((z is None and status[jz] & ENABLED_BIT) or k[jz] >= k1 + 2 * WATCHDOG_TICKS):
        jz = None
    if jz is None:
        out["device_ticks_to_0A"] = None
        out["device_0A_by"] = None
    else:
        out["device_ticks_to_0A"] = int(k[jz] - k0)
        out["device_0A_by"] = _zero_by(status[jz])
        out["device_0A_inside_window"] = bool(k[jz] < k1)
    # the truth's own fault column: ticks it marks inside [k0, k1)
    if "fault" in truth:
        inside = (k >= k0) & (k < k1)
        f = truth["fault"].astype(np.int64)
        out["truth_rows_in_window"] = int(inside.sum())
        out["truth_fault_rows"] = int(np.count_nonzero(f[inside]))
        out["truth_fault_bits"] = sorted({int(b) for b in f[inside]})
    return out


def analyse(sc: Scenario, workdir: Path, res: dict[str, Any]) -> dict[str, Any]:
    run, side, truth, tsum = load_logs(workdir)
    out: dict[str, Any] = {"ticks": tick_accounting(run, side) if run else {"rows": 0}}
    if side:
        out["exit_current_A"] = (side.get("summary") or {}).get("exit_current_A")
        out["safety"] = (side.get("summary") or {}).get("safety")
    if not run or not truth:
        out["error"] = "missing log(s): " + ", ".join(n for n, v in (("run", run), ("truth", truth)) if not v)
        return out
    # the device time of the daemon's first tick that saw the device's watchdog tripped (it latches)
    f = np.nan_to_num(run["fault"], nan=0.0).astype(np.int64) if "fault" in run else np.zeros(0, np.int64)
    hit = np.flatnonzero(f & DEVICE_WATCHDOG_BIT)
    out["daemon_saw_trip_t_dev"] = float(run["t_dev"][hit[0]]) if len(hit) else None
    out["truth_final_I_cmd"] = float(truth["I_cmd"][-1])
    out["truth_rows"] = int(len(truth["k"]))
    # the largest rise of the commanded current from one logged tick to the next (the first from 0 A):
    # the slew limit bounds it, after a fault, a resume and a re-arm alike
    I = np.nan_to_num(run["I"], nan=0.0)
    rises = np.diff(np.concatenate(([0.0], I)))
    out["max_rise_A"] = float(rises.max()) if len(rises) else 0.0
    windows = []
    for text in sc.faults:
        spec, _ = parse_fault_arg(text)
        assert spec is not None, text
        k0, k1 = spec.window(RATE_HZ)
        w = fault_window(run, truth, k0, k1)
        w["fault"] = spec.kind
        windows.append(w)
    out["windows"] = windows
    if sc.process:
        out["process"] = analyse_process(sc, workdir, run, truth, tsum, res)
    return out


def analyse_process(sc: Scenario, workdir: Path, run: dict, truth: dict, tsum: dict,
                    res: dict[str, Any]) -> dict[str, Any]:
    k = truth["k"].astype(np.int64)
    I_cmd = truth["I_cmd"]
    status = truth["status"].astype(np.int64)
    seq = run["seq"]
    fin = np.flatnonzero(np.isfinite(seq))
    out: dict[str, Any] = {}
    if not len(fin):
        out["error"] = "no sample in the daemon log"
        return out
    s_last = int(seq[fin[-1]])  # device tick of the last sample the daemon logged
    out["last_logged_seq"] = s_last
    bench = tsum.get("bench") or {}
    j = int(np.searchsorted(k, s_last + 1))
    if sc.process != "SIGKILL":
        # 0 A for good: the first tick after the last logged one from which I_cmd stays 0
        jz = _zero_for_good(I_cmd, j, len(k))
        out["device_ticks_to_0A_after_last_logged_tick"] = None if jz is None else int(k[jz] - s_last)
        out["device_0A_by"] = None if jz is None else _zero_by(status[jz])
    else:
        # the watchdog expiry after the kill says when the last setpoint arrived
        ev = [e for e in bench.get("watchdog_events") or [] if e["k"] > s_last]
        if ev:
            e = ev[0]
            k_ls = int(e["last_setpoint_k"])
            out["watchdog_k"] = int(e["k"])
            out["device_k_of_last_setpoint"] = k_ls
            out["log_ticks_lost_at_kill"] = max(0, k_ls - s_last)
            starts = bench.get("setpoint_starts") or []
            later = [s for s in starts if s["k"] > e["k"]]
            j_ls = int(np.searchsorted(k, k_ls))
            j_end = int(np.searchsorted(k, later[0]["k"])) if later else len(k)
            jz = _zero_for_good(I_cmd, j_ls, j_end)
            out["device_ticks_to_0A_after_kill"] = None if jz is None else int(k[jz]) - k_ls
            out["device_0A_by"] = None if jz is None else _zero_by(status[jz])
            if later:
                first = later[0]
                out["restart_first_setpoint_A"] = first["first_setpoint_A"]
                out["restart_first_setpoint_k"] = first["k"]
                between = (k >= e["k"]) & (k < first["k"])
                out["I_cmd_max_between_kill_and_restart"] = float(I_cmd[between].max()) if between.any() else 0.0
        r2, s2, _, _ = load_logs(workdir, "restart.csv")
        out["restart_rows"] = int(len(r2.get("k", ())))
        out["restart_ticks"] = tick_accounting(r2, s2) if r2 else None
    if sc.process == "reload":
        info = res.get("process_info") or {}
        before = (info.get("status_before") or {}).get("ticks")
        after = info.get("status_after") or {}
        out["reload_rejected"] = bool(after and (after.get("reloads") or {}).get("rejected", 0) >= 1)
        out["reload_error"] = (after.get("reloads") or {}).get("last_error") if after else None
        if before is not None:
            kk = run["k"]
            lo, hi = before - 200, (after.get("ticks") or before) + 200
            m = (kk >= lo) & (kk <= hi)
            d = np.diff(kk[m])
            out["reload_window_ticks"] = [int(lo), int(hi)]
            out["reload_window_rows"] = int(m.sum())
            out["reload_window_max_k_gap"] = int(d.max()) if len(d) else None
            out["reload_window_skipped"] = int(np.sum(d - 1)) if len(d) else None
    return out

