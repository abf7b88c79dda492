"""FixedRateLoop scheduling (fake clock, deterministic) and rt.apply_rt.

No test asserts real wall-clock latencies: the machine is shared and noisy.
"""

from __future__ import annotations

import gc
import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from mrctl.daemon import rt
from mrctl.daemon.loop import FixedRateLoop

P = 1_000_000  # period at 1 kHz, ns
T0 = 5_000_000_000


class FakeClock:
    """Monotonic ns clock that advances only when read (read_ns) or slept on.

    ``jitter()`` gives the extra ns each sleep oversleeps by (default 0).
    """

    def __init__(self, read_ns: int = 100, jitter=lambda: 0) -> None:
        self.t = T0
        self.read_ns = read_ns
        self.jitter = jitter
        self.reads = 0
        self.sleeps: list[tuple[int, int, int]] = []  # (t at call, requested ns, jitter ns)

    def __call__(self) -> int:
        t = self.t
        self.t += self.read_ns
        self.reads += 1
        return t

    def sleep(self, s: float) -> None:
        req = round(s * 1e9)
        assert req >= 0
        j = self.jitter()
        self.sleeps.append((self.t, req, j))
        self.t += req + j

    def work(self, ns: int) -> None:
        """Simulate a tick's compute time."""
        self.t += ns


def no_sleep(s: float) -> None:
    raise AssertionError("spin strategy must never sleep")


def make(clock: FakeClock, wait: str = "sleep", **kw) -> FixedRateLoop:
    return FixedRateLoop(1000.0, wait=wait, clock=clock, sleep=clock.sleep, **kw)


# --------------------------------------------------------------- deadlines


def test_deadlines_are_absolute_no_drift_over_100k_ticks() -> None:
    """Wake k == start + k·period + that tick's own oversleep: errors never add up."""
    rng = random.Random(42)
    clk = FakeClock(read_ns=37, jitter=lambda: rng.randrange(0, 150_000))
    work = random.Random(7)
    loop = make(clk, "sleep")
    wakes: list[int] = []
    ks: list[int] = []

    def tick(k: int, now: int) -> bool:
        ks.append(k)
        wakes.append(now)
        clk.work(work.randrange(0, 700_000))  # variable compute, always < period - jitter
        return True

    n = loop.run(tick, max_ticks=100_000)
    assert n == 100_000
    assert ks == list(range(100_000))
    t0 = loop.t_start_ns
    # Tick 0 is due at once; every later tick sleeps exactly once (the fake
    # sleep never returns early), so its lateness is exactly its own oversleep
    # plus the one clock read between computing and starting the sleep:
    # nothing is carried over from earlier ticks.
    assert len(clk.sleeps) == n - 1
    for k in range(1, n):
        assert wakes[k] - (t0 + k * P) == clk.read_ns + clk.sleeps[k - 1][2]
    late = [w - (t0 + k * P) for k, w in zip(ks, wakes)]
    assert 0 <= min(late) and max(late) < 150_000 + clk.read_ns
    assert wakes[-1] - t0 - 99_999 * P < 150_000 + clk.read_ns  # no drift after 100 s
    assert loop.stats.overruns == 0 and loop.stats.skipped_deadlines == 0


def test_period_rounding_non_integer_rate() -> None:
    clk = FakeClock(read_ns=0)
    loop = FixedRateLoop(3000.0, wait="sleep", clock=clk, sleep=clk.sleep)
    assert loop.period_ns == 333_333
    wakes: list[int] = []
    loop.run(lambda k, now: wakes.append(now), max_ticks=10_000)
    assert [w - loop.t_start_ns for w in wakes] == [k * 333_333 for k in range(10_000)]


# --------------------------------------------------------------- overruns


def test_overrun_is_counted_and_schedule_skips_forward() -> None:
    clk = FakeClock(read_ns=100)
    loop = make(clk, "sleep")
    seen: list[tuple[int, int]] = []

    def tick(k: int, now: int) -> bool:
        seen.append((k, now))
        clk.work(int(2.5 * P) if k == 5 else 100_000)
        return True

    loop.run(tick, max_ticks=10)
    ks = [k for k, _ in seen]
    # Tick 5 ends at ~d5 + 2.5 P: deadlines 6 and 7 are skipped, no burst.
    assert ks == [0, 1, 2, 3, 4, 5, 8, 9, 10, 11]
    t0 = loop.t_start_ns
    k8_wake = dict(seen)[8]
    assert 0 <= k8_wake - (t0 + 8 * P) < 1_000  # woke at deadline 8, not at once
    assert loop.stats.overruns == 1
    assert loop.stats.skipped_deadlines == 2
    d = loop.stats.summary()
    assert d["overruns"] == 1 and d["skipped_deadlines"] == 2
    assert d["longest_gap_us"] == pytest.approx(3000, abs=1)
    assert d["compute_max_us"] == pytest.approx(2500, abs=1)


