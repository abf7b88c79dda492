"""Helpers for loopback HIL tests: start hil_sim, run the daemon, join the logs."""

from __future__ import annotations

import math
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


class HilSim:
    """python -m hil_sim as a subprocess; waits for its READY line."""

    def __init__(self, *args: str, timeout_s: float = 20.0) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "hil_sim", *args], cwd=ROOT, env=ENV,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + timeout_s
        self.ready = ""
        while time.monotonic() < deadline:
            r, _, _ = select.select([self.proc.stdout], [], [], 0.2)
            if r:
                line = self.proc.stdout.readline()
                if line.startswith("hil_sim ready"):
                    self.ready = line.strip()
                    return
            if self.proc.poll() is not None:
                break
        err = self.proc.stderr.read() if self.proc.poll() is not None else ""
        self.stop()
        raise RuntimeError(f"hil_sim did not become ready: {err}")

    def field(self, name: str) -> str:
        for part in self.ready.split():
            if part.startswith(name + "="):
                return part.split("=", 1)[1]
        raise KeyError(name)

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return self.proc.returncode


def run_daemon(config: Path, out: Path, duration_s: float, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mrctl", "run", str(config), "--out", str(out),
                           "--duration", str(duration_s), "--quiet",
                           "--status-socket", str(out.with_suffix(".sock"))],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=timeout_s)


def hil_tracking(run: dict, truth: dict, settle_s: float = 1.0) -> dict:
    """Force NRMSE from ground truth: F_true at device tick k against the F_des
    the daemon computed from that tick's sample (joined on seq = k)."""
    seq = run["seq"]
    ok = np.isfinite(seq) & np.isfinite(run["F_des"])
    k_run = seq[ok].astype(np.int64)
    F_des = run["F_des"][ok]
    k_truth = truth["k"].astype(np.int64)
    idx = np.searchsorted(k_truth, k_run)
    idx = np.clip(idx, 0, len(k_truth) - 1)
    match = k_truth[idx] == k_run
    k_run, F_des, idx = k_run[match], F_des[match], idx[match]
    if len(idx) < 10:
        raise AssertionError(f"only {len(idx)} daemon ticks match the ground truth: the run did not control")
    t = truth["t"][idx]
    w = t >= t[0] + settle_s
    e = truth["F_true"][idx][w] - F_des[w]
    return {"nrmse": float(math.sqrt(np.mean(e * e)) / np.ptp(F_des[w])), "rows": int(w.sum()),
            "matched": int(match.sum())}
