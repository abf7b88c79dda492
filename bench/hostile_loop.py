#!/usr/bin/env python3
"""Hostile attacks on what stands beside the loop (issue 23: D1 D2 D4 D5 D7
D13 D14 D15 D19 D20), for ``bench/hostile.py``'s table.

:data:`ATTACKS` lists ``(defect id, one-line attack, run)``; ``run()`` makes
the attack on this tree in a temporary directory and child processes, in
under 30 s, and returns ``(held, short detail)``. Run alone, it prints them:

    python bench/hostile_loop.py            # every attack
    python bench/hostile_loop.py D2 D5      # some
"""

from __future__ import annotations

import atexit
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

sys.path.insert(0, str(Path(__file__).resolve().parent))

from loop_under_attack import FIG5, ROOT, Daemon, alias_bomb, flood, plugin_config, run_daemon  # noqa: E402

from mrctl.errors import ExitCode  # noqa: E402

TCP_EXP = (ROOT / "config" / "experiments" / "hil_modbus_tcp.yaml").read_text()
#: a bad config's extra keys removed, so that a plugin law's empty params validate
_PLAIN = ("  eps_N_per_A: 3.0        # hold the current where dF/dI is below ~3 N/A\n",
          "  max_slew_A_per_s: 50.0  # current-driver slew bound: 0.05 A per 1 ms tick\n")

PLUGINS = {
    "exits_law.py": "raise SystemExit(0)\n",
    "hangs_law.py": "import time\ntime.sleep(3600)\n",
    "reset_raises_law.py": """
from mrctl.laws.base import CurrentLaw
class Law(CurrentLaw):
    name = "reset_raises"
    params = {}
    def __init__(self, ctx):
        pass
    def reset(self, I0=0.0):
        raise RuntimeError("cannot reset me")
    def current(self, m, F_des):
        return 0.0
""",
    "slow_reset_law.py": """
import os, time
from mrctl.laws.base import CurrentLaw
_n = [0]
class Law(CurrentLaw):
    name = "slow_reset"
    params = {}
    def __init__(self, ctx):
        pass
    def reset(self, I0=0.0):
        _n[0] += 1
        if _n[0] == 2:  # the second reset: the link is open, the run log exists
            open(os.environ["SLOW_MARK"], "w").close()
            time.sleep(3.0)
    def current(self, m, F_des):
        return 0.1
""",
}


def _law(module: str) -> str:
    text = FIG5.replace("law: smooth", f"law: '{module}:Law'")
    for line in _PLAIN:
        text = text.replace(line, "")
    return text


def _tmp() -> Path:
    """A fresh directory with the plugins in it, removed when this process ends."""
    d = Path(tempfile.mkdtemp(prefix="mrctl-hostile-"))
    atexit.register(shutil.rmtree, d, True)
    for name, text in PLUGINS.items():
        (d / name).write_text(text)
    return d


def _env(d: Path, **extra: str) -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(d), str(ROOT)]), MRCTL_LOCK_DIR=str(d / "locks"),
                **extra)


def _mrctl(d: Path, *args: str, timeout: float = 25.0, **env: str) -> tuple[int | None, str, float]:
    """(exit code or None on timeout, stderr, seconds)."""
    t0 = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=d, env=_env(d, **env),
                           capture_output=True, text=True, timeout=timeout)
        return r.returncode, r.stderr, time.monotonic() - t0
    except subprocess.TimeoutExpired as exc:
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        return None, err, time.monotonic() - t0


def _last(err: str, n: int = 110) -> str:
    """The last line of ``err``, temporary paths cut to their file name."""
    lines = [line for line in err.strip().splitlines() if line.strip()]
    line = re.sub(r"/\S*/mrctl-hostile-[^/\s]+/(\S+/)?", "", lines[-1] if lines else "(no message)")
    return line.removeprefix("mrctl: ")[:n]


