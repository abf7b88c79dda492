"""Per-tick timing statistics for the fixed-rate control loop.

Why this shape: the loop records one sample per tick at 1 kHz for hours, so
recording must be O(1), allocation-free (beyond CPython's own int boxing) and
numpy-free; all statistics are computed offline, in :meth:`TimingStats.summary`.

Storage is a ring of the **last N samples** in two preallocated ``array('q')``
buffers (lateness and compute time, ns), plus exact whole-run counters and
running maxima. The default capacity, 600 000 samples, is 10 minutes at 1 kHz
and costs 9.6 MB (2 × 8 B × 600 000), allocated once at construction (so
``mlockall`` can pin it). A ring was chosen over a reservoir sample because

* percentiles over a recent, contiguous window are what an operator watching
  a live daemon wants (a reservoir over a 24 h run hides a fresh regression);
* 600 000 samples give a p99.9 estimated from 600 tail samples — plenty;
* a reservoir needs a random number per tick on the hot path;
* the things a ring would forget — the worst lateness, worst compute time,
  longest gap between tick starts, overrun and skip counts — are kept
  exactly, for the whole run, as scalars.

Thread safety: :meth:`record` is called by the loop thread; :meth:`snapshot`,
:meth:`summary` and :meth:`live_line` may be called from any other thread
(e.g. a status socket). A ``threading.Lock`` makes every snapshot a
consistent cut *between two ticks*: its counters, maxima and samples all
describe the same first ``ticks`` ticks. The uncontended lock costs about
0.1 µs per tick. The loop thread can be held up for as long as a reader holds
the lock — copying a full 600 000-sample ring takes ~1–2 ms (it would hold the
GIL just as long without a lock) — so periodic status readers should use
``last_n`` (``live_line`` uses the last 1000 samples, a few µs).
"""

from __future__ import annotations

import threading
from array import array
from dataclasses import dataclass
from typing import Any

#: 10 minutes at 1 kHz; see the module docstring.
DEFAULT_CAPACITY = 600_000

#: Samples used by :meth:`TimingStats.live_line` (1 s at 1 kHz).
LIVE_WINDOW = 1000

_INT64_MIN = -(1 << 63)

_PERCENTILES = (("p50", 50.0), ("p99", 99.0), ("p999", 99.9))


@dataclass(frozen=True)
class TimingSnapshot:
    """A consistent copy of a :class:`TimingStats` (samples in time order, ns)."""

    late_ns: array
    compute_ns: array
    ticks: int
    overruns: int
    skipped_deadlines: int
    max_late_ns: int
    max_compute_ns: int
    max_gap_ns: int


