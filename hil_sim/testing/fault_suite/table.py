"""From measurements to docs/reliability.md: a table row per scenario, the
departures from its documented expectation, and whether a run is usable."""

from __future__ import annotations

from typing import Any

from mrctl.errors import ExitCode

from hil_sim.testing.fault_suite.analysis import _fault_made_misses
from hil_sim.testing.fault_suite.scenario import RATE_HZ, Scenario

__all__ = ["table_row", "deviations", "usable"]


#: a run that completed while its fault broke an acceptance bound (more than
#: 2 % of its ticks in fault, or over 100 ms at forced 0 A): the verdict is
#: degraded, exit 5, and the reaction under test is judged as for exit 0
COMPLETED_DEGRADED = ExitCode.DEGRADED


def table_row(sc: Scenario, r: dict[str, Any]) -> dict[str, str]:
    """One row of docs/reliability.md: fault | expected | device ticks | daemon ticks |
    kept running / exit | recovered | ticks lost."""
    exit_code = r.get("exit_code")
    t = r.get("ticks") or {}
    lost = t.get("ticks_lost")
    skipped = t.get("k_jumps_skipped")
    lost_txt = "?" if lost is None else f"{lost}"
    if lost is not None and skipped is not None:
        lost_txt += f" (skipped deadlines {skipped})"
    if exit_code == 0:
        kept = "kept running, exit 0" if not sc.process else "exit 0"
    elif exit_code == COMPLETED_DEGRADED and not sc.process:
        kept = "kept running, exit 5 (degraded: the fault broke an acceptance bound)"
    else:
        kept = f"exit {exit_code}"
    rise = r.get("max_rise_A")
    row = {"fault": sc.name, "expected": sc.expected, "device": "-", "daemon": "-", "kept": kept,
           "recovered": "-", "lost": lost_txt, "rise": "-" if rise is None else f"{rise:.3f}"}
    if r.get("error"):
        row["device"] = row["daemon"] = f"error: {r['error']}"
        return row
    ws = r.get("windows") or []
    if ws:
        w = ws[0]
        if not w.get("valid"):
            row["device"] = row["daemon"] = f"invalid: {w.get('why')}"
            return row
        dz = w.get("device_ticks_to_0A")
        if w.get("device_I_before_A") == 0.0:
            row["device"] = "already 0 A"
        elif dz is None:
            rng = w.get("device_I_range_in_window_A")
            row["device"] = "never" + (f" (I_cmd {rng[0]:.2f}-{rng[1]:.2f} A in the window)" if rng else "")
        else:
            row["device"] = f"{dz} ({w.get('device_0A_by')})"
        nz = w.get("daemon_ticks_to_0A")
        row["daemon"] = "no FAULT" if nz is None else f"{nz}"
        later = w.get("later_fault_after_ticks")
        if nz is None and later is not None:
            miss = (f"missing samples {100 * w['missing_in_window']:.0f} % in the window, "
                    f"{100 * w['missing_outside_window']:.0f} % outside")
            if _fault_made_misses(w):
                row["daemon"] = f"FAULT {later} ticks in ({miss}: replies missing the timeout)"
            else:
                row["daemon"] += f" (a FAULT {later} ticks in: link noise, {miss})"
        if nz is None and exit_code in (0, COMPLETED_DEGRADED):
            row["recovered"] = "n/a (no fault)"
        elif exit_code not in (0, COMPLETED_DEGRADED):
            row["recovered"] = "no (run ended)"
        elif _latches(r):
            row["recovered"] = _after_latch(r)
        elif sc.safety.get("auto_resume") is False:
            row["recovered"] = "no (latched)" if not w.get("recovered") else "yes (?!)"
        elif w.get("recovered"):
            row["recovered"] = f"yes, {w.get('daemon_ticks_to_recover')} ticks after"
        else:
            row["recovered"] = "no"
    p = r.get("process")
    if sc.process and not (r.get("process_info") or {}).get("signal_sent"):
        row["device"] = row["daemon"] = "invalid: the daemon ended before the signal"
        return row
    if p:
        if sc.process in ("SIGTERM", "SIGINT"):
            row["device"] = f"{p.get('device_ticks_to_0A_after_last_logged_tick')} after the last tick ({p.get('device_0A_by')})"
            row["daemon"] = f"exit path (exit_current_A {r.get('exit_current_A')})"
            row["recovered"] = "n/a"
        elif sc.process == "SIGKILL":
            row["device"] = (f"{p.get('device_ticks_to_0A_after_kill')} after the last setpoint "
                             f"({p.get('device_0A_by')})")
            row["daemon"] = "- (killed)"
            row["kept"] = f"killed; restart exit {r.get('restart_exit_code')}"
            row["recovered"] = f"restart's first setpoint {p.get('restart_first_setpoint_A')} A"
            row["lost"] = f"{p.get('log_ticks_lost_at_kill')} at the kill (≤ 1000 allowed)"
        elif sc.process == "reload":
            row["device"] = "n/a"
            row["daemon"] = "n/a"
            row["recovered"] = "rejected, loop unaffected" if p.get("reload_rejected") else "NOT rejected?"
            row["lost"] = (f"{lost_txt}; max k gap {p.get('reload_window_max_k_gap')} within "
                           f"±200 ticks of the reload")
    return row


def _latches(r: dict[str, Any]) -> int:
    return int((r.get("safety") or {}).get("latches") or 0)


