"""The run log: one format for ``mrctl run`` and ``mrctl simulate``.

A run log is a plain CSV (the header is its first line, one row per tick,
SI units) and a JSON sidecar beside it (``run.csv`` → ``run.json``) that
describes it: every column's unit and meaning, the legend of the ``fault``
bit field, the exit codes, what ran with what (provenance) and the summary.
Both commands write exactly :data:`RUN_COLUMNS`, in this order, with the
same meaning per column; docs/runlog.md is generated from this module
(``python -m mrctl.runlog``).

Shared by what writes a log (the daemon's recorder, simulate) and what
reads one (report, identify, the test harnesses).
"""

from __future__ import annotations

from typing import Any, Mapping

#: format tag of the sidecar
SIDECAR_FORMAT = "mrctl-run/2"

#: (name, unit, meaning) of every column, in the CSV's order. "Simulated
#: bench" = the in-process sim backend, ``mrctl simulate``, or hil_sim.
_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("t", "s", "tick time k·dt since the start of the run"),
    ("x", "m", "displacement the controller used this tick (sensor reading; NaN while the safety supervisor "
               "had no usable sample)"),
    ("v", "m/s", "velocity the laws used this tick (sensor reading, or its lead-compensated prediction; "
                 "NaN while no usable sample)"),
    ("F_des", "N", "desired force from the demand law (NaN without one, or while no usable sample)"),
    ("F", "N", "load cell reading received this tick, as the laws saw it (NaN without a load cell or sample); "
               "on a simulated bench the plant's force of the previous tick plus sensor noise"),
    ("I", "A", "coil current commanded this tick, after the clamp and the safety supervisor"),
    ("k", "tick", "tick index (t = k·dt); a jump is a skipped deadline"),
    ("seq", "", "the device's sample sequence number (NaN: no sample this tick)"),
    ("t_dev", "s", "the device's time of the sample (NaN: no sample)"),
    ("I_applied", "A", "current the driver reported applied when the sample was taken (NaN if it does not "
                       "report one)"),
    ("F_true", "N", "the plant's force at this tick with this tick's current: simulated benches only, "
                    "NaN on hardware"),
    ("late_us", "us", "how late the tick started after its deadline (NaN offline)"),
    ("compute_us", "us", "time from the tick's start to its row being logged (NaN offline)"),
    ("fault", "flags", "safety supervisor fault bits of this tick (0 = none; legend in the sidecar's "
                       "fault_bits)"),
    ("link_errors", "count", "link errors since the start of the run"),
)

#: Columns of the run log, in order; the first six are the core every reader needs.
RUN_COLUMNS: tuple[str, ...] = tuple(c for c, _, _ in _COLUMNS)
#: Their units ("" = a count without unit).
RUN_UNITS: dict[str, str] = {c: u for c, u, _ in _COLUMNS}
#: One line each: what the column holds.
RUN_MEANINGS: dict[str, str] = {c: m for c, _, m in _COLUMNS}
#: The core columns, in order (s, m, m/s, N, N, A).
CORE_COLUMNS: tuple[str, ...] = RUN_COLUMNS[:6]
#: Their text formats: the log's contract, the bytes both builds write
#: (mrctl/runlog/rowtext.py formats them, in C in the compiled build). 9
#: significant digits are far below any sensor's resolution, and format 5x
#: faster than exact repr with '%'. Counters and clocks get 10 digits, exact
#: for integers below 1e10.
RUN_FORMATS = {c: "%.9g" for c in RUN_COLUMNS} | {"t": "%.10g", "k": "%.10g", "seq": "%.10g", "t_dev": "%.10g"}

#: The ``fault`` column's bits: (name, value, meaning). The supervisor's
#: :class:`mrctl.core.safety.Fault` has exactly these (tests/test_runlog_format.py).
FAULT_BITS: tuple[tuple[str, int, str], ...] = (
    ("MISSING", 1 << 0, "no sample this tick (timeout, link error)"),
    ("LATE", 1 << 1, "the sample was older than safety.max_age_s"),
    ("STALE", 1 << 2, "the sample's sequence number did not advance"),
    ("NON_FINITE", 1 << 3, "NaN or inf in x or v (or F: inf always, NaN if the load cell is required)"),
    ("OUT_OF_RANGE", 1 << 4, "x, v or F outside the configured safety range"),
    ("DEVICE_STATUS", 1 << 5, "the device reported a driver or sensor fault in its status"),
    ("DRIVER", 1 << 6, "the current driver could not be commanded (latched; the run ends)"),
    ("LAW", 1 << 7, "a control law raised, returned NaN/inf or overran its budget (latched; the run ends, docs/laws.md)"),
    ("ESTOP", 1 << 8, "the E-stop / interlock input is open (safety.estop): 0 A at once, latched"),
    ("DEVICE_WATCHDOG", 1 << 9, "the device's own watchdog tripped (it applied its safe state): latched"),
    ("LATCHED", 1 << 10, "the fault is latched: 0 A, output disabled, until mrctl arm (beside its cause's bits)"),
)

