#!/usr/bin/env python3
"""Daemon-level faults, measured, and their table in docs/reliability.md.

The link faults are bench/faults.py's table; these are the faults around the
loop that a probe of ``mrctl run`` as a careless or hostile local user found:
a second daemon on a device in use (Modbus TCP and serial, against hil_sim),
a disk that fills up mid-run (a 256 KiB tmpfs; needs root to mount), and a
symlink or an existing file at the log path. Each scenario runs the real
daemon as a process (hil_sim/testing/daemon_faults.py says exactly how) and
this rewrites the second generated block of docs/reliability.md.

    python bench/daemon_faults.py              # ~1 min, rewrites docs/reliability.md
    python bench/daemon_faults.py --no-docs --json runs/daemon_faults.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil_sim.testing.daemon_faults import disk_full, log_path_symlink, ownership  # noqa: E402
from mrctl.util.gendoc import replace_block  # noqa: E402

DOC = ROOT / "docs" / "reliability.md"
BEGIN = "<!-- BEGIN GENERATED: bench/daemon_faults.py -->"
END = "<!-- END GENERATED: bench/daemon_faults.py -->"


def _msg(lines: list[str], limit: int = 150) -> str:
    text = "; ".join(m.removeprefix("mrctl: ") for m in lines) or "(none)"
    text = re.sub(r"/\S*?mrctl-daemon-faults-[^/]+/", "WORK/", text)  # the run's temp directory
    text = text.replace("|", "/")
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _owner_row(r: dict[str, Any]) -> tuple[str, str, str]:
    if not r.get("a_in_loop"):
        return ("invalid: the first daemon did not reach its loop", "-", "retry")
    named = ("names the device and the owner's pid" if r["b_names_owner_pid"] and r["b_names_device"]
             else "does NOT name the device and the owner's pid")
    measured = (f"second: exit {r['b_exit']} after {r['b_wall_s']} s, {named}, log written: "
                f"{'yes' if r['b_wrote_log'] else 'no'} (\"{_msg(r['b_messages'], 110)}\"); first: exit "
                f"{r['a_exit']}, {r['a_link_errors_while_b']} link errors while the second started (while a "
                f"control daemon started on a device that is not there: {r['a_link_errors_while_control']}), faults "
                f"entered in its whole run {r['a_faults_entered']}")
    ok = (r["b_exit"] == 3 and r["b_names_owner_pid"] and r["b_names_device"] and not r["b_wrote_log"]
          and r["a_exit"] == 0)
    return measured, f"{r['a_exit']} / {r['b_exit']}", "none" if ok else "**departs**"


def _disk_row(r: dict[str, Any]) -> tuple[str, str, str]:
    if r.get("skipped"):
        return (f"not run: {r['skipped']}", "-", "-")
    s = r["sidecar"]
    warned = any("losing rows" in m for m in r["messages"])
    measured = (f"{'warned while running' if warned else 'NOT warned while running'}; sidecar: exit_code "
                f"{s['exit_code']}, {s['rows_written']} rows written, {s['dropped_rows']} lost from tick "
                f"{s['lost_first_tick']} of {s['ticks']} (loop ticks {r['loop_ticks']}), error "
                f"\"{(s['error'] or '').split(' (writing')[0]}\"; exit current {r['exit_current_A']} A; "
                f"traceback: {'yes' if r['traceback'] else 'no'}")
    ok = (r["exit"] == 4 and warned and s["exit_code"] == 4 and s["dropped_rows"] and r["exit_current_A"] == 0.0
          and s["rows_written"] + s["dropped_rows"] == s["ticks"] and not r["traceback"])
    return measured, str(r["exit"]), "none" if ok else "**departs**"


def _link_rows(r: dict[str, Any]) -> list[tuple[str, str, str, str, str]]:
    return [
        ("`--out` is a symlink to another file", "refused before the device is touched, exit 2; the target "
         "untouched",
         f"\"{_msg(r['messages'], 120)}\"; target untouched: {'yes' if r['target_untouched'] else 'NO'}",
         str(r["exit"]), "none" if r["exit"] == 2 and r["target_untouched"] else "**departs**"),
        ("the same, with `--force`", "the link itself replaced by the log, the target untouched, exit 0",
         f"link replaced by the log: {'yes' if r['force_link_replaced_by_log'] else 'NO'}; target untouched: "
         f"{'yes' if r['force_target_untouched'] else 'NO'}", str(r["force_exit"]),
         "none" if r["force_exit"] == 0 and r["force_link_replaced_by_log"] and r["force_target_untouched"]
         else "**departs**"),
        ("`--out` is an existing log", "refused unless `--force`, exit 2; the log untouched",
         f"\"{_msg(r['existing_messages'], 120)}\"; log untouched: {'yes' if r['existing_untouched'] else 'NO'}",
         str(r["existing_exit"]), "none" if r["existing_exit"] == 2 and r["existing_untouched"] else "**departs**"),
    ]


def run_all(work: Path, verbose: bool = True) -> tuple[list[tuple[str, ...]], dict[str, Any]]:
    rows: list[tuple[str, ...]] = []
    raw: dict[str, Any] = {}
    owner_expect = "refused before it sends anything (exit 3), naming the device and the owner's pid; the " \
                   "first runs on (a start costs it a few link errors on this 2-core box, as much as a control " \
                   "start that touches nothing)"
    scenarios: list[tuple[str, str, str, Callable[[], dict[str, Any]], Callable]] = [
        ("owner_tcp", "second `mrctl run` on the Modbus TCP device of a running one", owner_expect,
         lambda: ownership("modbus-tcp", work / "owner_tcp"), _owner_row),
        ("owner_serial", "second `mrctl run` on the serial device of a running one", owner_expect,
         lambda: ownership("serial", work / "owner_serial"), _owner_row),
        ("disk_full", "disk full mid-run (256 KiB tmpfs, fig5 4 s)", "the loop stays safe; warned on stderr and "
         "in `mrctl status` while it happens; exit 4; the sidecar records the loss",
         lambda: disk_full(work / "disk_full"), _disk_row),
        ("disk_full_sigterm", "disk full, then SIGTERM", "as above: exit 4 (not 1)",
         lambda: disk_full(work / "disk_full_sigterm", sigterm=True), _disk_row),
    ]
    for key, name, expected, run, row in scenarios:
        t0 = time.monotonic()
        for attempt in range(3):  # a first daemon that never reached its loop measured nothing: again
            r = raw[key] = run()
            if r.get("a_in_loop", True):
                break
        measured, code, dev = row(r)
        rows.append((name, expected, measured, code, dev))
        if verbose:
            print(f"{name}: {measured} [{time.monotonic() - t0:.1f} s]", file=sys.stderr, flush=True)
    r = raw["log_path"] = log_path_symlink(work / "log_path")
    rows += _link_rows(r)
    if verbose:
        for row_ in rows[-3:]:
            print(f"{row_[0]}: {row_[2]}", file=sys.stderr, flush=True)
    return rows, raw


def markdown(rows: list[tuple[str, ...]], meta: dict[str, Any]) -> str:
    lines = [f"Generated by `python bench/daemon_faults.py` on {meta['date']} ({meta['host']}, Python "
             f"{meta['python']}, {meta['cpus']} CPUs, {'root' if meta['root'] else 'not root'}); "
             f"{meta['wall_s']:.0f} s in total.", "",
             "| fault | expected reaction | measured | exit code | departs |",
             "|---|---|---|---|---|"]
    lines += [f"| {' | '.join(r)} |" for r in rows]
    return "\n".join(lines)


def write_doc(text: str) -> None:
    replace_block(DOC, BEGIN, END, text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write all measurements here")
    ap.add_argument("--keep", type=Path, help="keep the logs under this directory")
    ap.add_argument("--no-docs", action="store_true", help="do not rewrite docs/reliability.md")
    args = ap.parse_args(argv)
    work = args.keep or Path(tempfile.mkdtemp(prefix="mrctl-daemon-faults-"))  # _msg shortens this name
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        rows, raw = run_all(work)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    meta = {"date": time.strftime("%Y-%m-%d"), "host": platform.node(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "root": os.geteuid() == 0, "wall_s": time.monotonic() - t0}
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "results": raw}, indent=1, default=str) + "\n")
    text = markdown(rows, meta)
    print(text)
    if not args.no_docs:
        write_doc(text)
        print(f"updated {DOC}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