def test_several_overruns_and_late_wakeup_counted() -> None:
    # A sleep that oversleeps past the next deadline is a missed deadline too.
    over = iter([0, 0, int(1.2 * P)] + [0] * 100)
    clk = FakeClock(read_ns=0, jitter=lambda: next(over))
    loop = make(clk, "sleep")
    ks: list[int] = []

    def tick(k: int, now: int) -> bool:
        ks.append(k)
        clk.work(int(1.5 * P) if k in (10, 20) else 10_000)
        return True

    loop.run(tick, max_ticks=30)
    assert loop.stats.overruns == 3
    # k=3 woken 1.2 P late ends past d4 -> d5; k=10 and k=20 end at +1.5 P -> skip 1 each
    assert ks[:5] == [0, 1, 2, 3, 5]
    assert 11 not in ks and 21 not in ks and 12 in ks
    assert loop.stats.skipped_deadlines == 3


def test_ending_exactly_on_next_deadline_is_not_an_overrun() -> None:
    clk = FakeClock(read_ns=0)
    loop = make(clk, "sleep")
    ks: list[int] = []

    def tick(k: int, now: int) -> bool:
        ks.append(k)
        clk.work(P)  # ends exactly at the next deadline
        return True

    loop.run(tick, max_ticks=5)
    assert ks == [0, 1, 2, 3, 4]
    assert loop.stats.overruns == 0
    assert clk.sleeps == []  # never had to wait


# --------------------------------------------------------------- ending the run


def test_stop_from_tick_ends_loop() -> None:
    clk = FakeClock()
    loop = make(clk)

    def tick(k: int, now: int) -> bool:
        if k == 10:
            loop.stop()
        return True

    assert loop.run(tick, max_ticks=1000) == 11
    assert loop.stopped
    assert loop.run(tick) == 0  # sticky: a stopped loop does not start again


def test_stop_from_signal_handler() -> None:
    clk = FakeClock()
    loop = make(clk)
    old = signal.signal(signal.SIGUSR1, lambda *_: loop.stop())
    try:
        def tick(k: int, now: int) -> bool:
            if k == 3:
                signal.raise_signal(signal.SIGUSR1)
            return True

        assert loop.run(tick) == 4
    finally:
        signal.signal(signal.SIGUSR1, old)


def test_stop_from_other_thread_real_clock() -> None:
    loop = FixedRateLoop(1000.0, wait="sleep")
    started = threading.Event()

    count = [0]

    def tick(k: int, now: int) -> bool:
        count[0] += 1
        if count[0] >= 5:  # count ticks, not k: k jumps on a noisy machine
            started.set()
        return True

    result: list[int] = []
    th = threading.Thread(target=lambda: result.append(loop.run(tick)))
    th.start()
    assert started.wait(10)
    loop.stop()
    th.join(10)
    assert not th.is_alive() and result[0] == count[0] >= 5


def test_tick_returning_false_stops_and_none_continues() -> None:
    clk = FakeClock()
    assert make(clk).run(lambda k, now: k < 4) == 5
    assert make(clk).run(lambda k, now: None, max_ticks=7) == 7


def test_max_ticks_and_duration() -> None:
    clk = FakeClock()
    assert make(clk).run(lambda k, now: True, max_ticks=0) == 0
    assert make(clk).run(lambda k, now: True, max_ticks=123) == 123
    ks: list[int] = []
    loop = make(clk)
    assert loop.run(lambda k, now: ks.append(k), duration_s=1.0) == 1000
    assert ks == list(range(1000))
    # duration counts deadlines, not ticks: skipped ones shorten the run
    ks.clear()

    def slow(k: int, now: int) -> bool:
        ks.append(k)
        clk.work(int(1.5 * P) if k == 0 else 0)
        return True

    assert make(clk).run(slow, duration_s=0.01) == 9
    assert ks == [0] + list(range(2, 10))
    # both limits: whichever comes first
    assert make(clk).run(lambda k, now: True, max_ticks=5, duration_s=1.0) == 5


# --------------------------------------------------------------- wait strategies