def _run_args(d: Path, cfg: Path, seconds: float = 0.3) -> list[str]:
    return ["run", str(cfg), "--out", str(d / "r.csv"), "--duration", str(seconds), "--quiet",
            "--status-socket", str(d / "st.sock")]


# -- D1 ----------------------------------------------------------------------------
class _Listener:
    """A TCP port that counts who connects (a device that must never be reached)."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.connections = 0
        self._stop = threading.Event()
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                c, _ = self.sock.accept()
                self.connections += 1
                c.close()
            except OSError:
                continue

    def close(self) -> None:
        self._stop.set()
        self.sock.close()


def attack_d1() -> tuple[bool, str]:
    d = _tmp()
    dev = _Listener()
    try:
        code = ("import sys; from mrctl.io.modbus import ModbusLink; from mrctl.daemon.ownership import acquire\n"
                f"lock = acquire(ModbusLink('tcp', host='127.0.0.1', port={dev.port}, unit_id=1).device_key(), 'owner')\n"
                "print('held', flush=True); sys.stdin.read(); lock.release()\n")
        owner = subprocess.Popen([sys.executable, "-c", code], env=_env(d), stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True)
        assert owner.stdout is not None
        owner.stdout.readline()
        results = []
        for host, unit in (('"::ffff:127.0.0.1"', 1), ("127.0.0.1", 0), ("localhost", 17)):
            cfg = d / f"tcp{unit}.yaml"
            cfg.write_text(TCP_EXP.replace("host: 127.0.0.1, port: 5020, unit_id: 1",
                                           f"host: {host}, port: {dev.port}, unit_id: {unit}"))
            rc, err, _ = _mrctl(d, *_run_args(d, cfg, 1.0))
            results.append((rc, "in use by another mrctl" in err))
        owner.communicate("", timeout=10)
        held = all(rc == 3 and busy for rc, busy in results) and dev.connections == 0
        return held, (f"second daemon as ::ffff:127.0.0.1 unit 1, 127.0.0.1 unit 0, localhost unit 17: exits "
                      f"{[rc for rc, _ in results]}, device connections {dev.connections}")
    finally:
        dev.close()


# -- D2 ----------------------------------------------------------------------------
def _reload_sequence(texts: list[str]) -> Callable[[Daemon], list[tuple[float | None, str]]]:
    def during(dm: Daemon) -> list[tuple[float | None, str]]:
        out = []
        time.sleep(0.5)
        for text in texts:
            dm.cfg.write_text(text)
            t0 = time.monotonic()
            dm.proc.send_signal(signal.SIGHUP)
            t = dm.wait_line("reload rejected|reload: new demand", t0, 15.0)
            line = next((ln for tt, ln in dm.lines if tt == t), "") if t is not None else ""
            out.append((None if t is None else t - t0, line))
        return out

    return during


#: a run that completed: 0, or 5 when the machine's load broke its timing
#: bound (the verdict); the attack's own effect on timing is judged by the
#: longest gap against the quiet run's
COMPLETED = (ExitCode.OK, ExitCode.DEGRADED)


def _gap_ok(attack_us: float | None, quiet_us: float | None) -> bool:
    """Within 2x the quiet run's longest gap (or under 20 ms: noise on a busy 2-core box)."""
    return attack_us is not None and quiet_us is not None and (attack_us <= 2 * quiet_us or attack_us < 20_000)