#: ``mrctl`` exit codes (README, mrctl/errors.py).
EXIT_CODES: dict[str, str] = {
    "0": "success (a command that runs until stopped: also when stopped by SIGINT/SIGTERM)",
    "1": "internal error, or a control law that failed",
    "2": "bad input (config, option, --out, a file it names, a missing optional dependency)",
    "3": "link failure (cannot open, infeasible rate, driver lost, device owned by another mrctl)",
    "4": "run log incomplete (rows lost, disk full or failing)",
    "5": "run completed but degraded",
}


_STOPPED = "stopped by SIGINT/SIGTERM"
_INTERRUPTED = "Ctrl-C (SIGINT) before it finished: nothing written (SIGTERM: the system's default, 143)"
_INTERNAL = "internal error (a bug: the message says where)"

#: what each code means for each command (docs/cli.md's table, each command's --help,
#: tests/test_exit_codes.py drives every entry). A command that runs until stopped
#: (run, sweep, tap, exporter) exits 0 when the user stops it; a one-shot command
#: interrupted has no result, and says so with 130.
COMMAND_EXITS: dict[str, dict[int, str]] = {
    "run": {0: f"ran its duration, or {_STOPPED} (during start-up too: nothing left behind); the verdict "
               "judges the ticks before the signal, so deadlines missed while stopping never give 5",
            1: "a control law failed (raised, NaN, too slow: docs/laws.md), or " + _INTERNAL,
            2: "bad input: the config, an option, --out, a file the config names",
            3: "link failure: cannot open, too slow for the rate, driver lost, device owned by another mrctl",
            4: "run log incomplete: rows lost, disk full (the sidecar records what)",
            5: "degraded: an acceptance bound broken (stderr and the sidecar's verdict name it)"},
    "simulate": {0: "done, the verdict ok", 1: "a control law failed (the run ends at 0 A), or " + _INTERNAL,
                 2: "bad input: the config, an option, --out, a run log to replay",
                 4: "the run log could not be written", 5: "degraded: an acceptance bound broken",
                 130: _INTERRUPTED},
    "sweep": {0: f"every point has its row (failed points included), or {_STOPPED}: the table is valid and "
                 "the same command resumes it", 1: _INTERNAL,
              2: "bad input: the sweep file, an option, --out, a missing extra",
              3: "the Dask scheduler (--scheduler) cannot be reached"},
    "report": {0: "the figure written", 1: _INTERNAL,
               2: "bad input: a run or table that cannot be read, an option, --out, matplotlib missing",
               130: _INTERRUPTED},
    "identify": {0: "the parameters written", 1: _INTERNAL,
                 2: "bad input: runs or a dataset that cannot be read or fitted, an unphysical fit, an option",
                 130: _INTERRUPTED},
    "calibrate": {0: "the calibration written", 1: _INTERNAL, 2: "bad input: the config, an option, --out",
                  3: "link failure: the device cannot be opened or read, or is owned by another mrctl; at start "
                     "the E-stop is open or a watchdog trip or driver fault does not clear; during the measurement "
                     "the E-stop opened, the device's watchdog tripped or the driver faulted (stopped at 0 A, "
                     "nothing written)", 130: _INTERRUPTED},
    "check": {0: "the file is valid (and the link can sustain the rate)", 1: _INTERNAL,
              2: "invalid (every error listed with its key path), or the link cannot sustain the rate"},
    "status": {0: "the daemon answered", 1: _INTERNAL, 2: "bad input: an option",
               3: "nothing running on that socket, or not mrctl answering"},
    "ls": {0: "listed (none running is an empty list)", 1: _INTERNAL},
    "tap": {0: f"the rows asked for, or {_STOPPED}, or the reader closed the pipe", 1: _INTERNAL,
            2: "bad input: an option, a column, a trigger",
            3: "nothing running, the tap refused, or the daemon ended or dropped the tap before the rows came"},
    "arm": {0: "re-armed, or nothing to re-arm", 1: _INTERNAL,
            3: "refused (its cause is still there), or nothing running"},
    "exporter": {0: _STOPPED, 1: _INTERNAL,
                 2: "bad input: --listen, or prometheus-client missing (pip install 'mrctl[metrics]')"},
    "device": {0: "done (disarm: the device's watchdog off in its flash, read back)", 1: _INTERNAL,
               2: "bad input: the config, an option, a backend without a device preset",
               3: "link failure: the device cannot be opened, refuses the write, or is owned by another mrctl"},
    "examples": {0: "copied", 1: _INTERNAL, 2: "DIR already holds the files (--force replaces them), or is not "
                                                "a directory"},
    "docs": {0: "printed", 1: _INTERNAL, 2: "no such topic"},
}


