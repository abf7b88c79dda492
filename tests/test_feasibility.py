"""Start-up feasibility: wire time arithmetic, probe, decision and messages."""

import time
from types import SimpleNamespace

import pytest

from mrctl.daemon.feasibility import assess, probe, wire_time_s
from mrctl.io.base import LinkTimeout, Sample


def test_serial_wire_time_from_frame_sizes():
    w921 = wire_time_s(SimpleNamespace(type="serial", baudrate=921600))
    w115 = wire_time_s(SimpleNamespace(type="serial", baudrate=115200))
    assert w115 == pytest.approx(w921 * 8)  # linear in 1/baud
    assert assess(1000.0, w921).ok
    f = assess(1000.0, w115)
    assert not f.ok and f.suggested_rate_hz == 100.0
    assert "does not fit 1000 Hz" in f.message and "100 Hz" in f.message


def test_modbus_rtu_115200_cannot_do_1khz():
    from mrctl.io.registers import default_register_map

    cfg = SimpleNamespace(type="modbus-rtu", baudrate=115200, use_fc23=None, register_map=default_register_map())
    w = wire_time_s(cfg)
    assert w > 3.2e-3  # the 37-byte figure is a floor; 8E1 and gaps add more
    f = assess(1000.0, w, what="modbus-rtu 115200 Bd")
    assert not f.ok and f.suggested_rate_hz is not None and f.suggested_rate_hz <= 200.0


def test_tcp_and_sim_have_no_wire_limit():
    assert wire_time_s(SimpleNamespace(type="modbus-tcp")) is None
    assert wire_time_s(SimpleNamespace(type="sim")) is None


class SlowLink:
    split = False  # an exchange link (mrctl.io.base.Link)

    def __init__(self, delay_s, fail_every=0):
        self.delay_s, self.fail_every, self.n, self.setpoints = delay_s, fail_every, 0, []

    def exchange(self, I):
        self.n += 1
        self.setpoints.append(I)
        if self.fail_every and self.n % self.fail_every == 0:
            raise LinkTimeout("x")
        time.sleep(self.delay_s)
        return Sample(self.n, 0.0, 0.0, 0.0, float("nan"), 0)


def test_probe_sends_only_zero_amps_and_measures():
    link = SlowLink(0.002)
    rtts, errors = probe(link, 20)
    assert errors == 0 and len(rtts) == 20 and min(rtts) >= 0.002
    assert set(link.setpoints) == {0.0}
    f = assess(1000.0, None, rtts)
    assert not f.ok and f.suggested_rate_hz is not None and f.suggested_rate_hz <= 250.0
    assert "measured round trip" in f.message


def test_unreliable_and_dead_links_are_refused():
    rtts, errors = probe(SlowLink(0.0, fail_every=3), 30)
    assert errors == 10
    f = assess(100.0, None, rtts, errors)
    assert not f.ok and "unreliable" in f.message
    f = assess(100.0, None, [], 30)
    assert not f.ok and "no reply" in f.message


def test_a_tail_beyond_the_budget_warns_but_the_median_decides():
    rtts = [0.0002] * 95 + [0.003] * 5  # p50 0.2 ms, p99 3 ms
    f = assess(1000.0, 0.0006, rtts)
    assert f.ok and "warning: the p99 exceeds" in f.message
    f = assess(1000.0, 0.0006, [0.0012] * 100)  # the median itself does not fit
    assert not f.ok and f.suggested_rate_hz == 500.0


def test_device_pacing_check_refuses_a_device_that_ignores_sync():
    import time as _time

    from mrctl.daemon.feasibility import check_device_pacing

    class Link:
        split = False

        def __init__(self, gap_s):
            self.gap_s = gap_s

        def exchange(self, I):
            end = _time.perf_counter() + self.gap_s
            while _time.perf_counter() < end:
                pass

    why = check_device_pacing(Link(0.0), 1e-3)
    assert why is not None and "ignores the SYNC flag" in why and "loop.pacing: host" in why
    assert check_device_pacing(Link(1e-3), 1e-3) is None


def test_probe_timeouts_suggest_a_lower_rate_and_every_refusal_says_what_to_try():
    """Timeouts in the probe are a slow link (or host): a lower rate is
    suggested, which link.on_infeasible: reduce_rate takes; other failures
    leave no rate to suggest. Either way the message says what to try."""
    timeouts: list[int] = []
    t = iter(range(0, 10**6, 100))  # a virtual clock: 100 us per reading
    rtts, errors = probe(SlowLink(0.0, fail_every=3), 30, clock=lambda: next(t) * 1e-6, timeouts=timeouts)
    assert errors == 10 and timeouts == [10]
    assert rtts == [pytest.approx(1e-4)] * 20  # measured on the clock handed in
    f = assess(1000.0, None, rtts, errors, timeouts=timeouts[0])
    assert not f.ok and f.suggested_rate_hz == 500.0
    assert "10 timeouts" in f.message and "reduce_rate" in f.message and "cable" in f.message
    f = assess(1000.0, None, rtts, errors, timeouts=0)  # not timeouts: no rate helps
    assert not f.ok and f.suggested_rate_hz is None
    assert "unreliable" in f.message and "lower rate_hz" in f.message and "cable" in f.message
