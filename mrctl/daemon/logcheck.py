"""The run log as the service sees it: warn while rows are lost, judge it at the end.

:class:`LogWatch` is called by the monitor thread every 50 ms and by the
status thread on each ``mrctl status``: the first time the recorder reports
lost rows (a full or failing disk, a writer that cannot keep up) it warns,
once, on stderr and in systemd's ``STATUS=``, and its :attr:`LogWatch.state`
shows in ``mrctl status``; the loop and the damper's safety are not
affected. :func:`close_log` drains the recorder at the end, decides exit 4
if anything was lost, computes the tracking figures from the log, and
writes the final sidecar once, with the exit code; if even that cannot be
written (the disk is full and the reservation does not hold it), stderr
says so with the counts.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

from mrctl.errors import ExitCode
from mrctl.runlog.files import sidecar_path
from mrctl.runlog.metrics import tracked_force, tracking_summary


def tick_span(st: dict[str, Any]) -> str:
    """" (ticks a–b)" over the lost and dropped rows of recorder stats, or ""."""
    firsts = [t for t in (st.get("lost_first_tick"), st.get("overflow_first_tick")) if t is not None]
    lasts = [t for t in (st.get("lost_last_tick"), st.get("overflow_last_tick")) if t is not None]
    return f" (ticks {min(firsts)}–{max(lasts)})" if firsts and lasts else ""


class LogWatch:
    """Warns once when the run log starts losing rows; :attr:`state` for status."""

    def __init__(self, has_log: bool, warn: Callable[[str], None], notify: Callable[[str], object]) -> None:
        self.state = "ok" if has_log else "no log"
        self.warn = warn
        self.notify = notify
        self.warned = False
        self._lock = threading.Lock()

    def check(self, rec: Any) -> None:
        if rec is None or self.warned:
            return
        st = rec.stats()
        if not (st["dropped_rows"] or st["error"]):
            return
        firsts = [t for t in (st["lost_first_tick"], st["overflow_first_tick"]) if t is not None]
        first = min(firsts) if firsts else st["ticks"]
        why = st["error"] or "the writer cannot keep up (buffer full)"
        with self._lock:  # two threads call this
            if self.warned:
                return
            self.warned = True
            self.state = f"LOSING ROWS since tick {first}: {why}"
        self.warn(f"run log: losing rows from tick {first} on ({why}); the loop runs on and keeps the damper "
                  f"safe; the run will end with exit 4")
        self.notify(f"STATUS=run log losing rows: {why}")


def read_log(path: str | None) -> dict[str, Any] | None:
    """The run log's columns, or None (no log, unreadable)."""
    if not path:
        return None
    from mrctl.runlog.read import read_run

    try:
        return read_run(path)
    except Exception:  # noqa: BLE001 - figures are a bonus; the log itself was reported
        return None


def tracking(path: str | None, I_max: float, settle_s: float,
             cols: dict[str, Any] | None = None) -> dict[str, float] | None:
    """The tracking figures of a run log, or None (no log, too short, unreadable)."""
    cols = cols if cols is not None else read_log(path)
    if cols is None or len(cols.get("t", ())) < 2:
        return None
    F, _ = tracked_force(cols)
    try:
        return tracking_summary(cols["t"], cols["F_des"], F, cols["I"], I_max, settle_s)
    except Exception:  # noqa: BLE001
        return None


def verdict_exit(v: dict[str, Any], exit_code: int) -> int:
    """The exit code after a verdict: 5 for a degraded run that would
    otherwise exit 0; a worse ending keeps its own code."""
    return exit_code or (ExitCode.DEGRADED if v["verdict"] == "degraded" else exit_code)


def close_log(rec: Any, out: str, summary: dict[str, Any], exit_code: int, messages: list[str], *,
              I_max: float, settle_s: float, say: Callable[[str], None], warn: Callable[[str], None],
              format_tracking: Callable[[dict[str, float]], str],
              verdict: Callable[[dict[str, Any] | None, dict[str, float] | None], dict[str, Any]] | None = None,
              extra: dict[str, Any] | None = None) -> int:
    """Drain the recorder, judge the log, write the final sidecar once;
    returns the exit code (4 if anything was lost and nothing worse happened,
    5 if the run broke an acceptance bound and nothing worse happened).

    ``verdict(cols, tracking)`` judges the run from its rows (None when the
    log cannot be read) and its tracking figures
    (:func:`mrctl.runlog.acceptance.judge`'s dict); ``extra``: top-level
    keys of the sidecar (the run's requested and actual duration, the signal
    that stopped it)."""
    st = rec.close(write_sidecar=False)
    lost = st["dropped_rows"]
    if st["error"] or lost:
        warn(f"run log incomplete: {lost} of {st['ticks']} rows lost{tick_span(st)}"
             + (f"; {st['error']}" if st["error"] else "") + "; the sidecar records it")
        exit_code = exit_code or ExitCode.LOG
    cols = read_log(out)
    track = tracking(out, I_max, settle_s, cols)
    if track:
        summary["tracking"] = track
        say(format_tracking(track))
    extra = dict(extra or {})
    if verdict is not None:
        v = verdict(cols, track)
        exit_code = verdict_exit(v, exit_code)
        summary["acceptance"] = v
        extra.update(verdict=v["verdict"], verdict_reasons=v["reasons"])
    summary["exit_code"] = exit_code
    summary["messages"] = messages[-50:]
    err = rec.write_sidecar(summary, extra={"exit_code": exit_code, **extra})
    if err:
        warn(f"could not write the sidecar {sidecar_path(out)}: {err}; the run log has {st['rows_written']} "
             f"rows written and {lost} lost{tick_span(st)} of {st['ticks']} ticks; exit {exit_code or ExitCode.LOG}")
        exit_code = exit_code or ExitCode.LOG
    elif not lost and not st["error"]:
        say(f"wrote {out} ({st['rows_written']} rows) and its .json sidecar")
    return exit_code
