"""Run a scenario: hil_sim and ``mrctl run`` as processes, the process faults
(signals, a broken reload), then the analysis of the logs they left."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

from hil_sim.testing.fault_suite.analysis import analyse
from hil_sim.testing.fault_suite.scenario import BENCH, Scenario, experiment_config
from hil_sim.testing.harness import HilSim, Run

__all__ = ["Daemon", "warm_up", "run_scenario"]


class Daemon(Run):
    """``mrctl run CONFIG --out OUT --quiet`` as a subprocess (socket and stderr beside the log)."""

    def __init__(self, config: Path, out: Path, duration_s: float) -> None:
        super().__init__(config, out, duration_s, sock=out.with_suffix(".sock"), err_path=out.with_suffix(".stderr"))

    def wait_ticks(self, n: int, timeout_s: float = 30.0, min_current_A: float = 0.0) -> dict[str, Any] | None:
        """Poll the status socket until the loop has run n ticks and commands at
        least ``min_current_A`` (None if it ended first)."""
        return self.wait_for(lambda st: st.get("ticks", 0) >= n and (st.get("current_A") or 0.0) >= min_current_A,
                             timeout_s)


def _start_bench(sc: Scenario, workdir: Path) -> tuple[HilSim, Path]:
    truth = workdir / "truth.csv"
    args = ["--config", str(BENCH), "--transport", sc.transport, "--truth", str(truth),
            "--duration", str(sc.bench_duration_s)]
    if sc.transport == "modbus-tcp":
        args += ["--bind", "127.0.0.1:0"]
    else:
        args += ["--link", str(workdir / "tty")]
    args += ["--serve", "inline" if sc.shipped else sc.serve]
    for f in sc.faults:
        args += ["--fault", f]
    return HilSim(*args, workdir=workdir), truth


def warm_up(transport: str, link: str | None, port: int | None, n: int = 20) -> int:
    """A few 0 A exchanges with the bench before the daemon starts; returns the
    successful ones. The very first exchange of a fresh link is slow (cold code
    paths on both sides: up to ~5 ms measured), and the daemon's start-up 0 A
    exchange is a single attempt (exit 3 if it times out): warming the device
    side up keeps that start-up failure, which is not under test, rare."""
    from mrctl.io.base import LinkError

    if transport == "serial":
        from mrctl.io.serial import SerialLink

        lk: Any = SerialLink(str(link), timeout_s=0.02)
    elif transport == "modbus-tcp":
        from mrctl.io.modbus import ModbusLink

        lk = ModbusLink("tcp", host="127.0.0.1", port=int(port or 0), timeout_s=0.02, use_fc23=True)
    else:
        return 0
    ok = 0
    try:
        lk.open()
        for _ in range(n):
            try:
                lk.exchange(0.0)
                ok += 1
            except LinkError:
                pass
            time.sleep(0.001)
    except LinkError:
        pass
    finally:
        lk.close()
    return ok


def run_scenario(sc: Scenario, workdir: Path) -> dict[str, Any]:
    """Run one scenario in workdir (created); returns the measurements (see module doc)."""
    workdir.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    sim, truth_path = _start_bench(sc, workdir)
    res: dict[str, Any] = {"name": sc.name, "expected": sc.expected, "transport": sc.transport,
                           "faults": sc.faults, "process": sc.process}
    try:
        port = int(sim.field("bind").rsplit(":", 1)[1]) if sc.transport == "modbus-tcp" else None
        link = None if port else str(workdir / "tty")
        cfg = experiment_config(sc, workdir, link=link, port=port)
        res["warm_up_ok"] = warm_up(sc.transport, link, port)
        out = workdir / "run.csv"
        d = Daemon(cfg, out, sc.duration_s)
        proc_info: dict[str, Any] = {}
        if sc.arms_after_latch_s:
            latched = d.wait_for(lambda s: s.get("safety_state") == "LATCHED", timeout_s=sc.duration_s + 30.0)
            t_latched = time.monotonic()
            res["arms"] = [_arm_at(d, latched is not None, t_latched + after) for after in sc.arms_after_latch_s]
        if sc.process in ("SIGTERM", "SIGINT", "SIGKILL"):
            # signal while the law commands a clear current (not near one of the
            # fig5 law's own 0 A zero crossings), so "0 A at the device" is the exit's
            st = d.wait_ticks(sc.process_at_ticks, min_current_A=0.3)
            proc_info["status_before"] = _brief_status(st)
            if d.proc.poll() is None:
                d.proc.send_signal(getattr(signal, sc.process))
                proc_info["signal_sent"] = True
        elif sc.process == "reload":
            st = d.wait_ticks(sc.process_at_ticks)
            proc_info["status_before"] = _brief_status(st)
            if d.proc.poll() is None:
                # a broken edit: valid YAML, but a negative current limit
                broken = json.loads(cfg.read_text())
                broken["safety"]["I_max"] = -1.0
                cfg.write_text(json.dumps(broken, indent=1) + "\n")
                d.proc.send_signal(signal.SIGHUP)
                proc_info["signal_sent"] = True
                deadline = time.monotonic() + 10.0
                while time.monotonic() < deadline and d.proc.poll() is None:
                    s2 = d.status()
                    if s2 and s2.get("reloads", {}).get("rejected", 0) >= 1:
                        proc_info["status_after"] = _brief_status(s2)
                        break
                    time.sleep(0.02)
        res["exit_code"] = d.wait(timeout_s=sc.duration_s + 60.0)
        res["daemon_stderr"] = d.stderr().strip().splitlines()[-6:]
        res["process_info"] = proc_info
        if sc.process == "SIGKILL":
            # the restart: the same config, a new log; the device has been without
            # setpoints since the kill (its watchdog applied 0 A)
            time.sleep(0.3)
            d2 = Daemon(cfg, workdir / "restart.csv", 1.5)
            if d2.wait_ticks(1, timeout_s=20.0) is None and d2.proc.poll() not in (None, 0):
                # the restart's start-up exchange timed out (see warm_up): once more
                d2.wait()
                res["restart_attempts"] = 2
                d2 = Daemon(cfg, workdir / "restart.csv", 1.5)
            res["restart_exit_code"] = d2.wait(timeout_s=60.0)
            res["restart_stderr"] = d2.stderr().strip().splitlines()[-4:]
    finally:
        res["bench_exit_code"] = sim.stop()
        res["wall_s"] = round(time.monotonic() - t_start, 2)
    res.update(analyse(sc, workdir, res))
    return res


def _arm_at(d: Daemon, latched: bool, at: float) -> dict[str, Any]:
    """``mrctl arm`` (the client call) at monotonic time ``at``: what the daemon
    said, and its state just before (nothing if it never latched)."""
    from mrctl.daemon.arm import ArmRefused, arm
    from mrctl.daemon.status import StatusError

    if not latched:
        return {"status_before": None, "armed": False, "message": "never latched"}
    time.sleep(max(0.0, at - time.monotonic()))
    out: dict[str, Any] = {"status_before": _brief_status(d.status())}
    try:
        out["message"] = arm(d.sock)
        out["armed"] = True
    except ArmRefused as exc:
        out["armed"], out["message"] = False, str(exc)
    except StatusError as exc:
        out["armed"], out["message"] = False, f"no daemon: {exc}"
    return out


def _brief_status(st: dict[str, Any] | None) -> dict[str, Any] | None:
    if not st:
        return None
    return {k: st.get(k) for k in ("ticks", "safety_state", "latch_cause", "link_errors", "reloads", "current_A")}