def attack_d2_reload() -> tuple[bool, str]:
    d = _tmp()
    quiet = run_daemon(d / "quiet", 7.0)
    hostile = [FIG5 + alias_bomb(), FIG5 + "# " + "x" * 2_600_000 + "\n",
               FIG5.replace("rate_hz: 1000", "rate_hz: [" + ",".join(["1e9"] * 15_000) + "]")]
    r = run_daemon(d / "attack", 7.0, _reload_sequence(hostile + [FIG5.replace("c_des: 500.0", "c_des: 700.0")]))
    answers = r["during"] or []
    rejected = sum("reload rejected" in line for _, line in answers[:3])
    applied = len(answers) == 4 and "reload: new demand" in answers[3][1]
    gq, ga = quiet["timing"].get("longest_gap_us"), r["timing"].get("longest_gap_us")
    lat = max((t or 99) for t, _ in answers) if answers else None
    held = r["exit"] in COMPLETED and rejected == 3 and applied and _gap_ok(ga, gq)
    return held, (f"alias bomb, 2.6 MB, 60 KB of bad values: {rejected}/3 rejected, slowest answer "
                  f"{lat:.2f} s; good reload applied: {applied}; longest gap {ga / 1e3 if ga else float('nan'):.1f} ms "
                  f"(quiet {gq / 1e3 if gq else float('nan'):.1f} ms); exit {r['exit']}")


def attack_d2_check() -> tuple[bool, str]:
    d = _tmp()
    (d / "bomb.yaml").write_text(FIG5 + alias_bomb())
    (d / "big.yaml").write_text(FIG5 + "# " + "x" * 2_600_000 + "\n")
    rc1, err1, t1 = _mrctl(d, "check", str(d / "bomb.yaml"))
    rc2, err2, t2 = _mrctl(d, "check", str(d / "big.yaml"))
    held = rc1 == 2 and rc2 == 2 and len(err1) < 2000 and len(err2) < 2000 and max(t1, t2) < 10
    return held, f"check bomb: exit {rc1} in {t1:.1f} s ({_last(err1, 70)}); 2.6 MB: exit {rc2} ({_last(err2, 60)})"


# -- D4 ----------------------------------------------------------------------------
def attack_d4() -> tuple[bool, str]:
    d = _tmp()
    ns = d / "notify.sock"
    rx = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    rx.bind(str(ns))
    rx.settimeout(0.1)
    pings: list[float] = []
    stop = threading.Event()

    def listen() -> None:
        while not stop.is_set():
            try:
                if b"WATCHDOG=1" in rx.recv(4096):
                    pings.append(time.monotonic())
            except OSError:
                continue

    threading.Thread(target=listen, daemon=True).start()
    # run_daemon puts loop_under_attack's plugins beside the config
    texts = [plugin_config("hangs_at_import"), plugin_config("exits_at_import"),
             FIG5.replace("c_des: 500.0", "c_des: 700.0")]
    try:
        r = run_daemon(d / "run", 15.0, _reload_sequence(texts),
                       env={"NOTIFY_SOCKET": str(ns), "WATCHDOG_USEC": "400000"})
    finally:
        stop.set()
    rx.close()
    answers = r["during"] or []
    expect = ("took longer than", "SystemExit(0) raised at import", "reload: new demand")
    ok = [want in line for (_, line), want in zip(answers, expect)]
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    held = r["exit"] in COMPLETED and len(ok) == 3 and all(ok) and bool(gaps) and max(gaps) < 1.0
    return held, (f"reload with a plugin that hangs at import, then SystemExit, then a good file: answered "
                  f"{[round(t, 1) if t else None for t, _ in answers]} s as expected: {ok}; "
                  f"{len(pings)} WATCHDOG pings, longest pause {max(gaps) if gaps else float('nan'):.2f} s")


# -- D5 ----------------------------------------------------------------------------
def attack_d5() -> tuple[bool, str]:
    d = _tmp()
    quiet = run_daemon(d / "quiet", 6.0)
    r = run_daemon(d / "flood", 6.0, flood)
    tq, tf = quiet["timing"], r["timing"]
    gq, gf = tq.get("longest_gap_us"), tf.get("longest_gap_us")
    sq, sf = tq.get("skipped_deadlines") or 0, tf.get("skipped_deadlines") or 0
    held = r["exit"] in COMPLETED and _gap_ok(gf, gq) and sf <= 2 * sq + 20
    q = (r["during"] or {}).get("queries")
    return held, (f"8 scrapers back to back ({q} answers in 6 s): longest gap {gf / 1e3 if gf else float('nan'):.1f} ms, "
                  f"skipped {sf}; quiet {gq / 1e3 if gq else float('nan'):.1f} ms, skipped {sq}")


