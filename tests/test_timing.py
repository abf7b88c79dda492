"""TimingStats: ring storage, exact whole-run counters, numpy percentiles, snapshots."""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mrctl.daemon.timing import LIVE_WINDOW, TimingStats, format_summary


def test_percentiles_match_numpy_on_known_data() -> None:
    rng = np.random.default_rng(1)
    late = rng.integers(0, 2_000_000, size=5000)
    comp = rng.integers(1_000, 90_000, size=5000)
    s = TimingStats(capacity=10_000)
    for a, b in zip(late.tolist(), comp.tolist()):
        s.record(a, b, 1_000_000, False, 0)
    d = s.summary()
    assert d["ticks"] == d["samples"] == 5000
    for name, data in (("lateness", late), ("compute", comp)):
        us = data / 1e3
        for key, q in (("p50", 50), ("p99", 99), ("p999", 99.9)):
            assert d[f"{name}_{key}_us"] == pytest.approx(np.percentile(us, q), rel=1e-12)
        assert d[f"{name}_max_us"] == pytest.approx(us.max())
    assert d["longest_gap_us"] == 1000.0


def test_simple_percentiles_by_hand() -> None:
    s = TimingStats(capacity=100)
    for i in range(1, 101):  # 1..100 µs
        s.record(i * 1000, 0, 0, False, 0)
    d = s.summary()
    assert d["lateness_p50_us"] == pytest.approx(50.5)
    assert d["lateness_p99_us"] == pytest.approx(99.01)
    assert d["lateness_max_us"] == 100.0


def test_ring_wraps_and_keeps_time_order() -> None:
    s = TimingStats(capacity=7)
    for i in range(20):
        s.record(i, 10 * i, 0, False, 0)
    snap = s.snapshot()
    assert list(snap.late_ns) == list(range(13, 20))
    assert list(snap.compute_ns) == [10 * i for i in range(13, 20)]
    assert list(s.snapshot(3).late_ns) == [17, 18, 19]
    # 20 % 7 == 6: a window of 6 ends exactly at the ring's start, 7 wraps.
    assert list(s.snapshot(6).late_ns) == list(range(14, 20))
    assert list(s.snapshot(100).late_ns) == list(range(13, 20))
    assert list(s.snapshot(0).late_ns) == []
    assert snap.ticks == 20


def test_max_and_counts_are_exact_over_whole_run_after_wrap() -> None:
    s = TimingStats(capacity=100)
    for i in range(250):
        late = 9_999_000 if i == 10 else 1000
        comp = 7_000_000 if i == 20 else 2000
        gap = 5_000_000 if i == 30 else 1_000_000
        over = i % 50 == 0
        s.record(late, comp, gap, over, 3 if over else 0)
    d = s.summary()
    assert d["samples"] == 100 and d["ticks"] == 250
    # The worst samples were overwritten in the ring but the maxima are exact.
    assert d["lateness_max_us"] == 9999.0
    assert d["compute_max_us"] == 7000.0
    assert d["longest_gap_us"] == 5000.0
    assert d["lateness_p999_us"] == pytest.approx(1.0)
    assert d["overruns"] == 5 and d["skipped_deadlines"] == 15


def test_negative_lateness_max() -> None:
    # Device-paced lateness is relative to the previous sample and may be < 0.
    s = TimingStats(capacity=4)
    s.record(-500, 1, 0, False, 0)
    s.record(-200, 1, 0, False, 0)
    assert s.summary()["lateness_max_us"] == -0.2


def test_empty_summary_and_formatting() -> None:
    s = TimingStats(capacity=10)
    d = s.summary()
    assert d["ticks"] == 0 and d["lateness_p99_us"] is None and d["lateness_max_us"] is None
    assert "ticks 0" in format_summary(d)
    assert "ticks=0" in s.live_line()
    for i in range(3):
        s.record(1000 * i, 500, 1_000_000, i == 2, 1 if i == 2 else 0)
    text = format_summary(s.summary())
    assert "lateness" in text and "compute" in text and "overruns 1" in text
    line = s.live_line()
    assert "\n" not in line and "overruns=1" in line and "skipped=1" in line


def test_reset_reuses_buffers() -> None:
    s = TimingStats(capacity=5)
    buf = s._late
    for i in range(8):
        s.record(i, i, i, True, 1)
    s.reset()
    assert s._late is buf
    assert s.summary()["ticks"] == 0 and s.overruns == 0


def test_live_line_uses_recent_window() -> None:
    s = TimingStats(capacity=LIVE_WINDOW * 3)
    for _ in range(LIVE_WINDOW):
        s.record(900_000, 0, 0, False, 0)  # old: 900 µs late
    for _ in range(LIVE_WINDOW):
        s.record(1_000, 0, 0, False, 0)  # last second: 1 µs late
    assert "late p50/p99/max=1.0/1.0/900.0us" in s.live_line()


@settings(max_examples=50, deadline=None)
@given(cap=st.integers(1, 20), values=st.lists(st.integers(-(2**40), 2**40), max_size=60),
       last_n=st.one_of(st.none(), st.integers(0, 30)))
def test_snapshot_is_tail_of_recorded(cap: int, values: list[int], last_n: int | None) -> None:
    s = TimingStats(capacity=cap)
    for v in values:
        s.record(v, -v, 0, False, 0)
    held = values[-cap:] if values else []
    want = held if last_n is None else (held[max(0, len(held) - last_n):] if last_n else [])
    snap = s.snapshot(last_n)
    assert list(snap.late_ns) == want
    assert list(snap.compute_ns) == [-v for v in want]
    assert snap.ticks == len(values)


def test_snapshot_is_consistent_while_another_thread_records() -> None:
    """Every snapshot is a cut between two record() calls: counters match samples."""
    cap = 500
    total = 60_000
    s = TimingStats(capacity=cap)
    done = threading.Event()

    def writer() -> None:
        for i in range(total):
            s.record(i, 2 * i, i, i % 7 == 0, 2 if i % 7 == 0 else 0)
            if i % 1000 == 0:
                time.sleep(0)  # yield the GIL so the reader surely runs mid-stream
        done.set()

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # force frequent thread switches
    try:
        t = threading.Thread(target=writer)
        t.start()
        checked = 0
        mid_run = 0
        while not done.is_set() or checked == 0:
            snap = s.snapshot()
            n = snap.ticks
            late = list(snap.late_ns)
            assert late == list(range(max(0, n - cap), n))
            assert list(snap.compute_ns) == [2 * x for x in late]
            if n:
                assert snap.max_late_ns == n - 1 and snap.max_gap_ns == n - 1
                assert snap.overruns == (n - 1) // 7 + 1
                assert snap.skipped_deadlines == 2 * snap.overruns
                mid_run += n < total
            checked += 1
        t.join()
    finally:
        sys.setswitchinterval(old)
    assert s.snapshot().ticks == total
    assert mid_run > 0  # at least one snapshot really raced the writer