def test_spin_never_sleeps_and_wakes_right_at_deadline() -> None:
    clk = FakeClock(read_ns=500)
    loop = FixedRateLoop(1000.0, wait="spin", clock=clk, sleep=no_sleep)
    wakes: list[int] = []
    loop.run(lambda k, now: wakes.append(now), max_ticks=50)
    t0 = loop.t_start_ns
    for k, w in enumerate(wakes):
        assert 0 <= w - (t0 + k * P) <= clk.read_ns
    assert clk.reads > 50 * (P // 500) * 0.9  # it really polled the clock


def test_sleep_strategy_sleeps_to_deadline_without_spinning() -> None:
    clk = FakeClock(read_ns=100)
    loop = make(clk, "sleep")
    loop.run(lambda k, now: clk.work(200_000), max_ticks=20)
    t0 = loop.t_start_ns
    assert len(clk.sleeps) == 19  # tick 0 is due at once
    for i, (t, req, _) in enumerate(clk.sleeps, start=1):
        # slept exactly to the deadline (t is one clock read after computing req)
        assert t + req == t0 + i * P + clk.read_ns
    assert clk.reads == 1 + 20 * 3 - 1  # start, then pre-wait/after-sleep/end per tick


def test_sleep_strategy_resleeps_if_woken_early() -> None:
    clk = FakeClock(read_ns=0, jitter=lambda: 0)
    calls: list[float] = []

    def early_sleep(s: float) -> None:  # returns after half the time asked
        calls.append(s)
        clk.t += max(1, round(s * 1e9) // 2)

    loop = FixedRateLoop(1000.0, wait="sleep", clock=clk, sleep=early_sleep)
    wakes: list[int] = []
    loop.run(lambda k, now: wakes.append(now), max_ticks=3)
    assert all(w >= loop.t_start_ns + k * P for k, w in enumerate(wakes))
    assert len(calls) > 2


def test_hybrid_sleeps_to_margin_then_spins() -> None:
    clk = FakeClock(read_ns=1_000)
    margin_s = 3e-4
    loop = make(clk, "hybrid", spin_margin_s=margin_s)
    wakes: list[int] = []
    reads_per_tick: list[int] = []
    last = [0]

    def tick(k: int, now: int) -> bool:
        wakes.append(now)
        reads_per_tick.append(clk.reads - last[0])
        clk.work(100_000)
        last[0] = clk.reads
        return True

    loop.run(tick, max_ticks=20)
    t0 = loop.t_start_ns
    assert len(clk.sleeps) == 19
    for i, (t, req, _) in enumerate(clk.sleeps, start=1):
        assert t + req == t0 + i * P - 300_000 + clk.read_ns  # slept to deadline − margin
    for k, w in enumerate(wakes):
        assert 0 <= w - (t0 + k * P) <= clk.read_ns  # then spun up to the deadline
    # ~300 µs of spinning at 1 µs per clock read
    assert all(295 <= r <= 305 for r in reads_per_tick[1:])


def test_hybrid_skips_sleep_when_inside_margin() -> None:
    clk = FakeClock(read_ns=1_000)
    loop = make(clk, "hybrid", spin_margin_s=3e-4)
    loop.run(lambda k, now: clk.work(800_000), max_ticks=10)  # < 300 µs left each time
    assert clk.sleeps == []
    assert loop.stats.overruns == 0


def test_constructor_validation() -> None:
    with pytest.raises(ValueError):
        FixedRateLoop(0)
    with pytest.raises(ValueError):
        FixedRateLoop(1000, wait="yield")
    with pytest.raises(ValueError):
        FixedRateLoop(1000, spin_margin_s=-1)
    assert FixedRateLoop(1000).wait == "hybrid"


def test_stats_recorded_per_tick() -> None:
    clk = FakeClock(read_ns=0, jitter=lambda: 5_000)
    loop = make(clk, "sleep")
    loop.run(lambda k, now: clk.work(40_000), max_ticks=100)
    d = loop.stats.summary()
    assert d["ticks"] == 100
    assert d["lateness_p50_us"] == 5.0 and d["lateness_max_us"] == 5.0
    assert d["compute_p99_us"] == 40.0
    assert d["longest_gap_us"] == 1005.0  # tick 0 ran at once, tick 1 overslept


# --------------------------------------------------------------- device-paced


def test_device_paced() -> None:
    clk = FakeClock(read_ns=0)
    # The device delivers sample i at an absolute time; the loop blocks for it.
    gaps = [P] * 5 + [P + 200_000, P - 200_000] + [3 * P] + [P] * 4
    due = [T0 + sum(gaps[: i + 1]) for i in range(len(gaps))]
    it = iter(due)

    def wait_sample() -> object | None:
        t = next(it, None)
        if t is None:
            return None
        clk.t = max(clk.t, t)
        return {"t": t}

    seen: list[tuple[int, object]] = []

    def tick(n: int, now: int, sample: object) -> bool:
        seen.append((n, sample))
        clk.work(1_300_000 if n == 9 else 50_000)
        return True

    loop = FixedRateLoop(1000.0, clock=clk, sleep=no_sleep)
    n = loop.run_device_paced(wait_sample, tick)
    assert n == len(gaps) and [i for i, _ in seen] == list(range(n))
    assert seen[3][1] == {"t": due[3]}
    s = loop.stats.snapshot()
    # lateness: gap − period, relative to the previous sample (jitter)
    assert list(s.late_ns)[:8] == [0, 0, 0, 0, 0, 200_000, -200_000, 2 * P]
    # tick 9 overran (1.3 ms): sample 10 was already queued, read at once
    assert list(s.late_ns)[10] == 300_000 and list(s.late_ns)[11] == -300_000
    assert s.max_gap_ns == 3 * P
    # the 3 P gap: one overrun, 2 samples skipped; tick 9's compute: one overrun
    assert s.overruns == 2 and s.skipped_deadlines == 2


def test_device_paced_limits() -> None:
    clk = FakeClock(read_ns=0)

    def wait_sample() -> object:
        clk.t += P
        return 1

    loop = FixedRateLoop(1000.0, clock=clk, sleep=no_sleep)
    assert loop.run_device_paced(wait_sample, lambda n, now, s: True, max_ticks=17) == 17
    loop2 = FixedRateLoop(1000.0, clock=clk, sleep=no_sleep)
    assert loop2.run_device_paced(wait_sample, lambda n, now, s: True, duration_s=0.05) == 49
    loop3 = FixedRateLoop(1000.0, clock=clk, sleep=no_sleep)
    assert loop3.run_device_paced(wait_sample, lambda n, now, s: n < 2) == 3


# --------------------------------------------------------------- real clock smoke


def test_real_clock_smoke_hybrid() -> None:
    """200 ticks at 1 kHz on the real clock: functional facts only, no latencies."""
    loop = FixedRateLoop(1000.0, wait="hybrid")
    seen: list[tuple[int, int]] = []
    skipped_before: list[int] = []  # skips recorded by the earlier ticks, seen from each tick

    def tick(k: int, now: int) -> None:
        seen.append((k, now))
        skipped_before.append(loop.stats.skipped_deadlines)

    n = loop.run(tick, max_ticks=200)
    assert n == 200 and len(seen) == 200
    ks = [k for k, _ in seen]
    assert all(b > a for a, b in zip(ks, ks[1:]))
    t0 = loop.t_start_ns
    assert all(now >= t0 + k * loop.period_ns for k, now in seen)  # never early
    assert all(b[1] > a[1] for a, b in zip(seen, seen[1:]))
    d = loop.stats.summary()
    assert d["ticks"] == 200
    # k jumps exactly by the skips recorded so far (the last tick's own overrun,
    # if any, is counted after it and shows in no k)
    assert ks[-1] == 199 + skipped_before[-1]
    assert all(k == i + s for i, (k, s) in enumerate(zip(ks, skipped_before)))
    assert d["skipped_deadlines"] >= skipped_before[-1]


# --------------------------------------------------------------- rt


_RT_CHILD = textwrap.dedent(
    """
    import gc, json, os
    from mrctl.daemon import rt
    s = rt.RtSettings(fifo_priority=10, lock_memory=True,
                      cpus=frozenset(os.sched_getaffinity(0)), timer_slack_ns=1000,
                      gc_freeze=True, gc_disable=True)
    res = rt.apply_rt(s)
    inside = gc.isenabled()
    undo = rt.restore()
    print(json.dumps({"results": [r.__dict__ for r in res], "gc_inside": inside,
                      "gc_after": gc.isenabled(), "undo": undo,
                      "policy_after": os.sched_getscheduler(0)}))
    """
)


def test_apply_rt_for_real_reports_every_item() -> None:
    """Run in a child process so SCHED_FIFO/mlockall never leak into pytest."""
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root))
    out = subprocess.run([sys.executable, "-c", _RT_CHILD], capture_output=True,
                         text=True, env=env, timeout=60, check=True)
    d = json.loads(out.stdout)
    names = [r["name"] for r in d["results"]]
    assert sorted(names) == sorted(
        ["sched_fifo", "mlockall", "cpu_affinity", "timer_slack_ns", "gc_freeze", "gc_disable"])
    for r in d["results"]:
        assert isinstance(r["applied"], bool)
        assert isinstance(r["detail"], str) and r["detail"]  # refusals carry a reason
    assert d["gc_inside"] is False and d["gc_after"] is True
    assert d["policy_after"] == os.SCHED_OTHER  # restored (or never changed)
    byname = {r["name"]: r for r in d["results"]}
    assert byname["sched_fifo"]["requested"] == 10


