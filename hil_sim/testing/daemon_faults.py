"""Daemon-level faults: who owns the device, a full disk, a symlink at the log path.

The link faults are :mod:`hil_sim.testing.fault_suite`'s; these are the ones
around the loop, found by probing ``mrctl run`` as a careless or hostile
local user. Each scenario runs the real daemon as a process (against
hil_sim where a device is needed) and returns measurements; nothing here
asserts. Used by ``bench/daemon_faults.py`` (the second table of
docs/reliability.md) and by the regression tests (tests/test_ownership.py,
tests/test_disk_full.py, tests/test_log_paths.py).
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import time
from pathlib import Path
from typing import Any, Iterator

from hil_sim.testing.harness import ROOT, HilSim, Run
from hil_sim.testing.peers import free_port

BENCH = ROOT / "config" / "hil_fig5_bench.yaml"
EXPERIMENTS = {"serial": "hil_serial.yaml", "modbus-tcp": "hil_modbus_tcp.yaml"}
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"
#: allowances for a noisy shared VM, as the link-fault suite's (its module doc)
ROBUST_BACKEND = {"timeout_s": 0.005}
ROBUST_LINK = {"on_infeasible": "refuse", "probe_exchanges": 0}
ROBUST_SAFETY = {"link_loss_s": 0.5, "auto_resume": True}


# -- processes ----------------------------------------------------------------------
def _sidecar(out: Path) -> dict[str, Any]:
    try:
        return json.loads(out.with_suffix(".json").read_text())
    except (OSError, ValueError):
        return {}


def _mrctl_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.startswith("mrctl:")]


# -- 1. two daemons, one device --------------------------------------------------------
def hil_experiment(transport: str, workdir: Path, *, port: int | None = None, link: str | None = None,
                   file: str | None = None) -> Path:
    """The shipped fig5 HIL experiment for ``transport`` with the VM allowances,
    pointed at this bench; written as JSON (valid YAML)."""
    from mrctl.config import load_yaml

    data = load_yaml(ROOT / "config" / "experiments" / EXPERIMENTS[transport])
    be = {**data["backend"], **ROBUST_BACKEND}
    if port is not None:
        be["port"] = port
    if link is not None:
        be["url"] = link
    data.update(backend=be, name=f"owner_{transport}".replace("-", "_"),
                safety={**data["safety"], **ROBUST_SAFETY}, link={**data.get("link", {}), **ROBUST_LINK},
                loop={**data.get("loop", {}), "pacing": "host"})
    path = workdir / (file or f"experiment_{transport}.yaml")
    path.write_text(json.dumps(data, indent=1) + "\n")
    return path


@contextlib.contextmanager
def bench(transport: str, workdir: Path, duration_s: float = 60.0) -> Iterator[tuple[HilSim, str]]:
    """hil_sim serving ``transport`` (threaded), and the device's name as a
    user would give it (``127.0.0.1:PORT`` or the pty path)."""
    args = ["--config", str(BENCH), "--transport", transport, "--duration", str(duration_s), "--serve", "thread"]
    if transport == "modbus-tcp":
        args += ["--bind", "127.0.0.1:0"]
    else:
        args += ["--link", str(workdir / "tty")]
    sim = HilSim(*args, workdir=workdir)
    try:
        if transport == "modbus-tcp":
            yield sim, "127.0.0.1:" + sim.field("bind").rsplit(":", 1)[1]
        else:
            yield sim, str(workdir / "tty")
    finally:
        sim.stop()


def ownership(transport: str, workdir: Path, lock_dir: Path | None = None) -> dict[str, Any]:
    """Daemon A runs against hil_sim; daemon B is started on the same device
    while A is in its loop. What B does, and whether A noticed."""
    workdir.mkdir(parents=True, exist_ok=True)
    extra_env = {"MRCTL_LOCK_DIR": str(lock_dir)} if lock_dir is not None else None
    res: dict[str, Any] = {"transport": transport}
    with bench(transport, workdir) as (_sim, device):
        port = int(device.rsplit(":", 1)[1]) if transport == "modbus-tcp" else None
        cfg = hil_experiment(transport, workdir, port=port, link=None if port else device)
        res["device"] = device
        a = Run(cfg, workdir / "a.csv", 8.0, env_extra=extra_env)
        st = a.wait_for(lambda s: s.get("ticks", 0) >= 500, timeout_s=60.0)
        res["a_pid"] = a.pid
        res["a_in_loop"] = st is not None
        # control: a daemon as heavy to start as B (interpreter, imports, config,
        # lock) on a device that is not there (it exits 3 at open); the link
        # errors A logs meanwhile are the load of a start on this box
        errors_before = (st or {}).get("link_errors")
        if port:
            nowhere = {"port": free_port()}
        else:
            nowhere = {"link": str(workdir / "absent-tty")}
        ctl_cfg = hil_experiment(transport, workdir, file="control.yaml", **nowhere)
        c = Run(ctl_cfg, workdir / "control.csv", 2.0, env_extra=extra_env)
        res["control_exit"] = c.wait(timeout_s=60.0)
        st_c = a.status() or {}
        res["a_link_errors_while_control"] = (None if errors_before is None or "link_errors" not in st_c
                                              else st_c["link_errors"] - errors_before)
        errors_before = st_c.get("link_errors")
        t0 = time.monotonic()
        b = Run(cfg, workdir / "b.csv", 2.0, env_extra=extra_env)
        res["b_exit"] = b.wait(timeout_s=60.0)
        res["b_wall_s"] = round(time.monotonic() - t0, 2)
        st2 = a.status() or {}
        res["a_link_errors_while_b"] = (None if errors_before is None or "link_errors" not in st2
                                        else st2["link_errors"] - errors_before)
        err = b.stderr()
        res["b_messages"] = _mrctl_lines(err)
        res["b_names_owner_pid"] = f"pid {a.pid}" in err
        res["b_names_device"] = device in err
        res["b_wrote_log"] = (workdir / "b.csv").exists()
        res["a_exit"] = a.wait(timeout_s=60.0)
        side = _sidecar(workdir / "a.csv")
        summ = side.get("summary") or {}
        res["a_faults_entered"] = (summ.get("safety") or {}).get("faults_entered")
        res["a_link_errors"] = summ.get("link_errors")
        res["a_messages"] = _mrctl_lines(a.stderr())
    return res


# -- 2. a full disk ----------------------------------------------------------------------
@contextlib.contextmanager
def small_tmpfs(path: Path, size: str = "256k") -> Iterator[Path | None]:
    """A tmpfs of ``size`` mounted at ``path`` (root only); None if it cannot be."""
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        yield None
        return
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def disk_full(workdir: Path, *, sigterm: bool = False, size: str = "256k", duration_s: float = 4.0) -> dict[str, Any]:
    """``mrctl run fig5.yaml`` (in-process simulated bench) logging to a tiny
    tmpfs that fills up mid-run; with ``sigterm`` the run is stopped by SIGTERM
    once it has started losing rows."""
    workdir.mkdir(parents=True, exist_ok=True)
    res: dict[str, Any] = {"size": size, "sigterm": sigterm}
    with small_tmpfs(workdir / "small", size) as mnt:
        if mnt is None:
            res["skipped"] = "cannot mount a tmpfs here (needs root)"
            return res
        out = mnt / "run.csv"
        run = Run(FIG5, out, 30.0 if sigterm else duration_s, sock=workdir / "st.sock",
                  err_path=workdir / "run.stderr")
        if sigterm:
            st = run.wait_for(lambda s: ((s.get("recorder") or {}).get("dropped_rows") or 0) > 0, timeout_s=60.0)
            res["status_while_losing"] = {k: (st or {}).get(k) for k in ("ticks", "log", "recorder")}
            if run.proc.poll() is None:
                run.proc.send_signal(signal.SIGTERM)
                res["signal_sent"] = True
        res["exit"] = run.wait(timeout_s=120.0)
        err = run.stderr()
        res["messages"] = _mrctl_lines(err)
        res["traceback"] = "Traceback" in err
        side = _sidecar(out)
        summ = side.get("summary") or {}
        res["sidecar"] = {k: side.get(k) for k in ("complete", "exit_code", "rows_written", "dropped_rows",
                                                   "lost_rows", "overflow_rows", "lost_first_tick", "error",
                                                   "ticks")}
        res["exit_current_A"] = summ.get("exit_current_A")
        res["loop_ticks"] = (summ.get("timing") or {}).get("ticks")
    return res


# -- 3. the log path -----------------------------------------------------------------------
def log_path_symlink(workdir: Path) -> dict[str, Any]:
    """``ln -s precious.txt link.csv; mrctl run fig5.yaml --out link.csv`` (and
    then with ``--force``), and ``--out`` an existing log without ``--force``."""
    workdir.mkdir(parents=True, exist_ok=True)
    precious = workdir / "precious.txt"
    text = "irreplaceable notes\n"
    precious.write_text(text)
    link = workdir / "link.csv"
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(precious.name)
    res: dict[str, Any] = {}
    # about the path, not the timing: a 0.3 s run on a busy host may skip deadlines (exit 5)
    fig5 = workdir / "fig5.yaml"
    fig5.write_text(FIG5.read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    r1 = Run(fig5, link, 0.3, sock=workdir / "a.sock")
    res["exit"] = r1.wait()
    res["messages"] = _mrctl_lines(r1.stderr())
    res["target_untouched"] = precious.read_text() == text
    r2 = Run(fig5, link, 0.3, "--force", sock=workdir / "b.sock")
    res["force_exit"] = r2.wait()
    res["force_messages"] = _mrctl_lines(r2.stderr())
    res["force_target_untouched"] = precious.read_text() == text
    res["force_link_replaced_by_log"] = (not link.is_symlink()) and link.exists() and \
        link.read_text().split("\n", 1)[0].startswith("t,")
    # an existing log, without --force
    before = link.read_bytes() if link.exists() else b""
    r3 = Run(fig5, link, 0.3, sock=workdir / "c.sock")
    res["existing_exit"] = r3.wait()
    res["existing_messages"] = _mrctl_lines(r3.stderr())
    res["existing_untouched"] = link.exists() and link.read_bytes() == before
    return res