def _after_latch(r: dict[str, Any]) -> str:
    """The recovered column of a latched run: the cause, and what mrctl arm came to."""
    arms = r.get("arms") or []
    taken = [a for a in arms if a.get("armed") and "re-armed" in str(a.get("message"))]
    cause = next((str((a.get("status_before") or {}).get("latch_cause")) for a in arms), None)
    what = f"latched ({cause})" if cause else "latched"
    if not arms:
        return f"no: {what}, 0 A to the end"
    if taken:
        return f"{what}; after mrctl arm"
    return f"no: {what}; mrctl arm refused"


def deviations(sc: Scenario, r: dict[str, Any], hold_ticks: int = 5, slew_step_A: float = 0.05) -> list[str]:
    """Where the measurement departs from the scenario's documented expectation
    (``slew_step_A``: the pinned slew limit times the 1 ms period)."""
    out: list[str] = []
    exit_code = r.get("exit_code")
    rise = r.get("max_rise_A")
    if rise is not None and rise > slew_step_A + 1e-9:
        out.append(f"the current rose {rise:.3f} A in one tick > the slew limit's {slew_step_A:.3f} A")
    if sc.process == "SIGKILL":
        p = r.get("process") or {}
        if p.get("restart_first_setpoint_A") != 0.0:
            out.append(f"the restart's first setpoint was {p.get('restart_first_setpoint_A')} A, not 0 A")
        lost = p.get("log_ticks_lost_at_kill")
        if lost is None or lost > 1000:
            out.append(f"{lost} ticks lost at the kill (> 1 s)")
        if r.get("restart_exit_code") != 0:
            out.append(f"the restart exited {r.get('restart_exit_code')}")
        return out
    if exit_code != sc.expect_exit and not (sc.expect_exit == 0 and exit_code == COMPLETED_DEGRADED):
        why = "; ".join(m for m in r.get("daemon_stderr") or [] if m.startswith("mrctl:"))
        out.append(f"exit {exit_code}, expected {sc.expect_exit}" + (f" ({why})" if why else ""))
    t = r.get("ticks") or {}
    lost = t.get("ticks_lost")
    if lost:
        out.append(f"{lost} loop tick(s) not in the run log (loop {t.get('loop_ticks')}, rows {t.get('rows')})")
    if sc.process == "reload":
        p = r.get("process") or {}
        if not p.get("reload_rejected"):
            out.append("the broken config was not reported as rejected")
        return out
    if sc.process in ("SIGTERM", "SIGINT"):
        if r.get("exit_current_A") != 0.0:
            out.append(f"exit_current_A {r.get('exit_current_A')}")
        if (r.get("process") or {}).get("device_ticks_to_0A_after_last_logged_tick") is None:
            out.append("the device did not stay at 0 A after the daemon's last tick")
        return out
    for w in r.get("windows") or []:
        if not w.get("valid"):
            out.append(f"window invalid: {w.get('why')}")
            continue
        n = w.get("daemon_ticks_to_0A")
        if sc.expect_fault and n is None:
            out.append("no FAULT (0 A) from the supervisor")
        if not sc.expect_fault and n is not None:
            out.append(f"FAULT (0 A) after {n} daemon ticks, not expected")
        if not sc.expect_fault and n is None and w.get("later_fault_after_ticks") is not None \
                and _fault_made_misses(w):
            out.append(f"FAULT (0 A) {w['later_fault_after_ticks']} daemon ticks into the window: "
                       f"{100 * w['missing_in_window']:.0f} % of its samples missing "
                       f"({100 * w['missing_outside_window']:.0f} % outside it)")
        if n is not None and n > hold_ticks + 2:
            out.append(f"0 A after {n} daemon ticks > hold_ticks + 2 = {hold_ticks + 2}")
        if (sc.expect_fault and sc.expect_exit == 0 and exit_code in (0, COMPLETED_DEGRADED)
                and sc.safety.get("auto_resume", True) and not sc.expect_latch
                and not w.get("recovered")):
            out.append("did not recover (auto_resume)")
        if sc.safety.get("auto_resume") is False and w.get("recovered"):
            out.append("recovered although latched")
    if sc.expect_latch and not _latches(r) and not sc.expect_exit:
        out.append("did not latch")
    if not sc.expect_latch and not sc.expect_exit and sc.safety.get("auto_resume", True) and _latches(r):
        out.append(f"latched ({_after_latch(r)})")
    return out


def usable(r: dict[str, Any]) -> str | None:
    """Why a run cannot measure what it is for (then it is retried), or None.

    A start-up failure (no tick logged), or a fault window that began while the
    daemon or the device was already at 0 A (a noise FAULT of the box's link, or
    the law's own zero crossing): "ticks to 0 A" would be meaningless.
    """
    if (r.get("ticks") or {}).get("rows", 0) == 0 and r.get("exit_code") != 0:
        return "start-up failed: " + "; ".join(r.get("daemon_stderr") or [])
    ws = r.get("windows") or []
    trip = r.get("daemon_saw_trip_t_dev")
    if ws and trip is not None and trip < ws[0].get("k0", 0) / RATE_HZ:
        # the device's watchdog latches the run: a host stalled past it in the loop before the
        # fault began leaves nothing to measure (the box's noise, not the fault under test)
        return f"the device's watchdog tripped at device time {trip:.3f} s, before the fault (a stalled host)"
    for w in ws:
        if not w.get("valid"):
            return f"window invalid: {w.get('why')}"
        if w.get("I_before_A") == 0.0 or w.get("device_I_before_A") == 0.0:
            return "0 A already when the fault began"
    if r.get("process") and not (r.get("process_info") or {}).get("signal_sent"):
        return "the daemon ended before the signal"
    return None
