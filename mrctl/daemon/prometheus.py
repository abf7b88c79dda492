"""A status reply as Prometheus metrics: the text format, and the families the exporter serves.

``mrctl status --format prometheus`` prints the text exposition format
(0.0.4: ``# HELP``, ``# TYPE``, one sample per line) for node_exporter's
textfile collector; ``mrctl exporter`` (:mod:`mrctl.daemon.exporter`) serves
the same families over HTTP. Both read the status socket, never the control
process's memory, and this module needs nothing but the standard library.

Names follow Prometheus's conventions: an ``mrctl_`` prefix, base units in
the name (seconds, amperes, newtons, meters, hertz), ``_total`` on counters.
Percentiles of the loop's timing are summaries with a ``quantile`` label,
over the last 5000 ticks (the status reply's window). A value the daemon
does not have (no sample yet, no load cell) is ``NaN``. With ``damper``
(``--instance NAME``) every sample carries ``damper="NAME"``. docs/observe.md
lists every metric.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

SAFETY_STATES = ("STARTING", "OK", "HOLDING", "FAULT", "LATCHED")
BAD_SAMPLE_KINDS = ("missing", "late", "stale", "non_finite", "out_of_range", "device_status", "estop",
                    "device_watchdog")


@dataclass
class Family:
    name: str  # counters: with _total, as written in the text format
    type: str  # gauge, counter, summary
    help: str
    samples: list[tuple[str, dict[str, str], float]] = field(default_factory=list)


def _num(v: Any) -> float | None:
    if isinstance(v, bool):
        return float(v)
    if isinstance(v, (int, float)):
        return float(v)
    return None


def families(st: dict[str, Any] | None, damper: str | None = None) -> list[Family]:
    """The metric families of a status reply (``None``: no daemon answered → ``mrctl_up 0``)."""
    base = {"damper": damper} if damper else {}
    out: list[Family] = []

    def add(name: str, typ: str, help_: str, value: Any, labels: dict[str, str] | None = None,
            gauge_nan: bool = True) -> None:
        v = _num(value)
        if v is None:
            if typ != "gauge" or not gauge_nan:
                return
            v = math.nan
        fam = next((f for f in out if f.name == name), None)
        if fam is None:
            fam = Family(name, typ, help_)
            out.append(fam)
        fam.samples.append((name, {**base, **(labels or {})}, v))

    add("mrctl_up", "gauge", "1 if the daemon answered on its status socket, else 0", 0 if st is None else 1)
    if st is None:
        return out
    g = st.get
    add("mrctl_info", "gauge", "the running daemon: version, experiment, law (value 1)", 1,
        {"version": str(g("mrctl_version")), "experiment": str(g("experiment")), "law": str(g("law"))})
    add("mrctl_uptime_seconds", "gauge", "seconds since the daemon started", g("uptime_s"))
    add("mrctl_rate_hertz", "gauge", "control rate the loop runs at", g("rate_hz"))
    add("mrctl_ticks_total", "counter", "control ticks run", g("ticks"))
    t = g("timing") if isinstance(g("timing"), dict) else {}
    add("mrctl_overruns_total", "counter", "ticks that ended after the next deadline", t.get("overruns"))
    add("mrctl_skipped_deadlines_total", "counter", "deadlines skipped after overruns", t.get("skipped_deadlines"))
    for what, key, help_ in (("lateness", "lateness", "how late ticks started after their deadline"),
                             ("compute", "compute", "time from a tick's start to its row being logged")):
        for q, k in (("0.5", "p50"), ("0.99", "p99"), ("0.999", "p999")):
            v = _num(t.get(f"{key}_{k}_us"))
            if v is not None:
                add(f"mrctl_tick_{what}_seconds", "summary", f"{help_}, over the last 5000 ticks", v * 1e-6,
                    {"quantile": q})
        mx = _num(t.get(f"{key}_max_us"))
        add(f"mrctl_tick_{what}_max_seconds", "gauge", f"{help_}: the largest since the start",
            mx * 1e-6 if mx is not None else None)
    add("mrctl_current_amperes", "gauge", "coil current commanded on the last tick", g("current_A"))
    add("mrctl_desired_force_newtons", "gauge", "desired force of the last tick", g("F_des_N"))
    add("mrctl_displacement_meters", "gauge", "damper displacement of the last tick", g("x_m"))
    add("mrctl_velocity_meters_per_second", "gauge", "damper velocity of the last tick", g("v_mps"))
    add("mrctl_link_errors_total", "counter", "link errors (failed exchanges, reads, writes)", g("link_errors"))
    sc = g("safety_counters") if isinstance(g("safety_counters"), dict) else {}
    add("mrctl_safety_faults_total", "counter", "entries into the safety FAULT state (0 A)", sc.get("faults_entered"))
    state = g("safety_state")
    if isinstance(state, str):
        for s in SAFETY_STATES:
            add("mrctl_safety_state", "gauge", "safety supervisor state (1 for the current one)", int(s == state),
                {"state": s})
    for kind in BAD_SAMPLE_KINDS:
        add("mrctl_safety_bad_samples_total", "counter", "bad samples by kind", sc.get(kind), {"kind": kind})
    add("mrctl_safety_holds_total", "counter", "bad ticks bridged with the last good sample", sc.get("holds_used"))
    add("mrctl_safety_fault_ticks_total", "counter", "ticks spent in FAULT", sc.get("ticks_in_fault"))
    add("mrctl_safety_resumes_total", "counter", "automatic recoveries from FAULT", sc.get("resumes"))
    add("mrctl_safety_latches_total", "counter", "faults that latched (0 A until mrctl arm)", sc.get("latches"))
    add("mrctl_safety_latched_ticks_total", "counter", "ticks spent latched", sc.get("ticks_latched"))
    add("mrctl_safety_arms_total", "counter", "re-arms (mrctl arm) that took", sc.get("arms"))
    rec = g("recorder") if isinstance(g("recorder"), dict) else None
    if rec is not None:
        add("mrctl_recorder_rows_written_total", "counter", "run-log rows written", rec.get("rows_written"))
        add("mrctl_recorder_lost_rows_total", "counter", "run-log rows lost (buffer full or disk error)",
            rec.get("dropped_rows"))
        add("mrctl_recorder_error", "gauge", "1 if the run log's writer has failed", int(bool(rec.get("error"))))
    stream = g("stream") if isinstance(g("stream"), dict) else None
    if stream is not None:
        add("mrctl_stream_datagrams_total", "counter", "live-stream datagrams sent", stream.get("datagrams"))
        add("mrctl_stream_dropped_total", "counter", "live-stream datagrams dropped (no room, refused, error)",
            stream.get("dropped"))
        add("mrctl_stream_behind_rows_total", "counter", "rows not streamed because the stream fell behind",
            stream.get("rows_behind"))
    taps = g("taps") if isinstance(g("taps"), dict) else None
    if taps is not None:
        add("mrctl_taps", "gauge", "mrctl tap clients connected", taps.get("active"))
    rl = g("reloads") if isinstance(g("reloads"), dict) else {}
    for result in ("ok", "rejected"):
        add("mrctl_reloads_total", "counter", "SIGHUP reloads by result", rl.get(result), {"result": result})
    return out


def _label(v: str) -> str:
    return v.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _value(v: float) -> str:
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "+Inf" if v > 0 else "-Inf"
    return repr(int(v)) if v.is_integer() and abs(v) < 2**53 else format(v, ".10g")


def exposition(fams: list[Family]) -> str:
    """The text exposition format (version 0.0.4)."""
    lines: list[str] = []
    for f in fams:
        lines.append(f"# HELP {f.name} {f.help.replace(chr(92), chr(92) * 2).replace(chr(10), ' ')}")
        lines.append(f"# TYPE {f.name} {f.type}")
        for name, labels, v in f.samples:
            lab = ",".join(f'{k}="{_label(str(x))}"' for k, x in labels.items())
            lines.append(f"{name}{{{lab}}} {_value(v)}" if lab else f"{name} {_value(v)}")
    return "\n".join(lines) + "\n"


def prometheus_text(st: dict[str, Any] | None, damper: str | None = None) -> str:
    return exposition(families(st, damper))