# -- D20 ---------------------------------------------------------------------------
def _lock_path(d: Path, port: int) -> Path:
    from mrctl.daemon.ownership import _file_name
    from mrctl.io.modbus import ModbusLink

    (d / "locks").mkdir(exist_ok=True)
    return d / "locks" / _file_name(ModbusLink("tcp", host="127.0.0.1", port=port, unit_id=1).device_key() or "")


def attack_d20_fifo() -> tuple[bool, str]:
    d = _tmp()
    dev = _Listener()
    try:
        fifo = _lock_path(d, dev.port)
        os.mkfifo(fifo, 0o444)
        if os.getuid() == 0:
            os.chown(fifo, 65534, 65534)
        cfg = d / "tcp.yaml"
        cfg.write_text(TCP_EXP.replace("port: 5020", f"port: {dev.port}"))
        rc, err, t = _mrctl(d, *_run_args(d, cfg), timeout=15)
        held = rc == 3 and "is a FIFO, not a regular file" in err and dev.connections == 0
        return held, f"FIFO at the lock path: exit {rc} after {t:.1f} s: …{_last(err, 400).split('.lock', 1)[-1][:90]}"
    finally:
        dev.close()


def attack_d20_mode0() -> tuple[bool, str]:
    d = _tmp()
    dev = _Listener()
    try:
        p = _lock_path(d, dev.port)
        p.touch()
        os.chmod(p, 0)
        if os.getuid() == 0:
            os.chown(p, 65534, 65534)
        cfg = d / "tcp.yaml"
        cfg.write_text(TCP_EXP.replace("port: 5020", f"port: {dev.port}"))
        rc, err, t = _mrctl(d, *_run_args(d, cfg), timeout=15)
        held = rc == 3 and "not a lock file mrctl made" in err and dev.connections == 0
        return held, f"another user's 0000 file at the lock path: exit {rc}: …{_last(err, 400).split('.lock', 1)[-1][:90]}"
    finally:
        dev.close()


