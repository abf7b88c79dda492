"""Controller on exchange links: one tick of latency, link loss, reconnects."""

import math

import pytest

from mrctl.core.controller import Controller
from mrctl.laws.demand import Viscous
from mrctl.io.base import Disconnected, LinkTimeout, Sample
from mrctl.laws.inverse import SmoothInverse
from mrctl.model.params import TABLE_I
from mrctl.core.safety import SafetyConfig, SafetySupervisor


class FakeExchangeLink:
    """A device answering exchanges; can go silent or vanish for a while."""

    split = False
    host_clocked = False
    true_force_N = math.nan

    def __init__(self, silent=(), gone=()):
        self.k = 0
        self.sent = []
        self.silent, self.gone = silent, gone
        self.opens = 0
        self.is_open = True

    def open(self):
        self.opens += 1
        self.is_open = True

    def close(self):
        self.is_open = False

    def exchange(self, I):
        k = self.k
        self.k += 1
        if k in self.gone or not self.is_open:
            raise Disconnected("unplugged")
        if k in self.silent:
            raise LinkTimeout("no reply")
        self.sent.append((k, I))
        v = 0.0628 * math.cos(2 * math.pi * k * 1e-3)
        return Sample(k, k * 1e-3, 0.0, v, math.nan, 0)


def _ctl(link, **kw):
    sup = SafetySupervisor(SafetyConfig(I_max=0.6, hold_ticks=3, auto_resume=True, resume_good_ticks=5))
    return Controller(link, SmoothInverse(TABLE_I, 0.6, 1e-3), Viscous(500.0), sup, 1e-3, **kw), sup


def test_exchange_sends_the_current_computed_on_the_previous_tick():
    link = FakeExchangeLink()
    ctl, _ = _ctl(link)
    ctl.tick(0, 0)
    I0 = ctl.I_next
    ctl.tick(1, 0)
    assert link.sent[0] == (0, 0.0) and link.sent[1] == (1, I0) and I0 > 0.0


def test_short_silence_is_held_then_zero_then_recovers():
    link = FakeExchangeLink(silent=set(range(100, 120)))
    ctl, sup = _ctl(link, link_loss_ticks=100)
    for k in range(300):
        assert ctl.tick(k, 0) is True
    sent = dict(link.sent)
    assert sent[121] == 0.0  # fault (hold 3) was active when the link came back
    assert sup.counters().faults_entered == 1 and any(sent[k] > 0 for k in range(200, 300))


def test_long_silence_means_the_driver_is_lost():
    link = FakeExchangeLink(silent=set(range(100, 10_000)))
    ctl, sup = _ctl(link, link_loss_ticks=50)
    results = [ctl.tick(k, 0) for k in range(200)]
    assert results.index(False) == 100 + 50  # the 51st consecutive failure ends the run
    assert "link lost" in ctl.stopped_reason and sup.in_fault


def test_disconnected_link_is_reopened_at_a_bounded_rate():
    link = FakeExchangeLink(gone=set(range(100, 130)))
    ctl, _ = _ctl(link, link_loss_ticks=100, reconnect_every_ticks=10)
    for k in range(300):
        assert ctl.tick(k, 0) is True
    assert ctl.reconnects == 3  # failures 1, 11, 21 of the 30-tick outage
    assert link.opens == 3


def test_safe_stop_retries_until_zero_amps_is_delivered():
    link = FakeExchangeLink(silent={0, 1, 2})  # the first three exchanges get no reply
    ctl, _ = _ctl(link)
    assert ctl.safe_stop() is None
    assert link.sent == [(3, 0.0)]
    dead = FakeExchangeLink(silent=set(range(10**6)))
    ctl, _ = _ctl(dead)
    err = ctl.safe_stop(budget_s=0.0, min_attempts=5)
    assert err is not None and "no reply" in err and "(5 attempts" in err and dead.k == 5


def test_device_paced_ticks_follow_the_device_counter():
    """Device pacing: the time axis is the device's sample counter (a device
    tick with no reply leaves a gap, as a skipped deadline does), a silent
    exchange is still a tick (held, counted), and the current computed from
    a sample goes out in the very next exchange."""
    from mrctl.daemon.loop import FixedRateLoop

    class Paced(FakeExchangeLink):
        def exchange(self, I):
            s = super().exchange(I)
            self.k += 1 if s.seq == 3 else 0  # the device ran on: seq 5 follows 3
            return Sample(1000 + s.seq, s.t_dev_s, s.x_m, s.v_mps, s.F_N, 0)

    link = Paced(silent={6})
    ctl, sup = _ctl(link)
    rows = []
    ctl.record = lambda *r: rows.append(r)
    loop = FixedRateLoop(1000.0, wait="sleep")
    assert loop.run_device_paced(ctl.acquire, ctl.tick_paced, max_ticks=8) == 8
    ks = [r[6] for r in rows]
    seqs = [r[7] for r in rows]
    assert seqs[:4] == [1000, 1001, 1002, 1003] and seqs[4] == 1005 and math.isnan(seqs[5])
    assert ks == [0, 1, 2, 3, 5, 6, 7, 8]  # seq-based; the silent tick takes the next index
    assert [r[0] for r in rows][:5] == pytest.approx([0.0, 1e-3, 2e-3, 3e-3, 5e-3])
    # each exchange carries the current computed on the previous tick
    assert [I for _, I in link.sent][1:4] == pytest.approx([r[5] for r in rows][0:3])
    assert sup.fault_bits == 0  # one silent tick is within the hold


def test_device_paced_failures_are_paced_by_the_host():
    """Device pacing with a link that fails at once (unplugged): no device
    clock paces the loop, so each failed tick comes one period after the
    previous one, and link_loss_s, held in ticks, lasts its real time."""
    from mrctl.daemon.loop import FixedRateLoop

    class Clock:
        t = 0

        def now(self):
            self.t += 1000  # 1 µs per reading
            return self.t

        def sleep(self, s):
            self.t += int(s * 1e9)

    clk = Clock()
    link = FakeExchangeLink(gone=set(range(3, 1000)))
    ctl, sup = _ctl(link)
    ctl.link_loss_ticks = 50
    ctl.record = lambda *r: None
    loop = FixedRateLoop(1000.0, wait="sleep", clock=clk.now, sleep=clk.sleep)
    ctl.loop = loop
    n = loop.run_device_paced(ctl.acquire, ctl.tick_paced, max_ticks=500)
    assert "link lost" in (ctl.stopped_reason or "")
    assert n == 3 + 51  # 3 good ticks, then link_loss_ticks + 1 failures
    # ... and those 51 failed ticks took 51 periods of the loop's clock, not 51 µs
    assert clk.t - loop.t_start_ns >= 50 * 1_000_000