class TimingStats:
    """Fixed-capacity recorder of per-tick lateness / compute time.

    Units: everything recorded is in integer nanoseconds; :meth:`summary`
    reports microseconds (float).
    """

    __slots__ = (
        "capacity",
        "_late",
        "_comp",
        "_lock",
        "ticks",
        "overruns",
        "skipped_deadlines",
        "max_late_ns",
        "max_compute_ns",
        "max_gap_ns",
    )

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = int(capacity)
        self._late = array("q", [0]) * self.capacity
        self._comp = array("q", [0]) * self.capacity
        self._lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        """Forget all samples and counters (buffers are reused, not reallocated)."""
        with self._lock:
            self.ticks = 0
            self.overruns = 0
            self.skipped_deadlines = 0
            # Start below any sample: device-paced lateness can be negative.
            self.max_late_ns = _INT64_MIN
            self.max_compute_ns = _INT64_MIN
            self.max_gap_ns = 0

    def record(
        self, late_ns: int, compute_ns: int, gap_ns: int, overrun: bool, skipped: int
    ) -> None:
        """Record one tick. O(1), no allocation; called from the loop's hot path.

        ``late_ns``: wake-up time − deadline; ``compute_ns``: tick return −
        wake-up; ``gap_ns``: this tick's start − previous tick's start (0 for
        the first); ``overrun``: the tick missed a deadline; ``skipped``:
        deadlines passed over because of it.
        """
        with self._lock:
            i = self.ticks % self.capacity
            self._late[i] = late_ns
            self._comp[i] = compute_ns
            self.ticks += 1
            if late_ns > self.max_late_ns:
                self.max_late_ns = late_ns
            if compute_ns > self.max_compute_ns:
                self.max_compute_ns = compute_ns
            if gap_ns > self.max_gap_ns:
                self.max_gap_ns = gap_ns
            if overrun:
                self.overruns += 1
                self.skipped_deadlines += skipped

    def snapshot(self, last_n: int | None = None) -> TimingSnapshot:
        """Copy the counters and the last ``last_n`` samples (all held if None)."""
        with self._lock:
            n = self.ticks
            held = min(n, self.capacity)
            m = held if last_n is None else max(0, min(int(last_n), held))
            end = n % self.capacity  # one past the newest sample, in ring coordinates
            start = end - m
            if start >= 0:
                late = self._late[start:end]
                comp = self._comp[start:end]
            else:  # window wraps around the ring's end
                late = self._late[start:] + self._late[:end]
                comp = self._comp[start:] + self._comp[:end]
            return TimingSnapshot(
                late_ns=late,
                compute_ns=comp,
                ticks=n,
                overruns=self.overruns,
                skipped_deadlines=self.skipped_deadlines,
                max_late_ns=self.max_late_ns,
                max_compute_ns=self.max_compute_ns,
                max_gap_ns=self.max_gap_ns,
            )

    def summary(self, last_n: int | None = None) -> dict[str, Any]:
        """Statistics in µs: percentiles over the held window, exact whole-run max.

        Keys: ``ticks``, ``samples`` (window size the percentiles use),
        ``overruns``, ``skipped_deadlines``, ``longest_gap_us``,
        ``lateness_{p50,p99,p999,max}_us``, ``compute_{p50,p99,p999,max}_us``.
        Percentiles are ``None`` when no tick was recorded. Uses numpy; never
        call it from the loop thread while the loop runs.
        """
        return summarize(self.snapshot(last_n))

    def live_line(self) -> str:
        """One status line: percentiles over the last second, whole-run counters."""
        d = self.summary(LIVE_WINDOW)
        return (
            f"ticks={d['ticks']} late p50/p99/max={_f(d['lateness_p50_us'])}/"
            f"{_f(d['lateness_p99_us'])}/{_f(d['lateness_max_us'])}us "
            f"compute p99/max={_f(d['compute_p99_us'])}/{_f(d['compute_max_us'])}us "
            f"gap max={_f(d['longest_gap_us'])}us "
            f"overruns={d['overruns']} skipped={d['skipped_deadlines']}"
        )


def summarize(s: TimingSnapshot) -> dict[str, Any]:
    """Turn a snapshot into the :meth:`TimingStats.summary` dict (numpy, offline)."""
    import numpy as np  # imported here: keeps numpy out of the loop's import path

    d: dict[str, Any] = {
        "ticks": s.ticks,
        "samples": len(s.late_ns),
        "overruns": s.overruns,
        "skipped_deadlines": s.skipped_deadlines,
        "longest_gap_us": s.max_gap_ns / 1e3 if s.ticks else None,
    }
    for name, buf, mx in (
        ("lateness", s.late_ns, s.max_late_ns),
        ("compute", s.compute_ns, s.max_compute_ns),
    ):
        if len(buf):
            a = np.frombuffer(buf, dtype=np.int64).astype(np.float64) / 1e3
            qs = np.percentile(a, [q for _, q in _PERCENTILES])
            for (key, _), v in zip(_PERCENTILES, qs):
                d[f"{name}_{key}_us"] = float(v)
        else:
            for key, _ in _PERCENTILES:
                d[f"{name}_{key}_us"] = None
        d[f"{name}_max_us"] = mx / 1e3 if s.ticks else None  # exact, whole run
    return d


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def format_summary(d: dict[str, Any]) -> str:
    """Multi-line human summary of :meth:`TimingStats.summary` for the end of a run."""
    lines = [
        f"ticks {d['ticks']}  (percentiles over last {d['samples']})",
        "              p50      p99    p99.9      max   (us)",
    ]
    for name in ("lateness", "compute"):
        vals = [d.get(f"{name}_{k}_us") for k in ("p50", "p99", "p999", "max")]
        lines.append(f"{name:<9}" + "".join(f"{_f(v):>9}" for v in vals))
    lines.append(
        f"overruns {d['overruns']}  skipped deadlines {d['skipped_deadlines']}  "
        f"longest gap between tick starts {_f(d['longest_gap_us'])} us"
    )
    return "\n".join(lines)
