#!/usr/bin/env python3
"""HIL fault suite, long form: every fault kind against the daemon, and the table.

For each scenario below this starts ``python -m hil_sim`` (fig5 bench, the
fault scheduled on the device's tick time base) and ``mrctl run`` on the fig5
HIL experiment for that transport (``config/experiments/hil_*.yaml``) with
``safety: {hold_ticks: 5, auto_resume: true}`` (or a latched variant), waits
for the end, and measures from the daemon's run log + sidecar and hil_sim's
truth log + summary (hil_sim/testing/fault_suite/ says exactly how). It then
rewrites the generated part of ``docs/reliability.md``.

    python bench/faults.py                       # everything (~5 min), rewrites docs/reliability.md
    python bench/faults.py --only nan --only SIGKILL --no-docs
    python bench/faults.py --json runs/faults.json --keep /tmp/faults

The daemon's configs are the shipped fig5 HIL experiments with the suite's
allowances for a noisy shared VM (hil_sim/testing/fault_suite/scenario.py: 5 ms reply
timeout, hil_sim serving from a thread, no start-up probe, safety pinned to
hold_ticks 5 / auto_resume / link_loss_s 0.1); two rows run the shipped
serial experiment exactly as shipped, for comparison. A daemon that fails
before its loop logs a tick (a start-up failure, not under test) is retried
up to ``--retries`` times; retries are reported below the table, not hidden.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil_sim.testing.fault_suite import (  # noqa: E402
    Scenario,
    deviations,
    run_scenario,
    table_row,
    usable,
)
from mrctl.util.gendoc import replace_block  # noqa: E402

DOC = ROOT / "docs" / "reliability.md"
BEGIN = "<!-- BEGIN GENERATED -->"
END = "<!-- END GENERATED -->"

LATCHED = {"auto_resume": False}
#: re-arm (mrctl arm) 1 s after the daemon latched (the fault is over by then): the latch, then the ramp
ARM = {"arms_after_latch_s": (1.0,), "expect_latch": True}
LATCH = "latched: 0 A until mrctl arm, then a ramp at the slew limit"
#: a link_loss_s long enough for the daemon to reconnect after a 0.2 s outage
PATIENT = {"link_loss_s": 0.5}
HOLD = "hold 5 ticks, then 0 A"

# at_s 3.0 (device time): the daemon is in its loop by then, and the fig5
# sine is at peak velocity, so the commanded current is well above 0 A.
# Link faults meant to be survived last 0.15 s where a failed exchange waits
# for the 5 ms timeout (more than hold_ticks failures even when the box
# stretches ticks to ~10 ms, fewer than link_loss_s' 100), 70 ms where the
# device answers at once with something unusable (Modbus exception, broken
# MBAP): those fail at 1 kHz, and 100 of them in a row are a link loss.
SCENARIOS: list[Scenario] = [
    # -- sample faults (serial) ----------------------------------------------------
    Scenario("nan", f"{HOLD}; auto-resume", ["nan@3.0+0.3"]),
    Scenario("nan, latched", f"{HOLD}; stays 0 A (latched)", ["nan@3.0+0.3"], safety=LATCHED),
    Scenario("nan in v", f"{HOLD}; auto-resume", ["nan@3.0+0.3,field=v"]),
    Scenario("stale_seq", f"{HOLD}; auto-resume", ["stale_seq@3.0+0.3"]),
    Scenario("stale_seq, latched", f"{HOLD}; stays 0 A (latched)", ["stale_seq@3.0+0.3"], safety=LATCHED),
    Scenario("out_of_range", f"{HOLD}; auto-resume", ["out_of_range@3.0+0.3"]),
    # -- link faults (serial) -----------------------------------------------------------
    Scenario("drop_replies 0.15 s", f"{HOLD} (setpoints still arrive); auto-resume", ["drop_replies@3.0+0.15"]),
    Scenario("drop_replies 0.15 s, latched", f"{HOLD}; stays 0 A (latched)", ["drop_replies@3.0+0.15"],
             safety=LATCHED),
    Scenario("drop_replies 1 s", f"{HOLD}; link lost after link_loss_s (100 ticks): exit 3",
             ["drop_replies@3.0+1.0"], expect_exit=3),
    Scenario("delay_replies 0.5 ms (< tick)", "tolerated (reply within the timeout)",
             ["delay_replies@3.0+0.3,delay_s=0.0005"], expect_fault=False),
    Scenario("delay_replies 2 ms (> tick, < timeout)", "tolerated: samples ~2 ticks old, overruns "
             "(max_age_s unset: age not checked)", ["delay_replies@3.0+0.3,delay_s=0.002"], expect_fault=False),
    Scenario("delay_replies 10 ms (> timeout)", f"replies miss the timeout: {HOLD}; auto-resume",
             ["delay_replies@3.0+0.15,delay_s=0.01"]),
    Scenario("corrupt_crc 0.15 s", f"{HOLD}; auto-resume", ["corrupt_crc@3.0+0.15"]),
    Scenario("garbage", "tolerated: the decoder resynchronises", ["garbage@3.0+0.3"], expect_fault=False),
    Scenario("corrupt_crc 1 s", f"{HOLD}; exit 3 after link_loss_s", ["corrupt_crc@3.0+1.0"], expect_exit=3),
    Scenario("ignore_writes", f"{HOLD}; device watchdog 0 A (50 ms); exit 3", ["ignore_writes@3.0+1.0"], expect_exit=3),
    Scenario("ignore_setpoints", "not detected (samples are good): the device keeps the old current, "
             "the truth log shows it", ["ignore_setpoints@3.0+0.3"], expect_fault=False),
    Scenario("disconnect 0.2 s", f"{HOLD}; device watchdog 0 A; reconnect; {LATCH} (link_loss_s 0.5)",
             ["disconnect@3.0+0.2"], safety=PATIENT, **ARM),
    Scenario("disconnect 1 s", f"{HOLD}; device watchdog 0 A; exit 3", ["disconnect@3.0+1.0"], expect_exit=3),
    # -- the E-stop (the device reports ESTOP, latched until CLEAR_FAULTS once its input closed)
    Scenario("estop 0.5 s", f"0 A at once (no hold); {LATCH}", ["estop@3.0+0.5"], **ARM),
    Scenario("estop open at mrctl arm", "0 A at once; mrctl arm refused while the E-stop is open; 0 A to the end",
             ["estop@3.0+10"], arms_after_latch_s=(0.0,), expect_latch=True),
    Scenario("TCP estop 0.5 s", f"0 A at once (no hold); {LATCH}", ["estop@3.0+0.5"], transport="modbus-tcp", **ARM),
    # -- the shipped serial experiment as is (device-paced, 0.84 ms reply timeout,
    # link_loss_s and link probe as shipped, inline serving): what the suite's
    # allowances change
    Scenario("nan, shipped hil_serial.yaml", f"{HOLD}; auto-resume", ["nan@3.0+0.3"], shipped=True),
    Scenario("drop_replies 50 ms, shipped hil_serial.yaml", f"{HOLD}; auto-resume", ["drop_replies@3.0+0.05"],
             shipped=True),
    # -- Modbus TCP ---------------------------------------------------------------------
    Scenario("TCP nan", f"{HOLD}; auto-resume", ["nan@3.0+0.3"], transport="modbus-tcp"),
    Scenario("TCP modbus_exception 1 s", f"{HOLD}; writes refused: device watchdog 0 A; exit 3",
             ["modbus_exception@3.0+1.0"], transport="modbus-tcp", expect_exit=3),
    Scenario("TCP modbus_exception 70 ms", f"{HOLD}; writes refused: device watchdog 0 A; {LATCH}",
             ["modbus_exception@3.0+0.07"], transport="modbus-tcp", **ARM),
    Scenario("TCP corrupt MBAP 40 ms", f"{HOLD}; auto-resume (40 failed ticks < latch_after_s' 50)",
             ["corrupt_crc@3.0+0.04"], transport="modbus-tcp"),
    Scenario("TCP corrupt MBAP 0.2 s", f"{HOLD}; {LATCH} (a link loss over latch_after_s)",
             ["corrupt_crc@3.0+0.2"], transport="modbus-tcp", safety=PATIENT, **ARM),
    Scenario("TCP garbage 40 ms", f"{HOLD} (stream resync); auto-resume", ["garbage@3.0+0.04"],
             transport="modbus-tcp"),
    Scenario("TCP drop_replies 0.15 s", f"{HOLD}; auto-resume", ["drop_replies@3.0+0.15"], transport="modbus-tcp"),
    Scenario("TCP disconnect 0.2 s", f"{HOLD}; device watchdog 0 A; reconnect; {LATCH} (link_loss_s 0.5)",
             ["disconnect@3.0+0.2"], transport="modbus-tcp", safety=PATIENT, **ARM),
    Scenario("TCP ignore_writes", f"{HOLD}; device watchdog 0 A; exit 3", ["ignore_writes@3.0+1.0"],
             transport="modbus-tcp", expect_exit=3),
    # -- device pacing (loop.pacing: device, the SYNC flag; serial) ------------------------
    Scenario("nan, device-paced", f"{HOLD}; auto-resume", ["nan@3.0+0.3"], pacing="device"),
    Scenario("drop_replies 0.15 s, device-paced", f"{HOLD}; auto-resume", ["drop_replies@3.0+0.15"],
             pacing="device"),
    Scenario("disconnect 0.2 s, device-paced", f"{HOLD}; device watchdog 0 A; reconnect; {LATCH} "
             "(link_loss_s 0.5)", ["disconnect@3.0+0.2"], safety=PATIENT, pacing="device", **ARM),
    # -- Modbus RTU (device-paced and served inline, as hil_modbus_rtu.yaml and hil_sim ship;
    # its client sleeps for the reply, so the two do not starve each other) -------------
    Scenario("RTU nan", f"{HOLD}; auto-resume", ["nan@3.0+0.3"], transport="modbus-rtu", pacing="device", serve="inline"),
    Scenario("RTU corrupt_crc 40 ms", f"{HOLD}; auto-resume", ["corrupt_crc@3.0+0.04"], transport="modbus-rtu",
             pacing="device", serve="inline"),
    Scenario("RTU garbage", "tolerated: the client hunts for its reply", ["garbage@3.0+0.3"],
             transport="modbus-rtu", pacing="device", serve="inline", expect_fault=False),
    Scenario("RTU drop_replies 0.15 s", f"{HOLD}; auto-resume", ["drop_replies@3.0+0.15"], transport="modbus-rtu",
             pacing="device", serve="inline"),
    Scenario("RTU disconnect 0.2 s", f"{HOLD}; device watchdog 0 A; reconnect; {LATCH} (link_loss_s 0.5)",
             ["disconnect@3.0+0.2"], transport="modbus-rtu", safety=PATIENT, pacing="device", **ARM),
    # -- process faults -------------------------------------------------------------------
    Scenario("SIGTERM", "0 A at the device, complete log, exit 0", process="SIGTERM", duration_s=10.0,
             process_at_ticks=1000),
    Scenario("SIGINT", "0 A at the device, complete log, exit 0", process="SIGINT", duration_s=10.0,
             process_at_ticks=1000),
    Scenario("SIGKILL + restart", "log valid up to its last flush (≤ 1 s lost); device watchdog 0 A; "
             "the restart's first setpoint is 0 A", process="SIGKILL", duration_s=10.0, process_at_ticks=1700),
    Scenario("reload, broken config", "rejected; the loop runs on, no missing ticks", process="reload",
             duration_s=5.0, process_at_ticks=1000),
]


def run_all(scenarios: list[Scenario], workroot: Path, retries: int, verbose: bool = True) -> list[dict[str, Any]]:
    results = []
    for i, sc in enumerate(scenarios):
        attempts = 0
        failures: list[str] = []
        while True:
            attempts += 1
            wd = workroot / f"{i:02d}_{sc.name.replace(' ', '_').replace(',', '').replace('/', '_')}_{attempts}"
            r = run_scenario(sc, wd)
            why = usable(r)
            if why is None or attempts > retries:
                break
            failures.append(why)
            if verbose:
                print(f"  {sc.name}: not usable ({why}); retrying", file=sys.stderr, flush=True)
        r["attempts"] = attempts
        r["retried_because"] = failures
        r["workdir"] = str(wd)
        results.append(r)
        if verbose:
            row = table_row(sc, r)
            print(f"{sc.name:32s} | {row['device']:28s} | {row['daemon']:10s} | {row['kept']:24s} | "
                  f"{row['recovered']:24s} | {row['lost']}  [{r.get('wall_s')} s, attempt {attempts}]",
                  file=sys.stderr, flush=True)
    return results


def markdown(scenarios: list[Scenario], results: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    lines = [
        f"Generated by `python bench/faults.py` on {meta['date']} ({meta['host']}, Python {meta['python']}, "
        f"{meta['cpus']} CPUs); {meta['wall_s']:.0f} s in total.",
        "",
        "| fault | expected reaction | measured ticks to 0 A at the device | daemon ticks to 0 A commanded "
        "| kept running / exit code | recovered | largest rise per tick (A) | ticks lost |",
        "|---|---|---|---|---|---|---|---|",
    ]
    notes = []
    devs = []
    for sc, r in zip(scenarios, results):
        row = table_row(sc, r)
        name = f"{row['fault']} ({sc.transport})" if not sc.process else row["fault"]
        lines.append(f"| {name} | {row['expected']} | {row['device']} | {row['daemon']} | {row['kept']} | "
                     f"{row['recovered']} | {row['rise']} | {row['lost']} |")
        for why in r.get("retried_because") or []:
            notes.append(f"- {sc.name}: an earlier run was not usable and was repeated: {why}")
        for d in deviations(sc, r):
            devs.append(f"- **{sc.name}**: {d}")
    lines.append("")
    lines.append("Columns: *device* = truth-log ticks from the fault's first device tick to the first tick "
                 "whose applied driver input `I_cmd` is 0 A because of it, and who did it (`daemon` = its 0 A "
                 "setpoint arrived; `watchdog` = no live setpoint, `WATCHDOG_TRIPPED`, the device's 50 ms "
                 "watchdog; `never` = the device kept a current); *daemon* = the daemon's own ticks (run-log "
                 "rows) from the first tick that saw a bad or missing sample of the fault to the first row "
                 "commanding 0 A in FAULT; *largest rise* = the largest increase of the commanded current "
                 "from one logged tick to the next over the whole run (the first tick's from 0 A, every "
                 "resume's and re-arm's: the slew limit, 50 A/s, allows 0.050 A a tick); "
                 "*ticks lost* = the loop's tick count in the sidecar minus the "
                 "log's rows (skipped deadlines are not ticks; they are the `k` column's jumps).")
    lines += ["", "Where the measurement departs from the expected reaction (generated):", ""]
    lines += devs or ["- none"]
    if notes:
        lines += ["", "Repeated runs (a run that could not measure what it is for is repeated, up to "
                  "`--retries` times):", "", *notes]
    return "\n".join(lines)


def write_doc(text: str) -> None:
    replace_block(DOC, BEGIN, END, text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", default=[], help="run scenarios whose name contains this (repeatable)")
    ap.add_argument("--retries", type=int, default=3, help="start-up failures retried per scenario (default 3)")
    ap.add_argument("--json", type=Path, help="write all measurements here")
    ap.add_argument("--keep", type=Path, help="keep the logs under this directory (default: a temp dir, removed)")
    ap.add_argument("--no-docs", action="store_true", help="do not rewrite docs/reliability.md")
    args = ap.parse_args(argv)
    scenarios = [s for s in SCENARIOS if not args.only or any(o in s.name for o in args.only)]
    if not scenarios:
        ap.error("no scenario matches --only")
    root = args.keep or Path(tempfile.mkdtemp(prefix="mrctl-faults-"))
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        results = run_all(scenarios, root, args.retries)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    import os

    meta = {"date": time.strftime("%Y-%m-%d"), "host": platform.node(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "wall_s": time.monotonic() - t0}
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "results": results}, indent=1, default=str) + "\n")
    text = markdown(scenarios, results, meta)
    print(text)
    if not args.no_docs:
        if args.only:
            print("(--only: docs/reliability.md not rewritten; run without --only)", file=sys.stderr)
        else:
            write_doc(text)
            print(f"updated {DOC}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