def exit_codes_text(command: str | None = None) -> str:
    """The exit-code table as ``--help`` epilogs print it; ``command``: what
    each code means for that command, after the general table."""
    text = "exit codes:\n" + "\n".join(f"  {k}  {v}" for k, v in EXIT_CODES.items())
    if command in COMMAND_EXITS:
        text += f"\n\nmrctl {command} exits:\n" + "\n".join(
            f"  {k:<3}  {v}" for k, v in COMMAND_EXITS[command].items())
    return text


def command_exits_markdown() -> str:
    """docs/cli.md's table: each command's codes and what they mean there."""
    rows = ["| command | code | when |", "|---|---|---|"]
    for cmd, codes in COMMAND_EXITS.items():
        rows += [f"| `{cmd}` | {code} | {what} |" for code, what in codes.items()]
    return "\n".join(rows)


def describe_columns(columns: tuple[str, ...] = RUN_COLUMNS) -> dict[str, Any]:
    """The self-describing part of a sidecar: columns, units, meanings, the
    fault legend, the exit codes."""
    return {
        "columns": list(columns),
        "column_info": {c: {"unit": RUN_UNITS.get(c, ""), "meaning": RUN_MEANINGS.get(c, "")} for c in columns},
        "fault_bits": {name: {"value": value, "meaning": meaning} for name, value, meaning in FAULT_BITS},
        "exit_codes": dict(EXIT_CODES),
    }


def sidecar_header(command: str, csv_name: str, provenance: Mapping[str, Any]) -> dict[str, Any]:
    """The top of every sidecar, in this order: format, what wrote it, the
    column description, then the provenance (versions, host, config, parameters,
    I_max_A, rate_hz, …)."""
    return {"format": SIDECAR_FORMAT, "command": command, "csv": csv_name, **describe_columns(),
            **dict(provenance)}


def columns_markdown() -> str:
    """The column and fault-bit tables of docs/runlog.md."""
    lines = ["| column | unit | meaning |", "|---|---|---|"]
    lines += [f"| `{c}` | {u or '-'} | {m} |" for c, u, m in _COLUMNS]
    lines += ["", "| `fault` bit | value | meaning |", "|---|---|---|"]
    lines += [f"| `{n}` | {v} | {m} |" for n, v, m in FAULT_BITS]
    lines += ["", "| exit code | meaning |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in EXIT_CODES.items()]
    return "\n".join(lines)


def row_format(columns: tuple[str, ...], fmt: str | Mapping[str, str] = "%r", require_core: bool = True) -> str:
    """The ``%``-format of one CSV row of ``columns`` (``fmt``: one format for
    all, or ``{column: format}`` over a default of exact repr). ValueError
    for bad names (empty, padded, or with ``, " #`` or a newline),
    duplicates, missing core columns, or formats that are not one field each."""
    if not columns:
        raise ValueError("columns: need at least one column")
    bad = [c for c in columns if not c or c != c.strip() or any(ch in c for ch in ',"\r\n#')]
    if bad:
        raise ValueError(f"columns: invalid name(s) {bad!r} (empty, spaces, or one of , \" # newline)")
    dupes = sorted({c for c in columns if columns.count(c) > 1})
    if dupes:
        raise ValueError(f"columns: duplicate name(s) {dupes!r}")
    if require_core and columns[: len(CORE_COLUMNS)] != CORE_COLUMNS:
        raise ValueError(f"columns must start with {','.join(CORE_COLUMNS)}; got {','.join(columns)}")
    if isinstance(fmt, str):
        fmts = [fmt] * len(columns)
    else:
        unknown = sorted(set(fmt) - set(columns))
        if unknown:
            raise ValueError(f"fmt: unknown column(s) {unknown!r}")
        fmts = [fmt.get(c, "%r") for c in columns]
    row = ",".join(fmts) + "\n"
    try:
        probe = row % tuple(0.5 for _ in columns)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"fmt: bad format {row!r}: {exc}") from None
    if probe.count(",") != len(columns) - 1 or probe.count("\n") != 1:
        raise ValueError(f"fmt: formats must not produce ',' or newlines: {row!r}")
    return row