# -- D7 ----------------------------------------------------------------------------
def _signal_at_start(sig: signal.Signals) -> tuple[int | None, str, Path]:
    d = _tmp()
    cfg, mark, out = d / "exp.yaml", d / "mark", d / "r.csv"
    # the timing bounds open: the signal's handling is judged, not a loaded machine's clock
    cfg.write_text(_law("slow_reset_law") + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    p = subprocess.Popen([sys.executable, "-m", "mrctl", *_run_args(d, cfg, 2.0)], cwd=d,
                         env=_env(d, SLOW_MARK=str(mark)), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + 20
    while not mark.exists() and p.poll() is None and time.monotonic() < t_end:
        time.sleep(0.01)
    p.send_signal(sig)
    try:
        _, err = p.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        p.kill()
        _, err = p.communicate()
    return p.returncode, err, out


def attack_d7_term() -> tuple[bool, str]:
    rc, err, out = _signal_at_start(signal.SIGTERM)
    left = out.exists() or out.with_suffix(".json").exists()
    held = rc == 0 and not left and "0 A commanded" in err
    return held, f"SIGTERM with the link open and the log created: exit {rc}, files left: {left}; {_last(err, 80)}"


def attack_d7_hup() -> tuple[bool, str]:
    rc, err, out = _signal_at_start(signal.SIGHUP)
    held = rc == 0 and "reload: new demand" in err and out.exists()
    return held, f"SIGHUP during start-up: exit {rc}, kept as a reload: {'reload: new demand' in err}"


# -- D13 D15 D14 D19 -----------------------------------------------------------------
def _check_and_run(cfg_text: str, expect: str, **env: str) -> tuple[bool, str]:
    d = _tmp()
    cfg = d / "exp.yaml"
    cfg.write_text(cfg_text)
    res: dict[str, tuple[int | None, str, float]] = {}

    def go(cmd: str) -> None:
        res[cmd] = _mrctl(d, *(["check", str(cfg)] if cmd == "check" else _run_args(d, cfg)), **env)

    ts = [threading.Thread(target=go, args=(c,)) for c in ("check", "run")]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    held = all(rc == 2 and expect in err and "internal error" not in err for rc, err, _ in res.values())
    held = held and not (d / "r.csv").exists()
    return held, "; ".join(f"{c}: exit {rc} in {t:.1f} s" for c, (rc, _, t) in res.items()) + \
        f" ({_last(res['run'][1], 90)})"


def attack_d13() -> tuple[bool, str]:
    return _check_and_run(_law("exits_law"), "SystemExit(0) raised at import")


def attack_d15() -> tuple[bool, str]:
    return _check_and_run(_law("reset_raises_law"), "reset() raised RuntimeError")


def attack_d14() -> tuple[bool, str]:
    return _check_and_run(FIG5 + "stream: {url: 'udp://a..b:9870'}\n", "not a valid host name")


def attack_d19_import() -> tuple[bool, str]:
    return _check_and_run(_law("hangs_law"), "did not finish within")


def attack_d19_tap() -> tuple[bool, str]:
    d = _tmp()
    path = str(d / "mute.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(4)
    try:
        rc, err, t = _mrctl(d, "tap", "--socket", path, "-n", "5", timeout=20)
    finally:
        srv.close()
    return rc == 3 and t < 10, f"tap to a socket that accepts and never answers: exit {rc} after {t:.1f} s: {_last(err, 70)}"


ATTACKS: list[tuple[str, str, Callable[[], tuple[bool, str]]]] = [
    ("D1", "second daemon on an owned Modbus TCP device as ::ffff:127.0.0.1, unit 0, or localhost unit 17", attack_d1),
    ("D2", "SIGHUP with an alias bomb, a 2.6 MB file and 60 KB of bad values, then a good file", attack_d2_reload),
    ("D2", "mrctl check on an 860-byte alias bomb and a 2.6 MB config", attack_d2_check),
    ("D4", "SIGHUP with a plugin that hangs at import, then one raising SystemExit, then a good file", attack_d4),
    ("D5", "8 status scrapers back to back for a whole run, against a quiet run", attack_d5),
    ("D20", "another user's FIFO planted at the device's lock path", attack_d20_fifo),
    ("D20", "another user's mode-0000 file planted at the device's lock path", attack_d20_mode0),
    ("D7", "SIGTERM during start-up, the link open and the run log created", attack_d7_term),
    ("D7", "SIGHUP during start-up", attack_d7_hup),
    ("D13", "a plugin raising SystemExit at import (check and run)", attack_d13),
    ("D15", "a law whose reset() raises (check and run)", attack_d15),
    ("D14", "stream.url udp://a..b:9870 (check and run)", attack_d14),
    ("D19", "a plugin whose import never returns (check and run)", attack_d19_import),
    ("D19", "mrctl tap against a socket that accepts and never answers", attack_d19_tap),
]


def main(argv: list[str]) -> int:
    chosen = [a for a in ATTACKS if not argv or a[0] in argv]
    failed = 0
    for did, what, run in chosen:
        t0 = time.monotonic()
        try:
            held, detail = run()
        except Exception as exc:  # noqa: BLE001 - a broken attack is reported, not fatal
            held, detail = False, f"attack failed: {type(exc).__name__}: {exc}"
        failed += not held
        print(json.dumps({"id": did, "attack": what, "held": held, "detail": detail,
                          "seconds": round(time.monotonic() - t0, 1)}), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
