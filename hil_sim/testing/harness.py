"""Start ``python -m hil_sim`` and ``mrctl run`` as processes, and join their logs.

The client side of the simulated bench, shared by the loopback HIL tests,
``bench/hil_loop.py`` and the fault suite (:mod:`hil_sim.testing.fault_suite`).
"""

from __future__ import annotations

import math
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def env() -> dict[str, str]:
    """The environment for child processes: this checkout first on the path."""
    return dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


class HilSim:
    """``python -m hil_sim ARGS`` as a subprocess; waits for its READY line.

    Its stderr goes to a file in ``workdir`` (a pipe nobody reads could fill
    and stall the simulator's clock)."""

    def __init__(self, *args: str, workdir: Path | None = None, timeout_s: float = 30.0) -> None:
        wd = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="hil_sim-"))
        self.err_path = wd / f"hil_sim-{time.monotonic_ns()}.stderr"
        self._err = open(self.err_path, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "hil_sim", *args], cwd=ROOT, env=env(),
                                     stdout=subprocess.PIPE, stderr=self._err, text=True)
        self.ready = ""
        self.t_ready = math.nan
        deadline = time.monotonic() + timeout_s
        assert self.proc.stdout is not None
        while time.monotonic() < deadline:
            r, _, _ = select.select([self.proc.stdout], [], [], 0.1)
            if r:
                line = self.proc.stdout.readline()
                if line.startswith("hil_sim ready"):
                    self.ready = line.strip()
                    self.t_ready = time.monotonic()
                    return
                if not line:
                    break
            if self.proc.poll() is not None:
                break
        self.stop()
        raise RuntimeError(f"hil_sim did not become ready: {self.err_path.read_text()}")

    def field(self, name: str) -> str:
        """A ``name=value`` field of the READY line (e.g. ``bind``, ``tty``)."""
        for part in self.ready.split():
            if part.startswith(name + "="):
                return part.split("=", 1)[1]
        raise KeyError(name)

    def stop(self) -> int:
        """SIGTERM, wait (kill after 30 s); returns the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._err.close()
        return self.proc.returncode


def run_daemon(config: Path, out: Path, duration_s: float, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """``mrctl run CONFIG --out OUT --duration S --quiet`` to completion."""
    return subprocess.run([sys.executable, "-m", "mrctl", "run", str(config), "--out", str(out),
                           "--duration", str(duration_s), "--quiet",
                           "--status-socket", str(out.with_suffix(".sock"))],
                          cwd=ROOT, env=env(), capture_output=True, text=True, timeout=timeout_s)


def scored_run(config: Path, out: Path, seconds: float, hil: "HilSim", truth: Path) -> dict:
    """Run the daemon against a started ``hil``, stop the bench, and score the
    run against its truth log: ``{"error": last stderr line}`` if the daemon
    failed, else ``{"nrmse", "summary", "verdict", "verdict_reasons"}`` (the
    sidecar's); a degraded run (exit 5) is scored too."""
    from mrctl.runlog.read import read_run, read_sidecar

    try:
        res = run_daemon(config, out, seconds)
    finally:
        hil.stop()
    if res.returncode not in (0, 5):  # 5: completed, degraded (its verdict is kept): still a figure
        return {"error": res.stderr.strip().splitlines()[-1] if res.stderr.strip() else f"exit {res.returncode}"}
    side = read_sidecar(out)
    return {"nrmse": hil_tracking(read_run(out), read_run(truth))["nrmse"], "summary": side["summary"],
            "verdict": side.get("verdict"), "verdict_reasons": side.get("verdict_reasons", [])}


def hil_tracking(run: dict, truth: dict, settle_s: float = 1.0) -> dict:
    """Force NRMSE from ground truth: F_true at device tick k against the F_des
    the daemon computed from that tick's sample (joined on seq = k)."""
    seq = run["seq"]
    ok = np.isfinite(seq) & np.isfinite(run["F_des"])
    k_run = seq[ok].astype(np.int64)
    F_des = run["F_des"][ok]
    k_truth = truth["k"].astype(np.int64)
    idx = np.clip(np.searchsorted(k_truth, k_run), 0, len(k_truth) - 1)
    match = k_truth[idx] == k_run
    k_run, F_des, idx = k_run[match], F_des[match], idx[match]
    if len(idx) < 10:
        raise AssertionError(f"only {len(idx)} daemon ticks match the ground truth: the run did not control")
    t = truth["t"][idx]
    w = t >= t[0] + settle_s
    e = truth["F_true"][idx][w] - F_des[w]
    return {"nrmse": float(math.sqrt(np.mean(e * e)) / np.ptp(F_des[w])), "rows": int(w.sum()),
            "matched": int(match.sum())}


class Run:
    """``mrctl run CONFIG --out OUT --duration S --quiet [EXTRA...]`` as a subprocess,
    stderr to a file beside the log."""

    def __init__(self, config: Path, out: Path, duration_s: float, *extra: str,
                 env_extra: dict[str, str] | None = None, sock: Path | None = None,
                 err_path: Path | None = None) -> None:
        self.out = out
        self.sock = str(sock or out.with_name(out.stem + ".sock"))
        self.err_path = err_path or out.with_name(out.name + ".stderr")
        self._err = open(self.err_path, "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mrctl", "run", str(config), "--out", str(out), "--duration", str(duration_s),
             "--quiet", "--status-socket", self.sock, *extra],
            cwd=ROOT, env={**env(), **(env_extra or {})}, stdout=subprocess.DEVNULL, stderr=self._err)
        self.pid = self.proc.pid

    def status(self) -> dict[str, Any] | None:
        from mrctl.daemon.status import query_status

        try:
            st = query_status(self.sock, timeout_s=1.0)
        except (OSError, ValueError):
            return None
        return st if isinstance(st, dict) else None

    def wait_for(self, pred, timeout_s: float = 30.0) -> dict[str, Any] | None:
        """Poll the status socket until ``pred(status)``; None if the run ended first."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.proc.poll() is None:
            st = self.status()
            if st and pred(st):
                return st
            time.sleep(0.02)
        return None

    def wait(self, timeout_s: float = 120.0) -> int:
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._err.close()
        return self.proc.returncode

    def stderr(self) -> str:
        try:
            return self.err_path.read_text()
        except OSError:
            return ""