def test_apply_rt_refusals_carry_reason_and_never_raise() -> None:
    res = rt.apply_rt(rt.RtSettings(fifo_priority=1000, cpus=frozenset({100_000}),
                                    timer_slack_ns=-5))
    assert [r.name for r in res] == ["cpu_affinity", "timer_slack_ns", "sched_fifo"]
    for r in res:
        assert r.applied is False and r.detail
        assert "REFUSED" in str(r)
    assert "range" in res[2].detail
    rt.restore()
    assert rt.apply_rt(rt.RtSettings()) == []  # nothing requested, nothing reported


def test_rt_applied_context_restores_gc() -> None:
    assert gc.isenabled()
    with rt.rt_applied(rt.RtSettings(gc_disable=True)) as res:
        assert [(r.name, r.applied) for r in res] == [("gc_disable", True)]
        assert not gc.isenabled()
    assert gc.isenabled()


def test_loop_thread_smoke_with_gc_disabled() -> None:
    # The intended composition: rt around the loop, in the loop thread.
    clk = FakeClock()
    loop = make(clk)
    with rt.rt_applied(rt.RtSettings(gc_disable=True)):
        assert loop.run(lambda k, now: True, max_ticks=10) == 10
    assert gc.isenabled()


@pytest.mark.parametrize("wait", ["spin", "hybrid"])
def test_idle_hook_runs_only_in_the_spin_phase(wait):
    """hil_sim serves its link from this hook: it must run while the loop
    waits for a deadline (and only then), never delaying a tick."""
    clk = FakeClock(read_ns=1000)
    events = []
    loop = FixedRateLoop(1000.0, wait=wait, spin_margin_s=2e-4, clock=clk, sleep=clk.sleep,
                         idle=lambda: events.append(("idle", clk.t)))
    loop.run(lambda k, now: events.append(("tick", k)), max_ticks=5)
    ticks = [e for e in events if e[0] == "tick"]
    idles = [e for e in events if e[0] == "idle"]
    assert len(ticks) == 5 and idles
    # each idle call followed a clock reading taken before the deadline of the
    # tick that came next (the fake clock advances read_ns per reading)
    next_k = None
    for e in reversed(events):
        if e[0] == "tick":
            next_k = e[1]
        else:
            assert next_k is not None, "idle after the last tick"
            assert e[1] - clk.read_ns < loop.t_start_ns + next_k * loop.period_ns
    if wait == "hybrid":  # the sleep covers all but the 0.2 ms margin
        assert len(idles) <= 5 * (200_000 // 1000 + 2)


@pytest.mark.parametrize("wait", ["sleep", "spin", "hybrid"])
def test_background_work_ends_before_the_wait_must_begin(wait):
    """The recorder formats its log in this hook: it is called once per
    tick with the moment the wait must begin (deadline, less the hybrid spin
    margin, less the guard), and only when that moment is still ahead."""
    clk = FakeClock(read_ns=1000)
    calls = []

    def background(until_ns):
        calls.append((clk.t, until_ns))
        clk.work(max(0, until_ns - clk.t - 5_000))  # use nearly all the time given

    loop = FixedRateLoop(1000.0, wait=wait, spin_margin_s=3e-4, clock=clk, sleep=clk.sleep,
                         background=background, background_guard_s=1e-4)
    loop.run(lambda k, now: clk.work(50_000), max_ticks=6)
    lead = 100_000 + (300_000 if wait == "hybrid" else 0)
    assert len(calls) == 5  # not before tick 0 (already due)
    for k, (t_call, until) in enumerate(calls, start=1):
        assert until == loop.t_start_ns + k * P - lead
        assert t_call < until
    st = loop.stats.summary()
    assert st["overruns"] == 0  # the work never pushed a tick past its deadline
    assert st["lateness_max_us"] < 10  # fake-clock reads only
