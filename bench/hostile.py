#!/usr/bin/env python3
"""The hostile table: mrctl attacked as a careless or hostile local user would.

Each attack runs the real command line (``python -m mrctl ...``) in a
fresh temporary directory, every child bounded (< 30 s), and says whether
mrctl held (the documented reaction: a clear message and exit 2, a refusal,
nothing destroyed, no traceback, no hang) with a short detail. The
registry format is shared with ``bench/hostile_loop.py`` (the loop's
attacks: ownership, reloads, scrapers, signals, plugins), whose rows are
included when it exists:

    ATTACKS: list[tuple[str, str, Callable[[], tuple[bool, str]]]]
    # (defect id, one-line attack, fn -> (held, short detail)); fn runs in its own temp dir (the cwd)

``--write-docs`` regenerates the table in docs/reliability.md.

    python bench/hostile.py [--only D6] [--write-docs]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import platform
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil_sim.testing.peers import ReplyingServer, free_port  # noqa: E402
from mrctl.util.gendoc import replace_block  # noqa: E402

DATE = time.strftime("%Y-%m-%d")
BEGIN, END = "<!-- BEGIN GENERATED: bench/hostile.py -->", "<!-- END GENERATED: bench/hostile.py -->"
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"
CHILD_TIMEOUT_S = 25.0
#: a child's address space: a read of /dev/zero fails fast instead of eating the box
CHILD_MEMORY_BYTES = 2 << 30

Attack = tuple[str, str, Callable[[], tuple[bool, str]]]


# -- helpers ---------------------------------------------------------------------------------
class Result:
    def __init__(self, code: int | None, out: str, err: str, secs: float) -> None:
        self.code, self.out, self.err, self.secs = code, out, err, secs

    @property
    def clean(self) -> bool:
        """No traceback, no internal error, no hang."""
        return self.code is not None and "Traceback" not in self.err and "internal error" not in self.err

    def line(self) -> str:
        """The last line on stderr, shortened (paths of the temp dir as WORK)."""
        lines = [ln for ln in self.err.strip().splitlines() if ln.strip()]
        last = lines[-1] if lines else "(nothing on stderr)"
        last = last.replace(os.getcwd(), "WORK")
        return (last[:150] + "…") if len(last) > 150 else last

    def say(self) -> str:
        if self.code is None:
            return f"hung: killed after {CHILD_TIMEOUT_S:g} s"
        return f"exit {self.code}: \"{self.line()}\""


def _limit() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (CHILD_MEMORY_BYTES, CHILD_MEMORY_BYTES))


def mrctl(*args: str, timeout: float = CHILD_TIMEOUT_S, env: dict | None = None, stdin: str | None = None
          ) -> Result:
    """``python -m mrctl ARGS`` in the cwd, bounded in time and memory."""
    t0 = time.monotonic()
    full_env = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    try:
        r = subprocess.run([sys.executable, "-m", "mrctl", *args], capture_output=True, text=True, timeout=timeout,
                           env=full_env, preexec_fn=_limit, input=stdin)
        return Result(r.returncode, r.stdout, r.stderr, time.monotonic() - t0)
    except subprocess.TimeoutExpired as exc:
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        return Result(None, "", err, time.monotonic() - t0)


def python(code: str, *args: str) -> Result:
    """A child Python (the same limits) for attacks that need an injected fault."""
    t0 = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                           timeout=CHILD_TIMEOUT_S, env={**os.environ, "PYTHONPATH": str(ROOT)}, preexec_fn=_limit)
        return Result(r.returncode, r.stdout, r.stderr, time.monotonic() - t0)
    except subprocess.TimeoutExpired:
        return Result(None, "", "", time.monotonic() - t0)


def refused(r: Result, *needles: str) -> tuple[bool, str]:
    """Held if exit 2, clean, and the message says each of ``needles``."""
    ok = r.code == 2 and r.clean and all(n in r.err for n in needles)
    return ok, r.say()


# a small broadband dataset: the outputs are checked before it is read; it fits in a few seconds
DS = """version: 1
protocol: broadband
input: voltage
columns: {time: time_s, displacement: {name: D_mm, scale: 0.001}, force: F_N, input: U_V}
sample_rate_hz: 1000
files: [rec.csv]
fit: {starts: 1, max_nfev: 20}
"""


def dataset(text: str = DS) -> Path:
    import math

    rows = ["time_s,D_mm,F_N,U_V"]
    for k in range(3000):
        t = k / 1000
        u = 2.0 if (k // 250) % 2 else 0.0
        rows.append(f"{t:.3f},{5 * math.sin(2 * math.pi * t):.5f},{300 * math.cos(2 * math.pi * t) + 50 * u:.3f},{u}")
    Path("rec.csv").write_text("\n".join(rows) + "\n")
    Path("ds.yaml").write_text(text)
    return Path("ds.yaml")


def sim_run(name: str = "run.csv") -> Path:
    r = mrctl("simulate", str(FIG5), "--duration", "0.3", "--out", name)
    if r.code != 0:
        raise RuntimeError(f"simulate for the attack failed: {r.say()}")
    return Path(name)


def serve(path: str, reply: bytes, times: int = 1) -> threading.Thread:
    """A fake status socket answering ``times`` connections with ``reply``."""
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(4)
    srv.settimeout(CHILD_TIMEOUT_S)

    def run() -> None:
        try:
            for _ in range(times):
                c, _a = srv.accept()
                with contextlib.suppress(OSError):
                    c.settimeout(2.0)
                    with contextlib.suppress(OSError):
                        c.recv(65536)
                    c.sendall(reply)
                c.close()
        except OSError:
            pass
        finally:
            srv.close()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


# -- D6: outputs ---------------------------------------------------------------------------
def d6_identify_symlink() -> tuple[bool, str]:
    dataset()
    Path("precious.txt").write_text("keep\n")
    os.symlink("precious.txt", "P.yaml")
    r = mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress")
    ok, d = refused(r, "symlink")
    kept = Path("precious.txt").read_text() == "keep\n"
    return ok and kept, d + f"; target untouched: {kept}"


def d6_identify_existing() -> tuple[bool, str]:
    dataset()
    Path("P.yaml").write_text("old\n")
    r = mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress")
    ok, d = refused(r, "--force")
    return ok and Path("P.yaml").read_text() == "old\n", d


def d6_identify_json() -> tuple[bool, str]:
    dataset()
    r = mrctl("identify", "ds.yaml", "--out", "x.json", "--no-progress")
    ok, d = refused(r)
    return ok and not Path("x.json").exists(), d + f"; x.json written: {Path('x.json').exists()}"


def d6_identify_over_input() -> tuple[bool, str]:
    dataset()
    before = Path("ds.yaml").read_text()
    r = mrctl("identify", "ds.yaml", "--out", "ds.yaml", "--force", "--no-progress")
    ok, d = refused(r, "an input")
    return ok and Path("ds.yaml").read_text() == before, d


def d6_report_symlink() -> tuple[bool, str]:
    run = sim_run()
    Path("precious.txt").write_text("keep\n")
    os.symlink("precious.txt", "fig.png")
    r = mrctl("report", str(run), "--out", "fig.png")
    ok, d = refused(r, "symlink")
    return ok and Path("precious.txt").read_text() == "keep\n", d


def d6_report_over_sidecar() -> tuple[bool, str]:
    run = sim_run()
    os.symlink("run.json", "side.svg")
    before = Path("run.json").read_bytes()
    r = mrctl("report", str(run), "--out", "side.svg", "--force")
    ok, d = refused(r, "an input")
    return ok and Path("run.json").read_bytes() == before, d


# -- D8, D18: sidecars ---------------------------------------------------------------------
def d8_same_stem() -> tuple[bool, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # the timing bounds open: which run gets the sidecar is judged, not a loaded machine's clock
    Path("fig5.yaml").write_text(FIG5.read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    procs = [subprocess.Popen([sys.executable, "-m", "mrctl", "run", "fig5.yaml", "--duration", "1", "--quiet",
                               "--out", name, "--status-socket", f"s{i}.sock"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True, env=env, preexec_fn=_limit)
             for i, name in enumerate(("run.csv", "run.tsv"))]
    codes, errs = [], []
    for p in procs:
        try:
            _out, err = p.communicate(timeout=CHILD_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            p.kill()
            _out, err = p.communicate()
        codes.append(p.returncode)
        errs.append(err)
    side = json.loads(Path("run.json").read_text()) if Path("run.json").exists() else {}
    ok = sorted(codes) == [0, 2] and side.get("complete") is True and all("Traceback" not in e for e in errs)
    loser = errs[codes.index(2)].strip().splitlines()[-1].replace(os.getcwd(), "WORK") if 2 in codes else "-"
    return ok, (f"exits {codes[0]}/{codes[1]}; the refused one: \"{loser[:110]}\"; "
                f"run.json complete: {side.get('complete')}")


def d18_simulate_full_disk() -> tuple[bool, str]:
    code = """
import errno, sys
import mrctl.runlog.files as files
real = files.create_log
class Full:
    def __init__(self, fh): self.fh = fh
    def write(self, b): raise OSError(errno.ENOSPC, "No space left on device")
    def fileno(self): return self.fh.fileno()
    def close(self): self.fh.close()
    def __enter__(self): return self
    def __exit__(self, *a): self.close()
files.create_log = lambda p, force=False, mkdir=False: Full(real(p, force, mkdir))
from mrctl.cli import main
sys.exit(main(sys.argv[1:]))
"""
    r = python(code, "simulate", str(FIG5), "--duration", "0.3", "--out", "run.csv")
    side = json.loads(Path("run.json").read_text()) if Path("run.json").exists() else None
    ok = r.code == 4 and r.clean and side is not None and side.get("exit_code") == 4 and side.get("complete") is False
    return ok, f"exit {r.code}; sidecar: " + (f"exit_code {side.get('exit_code')}, complete {side.get('complete')}"
                                             if side else "none") + " (ENOSPC injected at the CSV's write)"


# -- D9: degenerate datasets -------------------------------------------------------------
def _degenerate(change: dict[str, str], needle: str, setup: Callable[[], None] | None = None
                ) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        text = DS
        for a, b in change.items():
            text = text.replace(a, b)
        dataset(text)
        if setup:
            setup()
        r = mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress")
        ok, d = refused(r, needle)
        return ok and not Path("P.yaml").exists() and not Path("P.json").exists(), d

    return fn


def _flat() -> None:
    lines = Path("rec.csv").read_text().splitlines()
    Path("flat.csv").write_text("\n".join([lines[0]] + [",".join(ln.split(",")[:2] + ["7.0"] + ln.split(",")[3:])
                                                        for ln in lines[1:]]) + "\n")


# -- D11: unbounded reads --------------------------------------------------------------------
def d11_sidecar_dev_zero() -> tuple[bool, str]:
    run = sim_run()
    os.unlink("run.json")
    os.symlink("/dev/zero", "run.json")
    r = mrctl("report", str(run), "--out", "fig.png")
    return r.code == 0 and r.clean and r.secs < 20, f"exit {r.code} in {r.secs:.1f} s (the sidecar ignored)"


def d11_data_dev_zero() -> tuple[bool, str]:
    dataset(DS.replace("rec.csv", "/dev/zero"))
    return refused(mrctl("identify", "ds.yaml", "--out", "P.yaml", "--allow-outside-paths", "--no-progress"),
                   "character device")


def d11_manifest_fifo() -> tuple[bool, str]:
    os.mkfifo("m.csv")
    Path("ds.yaml").write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, force: F}\n"
                               "model: {stiffness: false}\nmanifest: {path: m.csv, file: file, level: level}\n")
    return refused(mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress"), "FIFO")


# -- D16: containment and echo ------------------------------------------------------------
def d16_etc_passwd() -> tuple[bool, str]:
    dataset(DS.replace("rec.csv", "/etc/passwd"))
    r = mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress")
    ok, d = refused(r, "outside")
    return ok and "root:" not in r.err, d


def d16_etc_passwd_allowed() -> tuple[bool, str]:
    dataset(DS.replace("rec.csv", "/etc/passwd"))
    r = mrctl("identify", "ds.yaml", "--out", "P.yaml", "--allow-outside-paths", "--no-progress")
    return r.code == 2 and r.clean and "root:" not in r.err, r.say() + "; contents echoed: " + str("root:" in r.err)


def d16_manifest_row_outside() -> tuple[bool, str]:
    Path("m.csv").write_text("file,level\n/etc/passwd,0.5\n")
    Path("ds.yaml").write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, force: F}\n"
                               "model: {stiffness: false}\nmanifest: {path: m.csv, file: file, level: level}\n")
    r = mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress")
    ok, d = refused(r, "outside")
    return ok and "root:" not in r.err, d


def d16_demand_file() -> tuple[bool, str]:
    text = FIG5.read_text().replace("demand: {type: viscous, c_des: 500.0}", "demand: {type: file, path: /etc/passwd}")
    Path("x.yaml").write_text(text)
    r = mrctl("check", "x.yaml")
    ok, d = refused(r, "outside")
    return ok and "root:" not in r.err, d


def d16_demand_file_echo() -> tuple[bool, str]:
    text = FIG5.read_text().replace("demand: {type: viscous, c_des: 500.0}", "demand: {type: file, path: /etc/passwd}")
    Path("x.yaml").write_text(text)
    r = mrctl("check", "x.yaml", "--allow-outside-paths")
    return r.code == 2 and r.clean and "root:" not in r.err, r.say()


# -- D10: deep nesting -----------------------------------------------------------------------
def d10_config() -> tuple[bool, str]:
    Path("deep.yaml").write_text("[" * 60_000 + "\n")  # under the 64 KiB cap: the parser meets it
    return refused(mrctl("check", "deep.yaml"), "nested too deeply")


def d10_dataset() -> tuple[bool, str]:
    Path("deep.yaml").write_text("version: 1\nfiles: " + "[" * 60_000 + "\n")
    return refused(mrctl("identify", "deep.yaml", "--out", "P.yaml"), "nested too deeply")


def d10_sidecar() -> tuple[bool, str]:
    run = sim_run()
    Path("run.json").write_text("[" * 200_000)
    r = mrctl("report", str(run), "--out", "fig.png")
    return r.code == 0 and r.clean, f"exit {r.code} (the sidecar ignored)"


def d10_status_reply() -> tuple[bool, str]:
    serve(str(Path("s.sock").resolve()), b"[" * 200_000)
    r = mrctl("status", "--socket", "s.sock")
    return r.code == 3 and r.clean and "not a status reply" in r.err, r.say()  # no mrctl answering: 3


def d10_tap_reply() -> tuple[bool, str]:
    serve(str(Path("t.sock").resolve()), b"[" * 60_000 + b"\n")
    r = mrctl("tap", "--socket", "t.sock", "-n", "1")
    return r.code == 3 and r.clean and "not a tap reply" in r.err, r.say()


def d10_exporter() -> tuple[bool, str]:
    if importlib.util.find_spec("prometheus_client") is None:
        return True, "not run: prometheus_client not installed"
    import urllib.request

    serve(str(Path("s.sock").resolve()), b"[" * 200_000)
    port = free_port()
    p = subprocess.Popen([sys.executable, "-m", "mrctl", "exporter", "--listen", f"127.0.0.1:{port}", "--socket",
                          "s.sock"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, preexec_fn=_limit)
    try:
        body, status = "", None
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
                    status, body = resp.status, resp.read().decode()
                break
            except OSError as exc:
                if getattr(exc, "code", None):
                    status = exc.code
                    break
                time.sleep(0.2)
    finally:
        p.terminate()
        try:
            _o, err = p.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            _o, err = p.communicate()
    up = [ln for ln in body.splitlines() if ln.startswith("mrctl_up")]
    ok = status == 200 and "Traceback" not in err and bool(up)
    return ok, f"HTTP {status}; {up[0] if up else 'no mrctl_up'}; traceback: {'Traceback' in err}"


# -- D17: messages -------------------------------------------------------------------------
def d17_status_dir_file() -> tuple[bool, str]:
    Path(f"mrctl-{os.getuid()}").write_text("")
    r = mrctl("status", env={"TMPDIR": os.getcwd(), "RUNTIME_DIRECTORY": ""})
    return r.code == 3 and r.clean and "a regular file" in r.err, r.say()


def d17_fifo_data() -> tuple[bool, str]:
    dataset(DS.replace("rec.csv", "fifo.csv"))
    os.mkfifo("fifo.csv")
    r = mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress")
    ok, d = refused(r, "a FIFO")
    return ok and "no such file" not in r.err, d


def d17_manifest_nan() -> tuple[bool, str]:
    Path("r.csv").write_text("t,x,F\n0,0,0\n0.01,1,1\n0.02,0,2\n")
    Path("m.csv").write_text("file,level\nr.csv,nan\n")
    Path("ds.yaml").write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, force: F}\n"
                               "model: {stiffness: false}\nmanifest: {path: m.csv, file: file, level: level}\n")
    return refused(mrctl("identify", "ds.yaml", "--out", "P.yaml", "--no-progress"), "not a finite number")


def d17_exporter_ipv6() -> tuple[bool, str]:
    if importlib.util.find_spec("prometheus_client") is None:
        return True, "not run: prometheus_client not installed"
    if not socket.has_ipv6:
        return True, "not run: no IPv6 on this host"
    p = subprocess.Popen([sys.executable, "-m", "mrctl", "exporter", "--listen", f"[::1]:{free_port()}", "--socket",
                          "s.sock"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, preexec_fn=_limit)
    line = ""
    try:
        assert p.stdout is not None
        line = p.stdout.readline().strip()
    finally:
        p.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.communicate(timeout=10)
        if p.poll() is None:
            p.kill()
            p.communicate()
    if not line:
        return True, "not run: cannot listen on [::1] here"
    return "http://[::1]:" in line, line[:120]


def d17_status_pipe() -> tuple[bool, str]:
    serve(str(Path("s.sock").resolve()), json.dumps({"state": "RUN", "pad": "x" * 300_000}).encode())
    p = subprocess.Popen([sys.executable, "-m", "mrctl", "status", "--socket", "s.sock", "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()  # `| true`
    try:
        code = p.wait(timeout=CHILD_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        p.kill()
        code = None
    err = p.stderr.read().decode(errors="replace")
    ok = code == 0 and "Broken pipe" not in err and "Traceback" not in err
    return ok, f"exit {code}, stderr {err.strip()[:80]!r}"


def d17_empty_out() -> tuple[bool, str]:
    return refused(mrctl("run", str(FIG5), "--duration", "0.2", "--out", "", "--quiet"), "empty")


def d17_empty_stream() -> tuple[bool, str]:
    return refused(mrctl("run", str(FIG5), "--duration", "0.2", "--stream", "", "--quiet"), "empty")


# -- the first hardening round (docs above): still held ---------------------------------------
def r1_log_symlink() -> tuple[bool, str]:
    Path("precious.txt").write_text("keep\n")
    os.symlink("precious.txt", "link.csv")
    r = mrctl("run", str(FIG5), "--duration", "0.2", "--out", "link.csv", "--quiet")
    ok, d = refused(r, "symlink")
    return ok and Path("precious.txt").read_text() == "keep\n", d


def r1_log_existing() -> tuple[bool, str]:
    Path("run.csv").write_text("old\n")
    r = mrctl("simulate", str(FIG5), "--duration", "0.2", "--out", "run.csv")
    ok, d = refused(r, "--force")
    return ok and Path("run.csv").read_text() == "old\n", d


def r1_excitation_dev_zero() -> tuple[bool, str]:
    text = FIG5.read_text().replace("excitation: {type: sine, amplitude_m: 0.010, frequency_hz: 1.0}",
                                    "excitation: {type: file, path: /dev/zero}")
    Path("x.yaml").write_text(text)
    r = mrctl("check", "x.yaml", "--allow-outside-paths")
    return r.code == 2 and r.clean and "/dev/zero" in r.err, r.say()


# -- issue 33: the third probe (sweep, calibrate, examples, the files configs name) ---------------
SECRET = "/etc/shadow" if os.access("/etc/shadow", os.R_OK) else "/etc/passwd"


def _secret_echoed(text: str) -> bool:
    """A line of the secret file in ``text`` (its first field before ':' is a user name)."""
    return any(ln.split(":", 1)[0] + ":" in text for ln in Path(SECRET).read_text().splitlines()[:3] if ":" in ln)


def _fig5_with(**changes: str) -> Path:
    text = FIG5.read_text()
    for key, value in changes.items():
        text = text.replace("parameters: table1", f"parameters: table1\n{key}: {value}") if key != "parameters" \
            else text.replace("parameters: table1", f"parameters: {value}")
    Path("x.yaml").write_text(text)
    return Path("x.yaml")


def _file_key(key: str, allow: bool) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        if key == "plant.model.parameters":
            model = f"model: {{type: bouc-wen, parameters: {SECRET}}}"
            Path("x.yaml").write_text(FIG5.read_text().replace("plant: {driver_tau_s: 0.0}",
                                                               f"plant: {{driver_tau_s: 0.0, {model}}}"))
        else:
            _fig5_with(**{key: SECRET})
        r = mrctl("check", "x.yaml", *(["--allow-outside-paths"] if allow else []))
        echoed = _secret_echoed(r.err)
        ok = r.code == 2 and r.clean and not echoed and ("outside" in r.err or allow)
        return ok, r.say() + f"; a line of {SECRET} echoed: {echoed}"

    return fn


def _sweep_base(duration: float = 0.2) -> None:
    Path("base.yaml").write_text((ROOT / "config" / "experiments" / "fig5_robust.yaml").read_text()
                                 .replace("duration_s: 4.0", f"duration_s: {duration}"))


def h1_sweep_base() -> tuple[bool, str]:
    Path("s.yaml").write_text(f"base: {SECRET}\n")
    r = mrctl("check", "s.yaml")
    r2 = mrctl("check", "s.yaml", "--allow-outside-paths")
    echoed = _secret_echoed(r.err + r2.err)
    return refused(r, "outside")[0] and r2.code == 2 and r2.clean and not echoed, \
        r.say() + f"; with --allow-outside-paths exit {r2.code}, a line echoed: {echoed}"


def h1_sweep_grid() -> tuple[bool, str]:
    _sweep_base()
    Path("s.yaml").write_text(f"base: base.yaml\ngrid:\n  plant.parameters: [table1, {SECRET}]\n")
    r = mrctl("sweep", "s.yaml", "--out", "r.csv", "--allow-outside-paths", "--workers", "1", "--no-progress")
    table = Path("r.csv").read_text() if Path("r.csv").exists() else ""
    echoed = _secret_echoed(table + r.err)
    return r.code == 0 and r.clean and "invalid" in table and not echoed, \
        f"exit {r.code}; the point's row is invalid: {'invalid' in table}; a line of {SECRET} in the table: {echoed}"


def h1_replay_sidecar() -> tuple[bool, str]:
    run = sim_run()
    side = json.loads(Path("run.json").read_text())
    side["config"]["parameters"], side["config_file"] = SECRET, str(Path(SECRET).parent / "x.yaml")
    Path("run.json").write_text(json.dumps(side))
    r = mrctl("simulate", "--replay", str(run))
    ok, d = refused(r, "outside")
    return ok and not _secret_echoed(r.err), d


def h2_two_sweeps() -> tuple[bool, str]:
    _sweep_base(duration=1.0)
    Path("s.yaml").write_text("base: base.yaml\nrandom: {n: 200, plant.parameters.F0: {factor_uniform: [0.8, 1.2]}}\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    first = subprocess.Popen([sys.executable, "-m", "mrctl", "sweep", "s.yaml", "--out", "r.csv", "--workers", "1",
                              "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                             preexec_fn=_limit)
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (not Path("r.csv").exists() or Path("r.csv").read_text().count("\n") < 2):
            time.sleep(0.05)
        r = mrctl("sweep", "s.yaml", "--out", "r.csv", "--no-progress")
    finally:
        first.kill()
        first.wait()
    ok = r.code == 3 and r.clean and f"pid {first.pid}" in r.err
    return ok, r.say().replace(str(first.pid), "PID")


def h2_duplicates() -> tuple[bool, str]:
    _sweep_base()
    Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250, 500, 750]}\n")
    r = mrctl("sweep", "s.yaml", "--out", "r.csv", "--workers", "1", "--no-progress")
    lines = Path("r.csv").read_text().splitlines()
    with open("r.csv", "a") as fh:  # what two sweeps on one table left behind
        fh.write("\n".join(lines[1:] * 2) + "\n")
    Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250, 500, 750, 1000]}\n")
    r = mrctl("sweep", "s.yaml", "--out", "r.csv", "--workers", "1", "--no-progress")
    points = [ln.split(",")[0] for ln in Path("r.csv").read_text().splitlines()[1:]]
    return r.code == 0 and points == ["0", "1", "2", "3"], f"exit {r.code}; 3 points written 3 times, resumed: " \
                                                           f"points {','.join(points)}"


def h3_out_fifo() -> tuple[bool, str]:
    _sweep_base()
    Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250]}\n")
    os.mkfifo("r.csv")
    return refused(mrctl("sweep", "s.yaml", "--out", "r.csv"), "FIFO")


def _scheduler(reply: bytes | None, needle: str) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        if importlib.util.find_spec("distributed") is None:
            return True, "not run: dask.distributed not installed"
        _sweep_base()
        Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250]}\n")
        with ReplyingServer(reply) as srv:
            r = mrctl("sweep", "s.yaml", "--out", "r.csv", "--scheduler", srv.address)
        return r.code == 3 and r.clean and needle in r.err, r.say() + f" after {r.secs:.1f} s"

    return fn


def h4_cap() -> tuple[bool, str]:
    from mrctl.sweep.spec import MAX_POINTS

    _sweep_base()
    Path("s.yaml").write_text(f"base: base.yaml\ngrid: {{inverse.law: [smooth, closed]}}\n"
                              f"random: {{n: {MAX_POINTS // 2}, plant.parameters.F0: {{factor_uniform: [0.8, 1.2]}}}}\n")
    c = mrctl("check", "s.yaml")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "mrctl", "sweep", "s.yaml", "--out", "r.csv", "--workers", "1",
                          "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                         preexec_fn=_limit)
    deadline = t0 + 20
    while time.monotonic() < deadline and (not Path("r.csv").exists() or Path("r.csv").read_text().count("\n") < 4):
        time.sleep(0.05)
    first = time.monotonic() - t0
    p.send_signal(signal.SIGINT)
    _pid, status, usage = os.wait4(p.pid, 0)
    code = os.waitstatus_to_exitcode(status)
    rss = usage.ru_maxrss / 1024
    ok = c.code == 0 and c.secs < 20 and code == 0 and first < 20 and rss < 300  # Ctrl-C: 0, the table valid
    return ok, (f"check: exit {c.code} in {c.secs:.1f} s; sweep of {MAX_POINTS} points: 3 rows after {first:.1f} s, "
                f"Ctrl-C exit {code}, max RSS {rss:.0f} MB")


def h5_calibrate_over_config() -> tuple[bool, str]:
    Path("c.yaml").write_text((ROOT / "config" / "experiments" / "labjack_t7.yaml").read_text())
    before = Path("c.yaml").read_bytes()
    r = mrctl("calibrate", "c.yaml", "--out", "c.yaml", "--force")
    ok, d = refused(r, "an input")
    return ok and Path("c.yaml").read_bytes() == before, d


def h5_simulate_over_series() -> tuple[bool, str]:
    sim_run("e.csv")
    Path("x.yaml").write_text(FIG5.read_text().replace(
        "excitation: {type: sine, amplitude_m: 0.010, frequency_hz: 1.0}", "excitation: {type: file, path: e.csv}"))
    before = Path("e.csv").read_bytes()
    r = mrctl("simulate", "x.yaml", "--out", "e.csv", "--force")
    ok, d = refused(r, "an input")
    return ok and Path("e.csv").read_bytes() == before, d


def h6_examples(force: bool) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        Path("elsewhere").mkdir()
        Path("ex").mkdir()
        os.symlink("../elsewhere", "ex/config")
        r = mrctl("examples", "ex", *(["--force"] if force else []))
        ok, d = refused(r, "symlink")
        written = sorted(p.name for p in Path("elsewhere").rglob("*"))
        return ok and not written, d + f"; files in the link's target: {len(written)}"

    return fn


def h7_corrupt_parquet(command: str) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        if importlib.util.find_spec("pyarrow") is None:
            return True, "not run: pyarrow not installed"
        _sweep_base()
        Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250]}\n")
        Path("r.parquet").write_bytes(b"PAR1" + os.urandom(4000) + b"PAR1")
        args = ("sweep", "s.yaml", "--out", "r.parquet") if command == "sweep" else ("report", "r.parquet", "--out",
                                                                                     "f.png")
        return refused(mrctl(*args), "Parquet")

    return fn


def h7_hand_edited(edit: str) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        _sweep_base()
        Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250, 500]}\n")
        mrctl("sweep", "s.yaml", "--out", "r.csv", "--workers", "1", "--no-progress")
        raw = Path("r.csv").read_bytes()
        raw = raw.replace(b"\n0,", b"\nzero,", 1) if edit == "point" else raw + b"1,\xff\xfe,caf\xe9\n"
        Path("r.csv").write_bytes(raw)
        Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250, 500, 750]}\n")
        r = mrctl("sweep", "s.yaml", "--out", "r.csv", "--no-progress")
        ok, d = refused(r, "line 2" if edit == "point" else "line 4")
        return ok and Path("r.csv").read_bytes() == raw, d

    return fn


def h8_killed_sweep() -> tuple[bool, str]:
    _sweep_base(duration=1.0)
    Path("s.yaml").write_text("base: base.yaml\nrandom: {n: 200, plant.parameters.F0: {factor_uniform: [0.8, 1.2]}}\n")
    p = subprocess.Popen([sys.executable, "-m", "mrctl", "sweep", "s.yaml", "--out", "r.csv", "--workers", "2",
                          "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and (not Path("r.csv").exists() or Path("r.csv").read_text().count("\n") < 2):
        time.sleep(0.05)
    workers = [int(d.name) for d in Path("/proc").iterdir() if d.name.isdigit() and _ppid(d) == p.pid]
    p.kill()
    p.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.05)
    alive = [w for w in workers if _alive(w)]
    r = mrctl("sweep", "s.yaml", "--out", "r.csv", "--no-progress", timeout=CHILD_TIMEOUT_S)
    ok = len(workers) == 2 and not alive and r.code in (0, None) and "in use" not in r.err
    return ok, (f"{len(workers)} workers, alive after the SIGKILL: {len(alive)}; the next sweep on the table: "
                + ("still running (not refused)" if r.code is None else f"exit {r.code}"))


def _ppid(d: Path) -> int | None:
    try:
        return int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def h8_foreign_parquet() -> tuple[bool, str]:
    if importlib.util.find_spec("pyarrow") is None:
        return True, "not run: pyarrow not installed"
    import pyarrow as pa
    import pyarrow.parquet as pq

    _sweep_base()
    Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250]}\n")
    pq.write_table(pa.table({"a": [1]}), "r.parquet")
    ok, d = refused(mrctl("sweep", "s.yaml", "--out", "r.parquet"), "another sweep")
    journal = Path("r.parquet.partial.csv").exists()
    return ok and not journal, d + f"; journal left: {journal}"


def h8_out_special(out: str) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        _sweep_base()
        Path("s.yaml").write_text("base: base.yaml\ngrid: {demand.c_des: [250]}\n")
        if out == "dir":
            Path("r.csv").mkdir()
        r = mrctl("sweep", "s.yaml", "--out", "r.csv" if out == "dir" else "/dev/null")
        return refused(r, "not a regular file")

    return fn


def h8_base_special(base: str) -> Callable[[], tuple[bool, str]]:
    def fn() -> tuple[bool, str]:
        if base == "fifo":
            os.mkfifo("b.yaml")
        Path("s.yaml").write_text(f"base: {'b.yaml' if base == 'fifo' else '/dev/zero'}\n")
        r = mrctl("check", "s.yaml", "--allow-outside-paths")
        ok, d = refused(r, "not a regular file")
        return ok and "no such file" not in r.err, d

    return fn


def h8_force_over_device() -> tuple[bool, str]:
    """Never /dev/null itself: a clone of it (root), or a FIFO, in the attack's directory."""
    name = "null"
    try:
        os.mknod(name, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except PermissionError:
        os.mkfifo(name)
    before = os.lstat(name)
    r = mrctl("run", str(FIG5), "--out", name, "--force", "--duration", "0.2", "--quiet")
    after = os.lstat(name)
    ok, d = refused(r, "not a regular file")
    same = (after.st_ino, after.st_mode) == (before.st_ino, before.st_mode)
    return ok and same and not Path("null.json").exists(), d + f"; the device node untouched: {same}"


ATTACKS: list[Attack] = [
    ("D6", "`identify --out P.yaml` where P.yaml is a symlink to another file", d6_identify_symlink),
    ("D6", "`identify --out P.yaml` over an existing file", d6_identify_existing),
    ("D6", "`identify ds.yaml --out x.json` (the summary's own name)", d6_identify_json),
    ("D6", "`identify ds.yaml --out ds.yaml --force` (the input)", d6_identify_over_input),
    ("D6", "`report --out fig.png` where fig.png is a symlink", d6_report_symlink),
    ("D6", "`report run.csv --out side.svg --force`, side.svg a symlink to run.json", d6_report_over_sidecar),
    ("D8", "`run --out run.csv` and `run --out run.tsv` at once (one sidecar name)", d8_same_stem),
    ("D18", "`simulate --out run.csv` on a full disk", d18_simulate_full_disk),
    ("D9", "dataset with zero-variance force", _degenerate({"rec.csv": "flat.csv"}, "is constant", _flat)),
    ("D9", "dataset with `sample_rate_hz: 1e300`", _degenerate({"sample_rate_hz: 1000": "sample_rate_hz: 1e300"},
                                                               "sample_rate_hz")),
    ("D9", "dataset with `force: {scale: 1e308}`", _degenerate({"force: F_N": "force: {name: F_N, scale: 1e308}"},
                                                              "columns.force.scale")),
    ("D9", "dataset with `delimiter: ''`", _degenerate({"fit: {": "format: {delimiter: ''}\nfit: {"},
                                                       "format.delimiter")),
    ("D9", "an empty file named .mat", _degenerate({"rec.csv": "e.mat"}, "empty file",
                                                   lambda: Path("e.mat").write_bytes(b""))),
    ("D9", "a text file named .mat", _degenerate({"rec.csv": "t.mat"}, "not a readable MATLAB",
                                                 lambda: Path("t.mat").write_text("a,b\n1,2\n"))),
    ("D11", "report with the sidecar a symlink to /dev/zero", d11_sidecar_dev_zero),
    ("D11", "dataset file /dev/zero (with --allow-outside-paths)", d11_data_dev_zero),
    ("D11", "dataset manifest a FIFO", d11_manifest_fifo),
    ("D16", "dataset `files: [/etc/passwd]`", d16_etc_passwd),
    ("D16", "the same with --allow-outside-paths: contents not echoed", d16_etc_passwd_allowed),
    ("D16", "manifest row naming /etc/passwd", d16_manifest_row_outside),
    ("D16", "`demand: {type: file, path: /etc/passwd}`", d16_demand_file),
    ("D16", "the same with --allow-outside-paths: contents not echoed", d16_demand_file_echo),
    ("D10", "config of 60 000 `[` (under the 64 KiB cap)", d10_config),
    ("D10", "dataset with 60 000 `[` (under the 64 KiB cap)", d10_dataset),
    ("D10", "sidecar of 200 000 `[` (report)", d10_sidecar),
    ("D10", "status reply of 200 000 `[`", d10_status_reply),
    ("D10", "tap reply of 60 000 `[`", d10_tap_reply),
    ("D10", "exporter scraping a status reply of 200 000 `[`", d10_exporter),
    ("D17", "a regular file where the per-user status directory goes", d17_status_dir_file),
    ("D17", "dataset file a FIFO", d17_fifo_data),
    ("D17", "manifest level `nan`", d17_manifest_nan),
    ("D17", "`exporter --listen [::1]:PORT`: the URL it prints", d17_exporter_ipv6),
    ("D17", "`mrctl status --json | true`", d17_status_pipe),
    ("D17", "`run --out ''`", d17_empty_out),
    ("D17", "`run --stream ''`", d17_empty_stream),
    ("round 1", "`run --out link.csv`, a symlink to another file", r1_log_symlink),
    ("round 1", "`simulate --out run.csv` over an existing log", r1_log_existing),
    ("round 1", "`excitation: {type: file, path: /dev/zero}` (with --allow-outside-paths)", r1_excitation_dev_zero),
    ("III.1", "`parameters: /etc/shadow` (check)", _file_key("parameters", False)),
    ("III.1", "the same with --allow-outside-paths: no line of it echoed", _file_key("parameters", True)),
    ("III.1", "`calibration: /etc/shadow` (check, --allow-outside-paths)", _file_key("calibration", True)),
    ("III.1", "`plant.model.parameters: /etc/shadow` (check)", _file_key("plant.model.parameters", False)),
    ("III.1", "a sweep's `base: /etc/shadow` (check, and with --allow-outside-paths)", h1_sweep_base),
    ("III.1", "a sweep's grid value `plant.parameters: /etc/shadow` (--allow-outside-paths): the table's error column",
     h1_sweep_grid),
    ("III.1", "a replay sidecar whose config names /etc/shadow and claims to come from /etc", h1_replay_sidecar),
    ("III.2", "a second `mrctl sweep` on a table another is writing", h2_two_sweeps),
    ("III.2", "a table holding every point three times, resumed", h2_duplicates),
    ("III.3", "`sweep --out r.csv`, r.csv a FIFO", h3_out_fifo),
    ("III.3", "`--scheduler` at a server that accepts and never answers", _scheduler(None, "no answer within")),
    ("III.4", "`random: {n: 5000000}` x 2 laws (the cap): check, then the sweep's first rows", h4_cap),
    ("III.5", "`calibrate c.yaml --out c.yaml --force`", h5_calibrate_over_config),
    ("III.5", "`simulate x.yaml --out e.csv --force`, e.csv the excitation x.yaml names", h5_simulate_over_series),
    ("III.6", "`examples ex`, ex/config a symlink to another folder", h6_examples(False)),
    ("III.6", "the same with --force", h6_examples(True)),
    ("III.7", "`--scheduler` at a server sending random bytes", _scheduler(os.urandom(4096), "not a Dask scheduler")),
    ("III.7", "`--scheduler` at an HTTP server", _scheduler(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n"
                                                         b"Connection: close\r\n\r\n", "not a Dask scheduler")),
    ("III.7", "`--scheduler` at a server sending a frame of 2^62 bytes",
     _scheduler((3).to_bytes(8, "little") + (1 << 62).to_bytes(8, "little") + bytes(64), "not a Dask scheduler")),
    ("III.7", "a corrupt `.parquet` as `sweep --out`", h7_corrupt_parquet("sweep")),
    ("III.7", "a corrupt `.parquet` as `report` input", h7_corrupt_parquet("report")),
    ("III.7", "a results table with a non-integer `point`, resumed", h7_hand_edited("point")),
    ("III.7", "a results table with a non-UTF-8 line, resumed", h7_hand_edited("utf8")),
    ("III.8", "SIGKILL of a sweep on 2 workers, then the next sweep on its table", h8_killed_sweep),
    ("III.8", "`sweep --out r.parquet`, r.parquet another program's table", h8_foreign_parquet),
    ("III.8", "`sweep --out DIR`", h8_out_special("dir")),
    ("III.8", "`sweep --out /dev/null`", h8_out_special("null")),
    ("III.8", "a sweep's `base:` a FIFO", h8_base_special("fifo")),
    ("III.8", "a sweep's `base: /dev/zero` (with --allow-outside-paths)", h8_base_special("zero")),
    ("III.8", "`run --out null --force`, null a device node (a clone of /dev/null)", h8_force_over_device),
]


def all_attacks() -> list[Attack]:
    """Ours, then bench/hostile_loop.py's (if it exists) in its own order."""
    attacks = list(ATTACKS)
    loop = Path(__file__).with_name("hostile_loop.py")
    if loop.exists():
        sys.path.insert(0, str(loop.parent))  # it may import this module's helpers (import hostile)
        spec = importlib.util.spec_from_file_location("hostile_loop", loop)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        attacks += list(mod.ATTACKS)
    return attacks


def run_one(fn: Callable[[], tuple[bool, str]]) -> tuple[bool, str, float]:
    """``fn`` in a fresh temp dir (its cwd); an exception is a FAILED row, not a crash."""
    here = os.getcwd()
    d = tempfile.mkdtemp(prefix="mrctl-hostile-")
    t0 = time.monotonic()
    try:
        os.chdir(d)
        held, detail = fn()
    except Exception as exc:  # noqa: BLE001 - the table shows it
        held, detail = False, f"the attack itself failed: {type(exc).__name__}: {exc}"[:200]
    finally:
        os.chdir(here)
        shutil.rmtree(d, ignore_errors=True)
    return bool(held), detail, time.monotonic() - t0


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="only the attacks of this defect id (D6, D17, round 1, ...)")
    ap.add_argument("--write-docs", action="store_true", help="regenerate the table in docs/reliability.md")
    a = ap.parse_args()
    attacks = [x for x in all_attacks() if a.only is None or x[0] == a.only]
    t0 = time.monotonic()
    rows, failed, slow = [], 0, []
    for defect, attack, fn in attacks:
        held, detail, secs = run_one(fn)
        failed += not held
        if secs > 30:
            slow.append(f"{defect} {attack}: {secs:.0f} s")
        print(f"{'held  ' if held else 'FAILED'} {defect:7s} {attack} ({secs:.1f} s): {detail}", flush=True)
        rows.append(f"| {defect} | {_cell(attack)} | {'held' if held else '**FAILED**'} | {_cell(detail)} |")
    total = time.monotonic() - t0
    head = (f"Generated by `python bench/hostile.py --write-docs` on {DATE} ({platform.node()}, Python "
            f"{platform.python_version()}, {os.cpu_count()} CPUs{', root' if os.getuid() == 0 else ''}); "
            f"{len(rows)} attacks, {len(rows) - failed} held, {failed} failed; {total:.0f} s in total.")
    text = "\n".join([head, "", "| defect | attack | held / FAILED | detail |", "|---|---|---|---|", *rows])
    if slow:
        text += "\n\nAttacks over their 30 s bound: " + "; ".join(slow)
    print(f"{len(rows)} attacks, {failed} failed, {total:.0f} s")
    if a.write_docs:
        replace_block(ROOT / "docs" / "reliability.md", BEGIN, END, text)
        print("updated docs/reliability.md", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
