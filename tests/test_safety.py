"""Safety supervisor: hold-over, FAULT → 0 A, recovery, clamp and slew."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import NamedTuple

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from mrctl.core.safety import (
    Fault,
    SafetyConfig,
    SafetyCounters,
    SafetyState,
    SafetySupervisor,
    clamp_current,
)

I_MAX = 1.0
DT = 1e-3


class S(NamedTuple):
    seq: int
    x_m: float = 0.0
    v_mps: float = 0.0
    F_N: float = math.nan
    status: int = 0


def cfg(**kw) -> SafetyConfig:
    base = dict(I_max=I_MAX, hold_ticks=3, max_age_s=5e-3,
                x_range_m=(-0.02, 0.02), v_range_mps=(-1.0, 1.0), F_range_N=(-2000.0, 2000.0))
    base.update(kw)
    return SafetyConfig(**base)


class Feed:
    """Drives a supervisor with good samples (advancing seq) and bad ones by kind."""

    def __init__(self, sup: SafetySupervisor, seq0: int = 0) -> None:
        self.sup = sup
        self.seq = seq0
        self.good_seq = seq0  # seq of the last good sample fed

    def _next(self) -> int:
        self.seq = (self.seq + 1) % 2**32
        return self.seq

    def good(self, I: float = 0.5, x: float = 0.001):
        s = S(self._next(), x_m=x)
        self.good_seq = s.seq
        used = self.sup.check_sample(s, 1e-4)
        return used, self.sup.limit(I if used is not None else 0.0), s

    def bad(self, kind: str, I: float = 0.5):
        sup = self.sup
        if kind == "missing":
            used = sup.check_sample(None, 0.0)
        elif kind == "late":
            used = sup.check_sample(S(self._next()), 0.1)
        elif kind == "late_nan_age":
            used = sup.check_sample(S(self._next()), math.nan)
        elif kind == "stale":
            used = sup.check_sample(S(self.good_seq), 1e-4)  # repeats the last good seq
        elif kind == "backwards":
            used = sup.check_sample(S((self.good_seq - 5) % 2**32), 1e-4)
        elif kind == "nan_x":
            used = sup.check_sample(S(self._next(), x_m=math.nan), 1e-4)
        elif kind == "inf_v":
            used = sup.check_sample(S(self._next(), v_mps=-math.inf), 1e-4)
        elif kind == "inf_F":
            used = sup.check_sample(S(self._next(), F_N=math.inf), 1e-4)
        elif kind == "range_x":
            used = sup.check_sample(S(self._next(), x_m=0.5), 1e-4)
        elif kind == "range_v":
            used = sup.check_sample(S(self._next(), v_mps=-3.0), 1e-4)
        elif kind == "range_F":
            used = sup.check_sample(S(self._next(), F_N=1e5), 1e-4)
        else:  # pragma: no cover
            raise AssertionError(kind)
        return used, sup.limit(I if used is not None else 0.0)


BAD_KINDS = {
    "missing": Fault.MISSING,
    "late": Fault.LATE,
    "late_nan_age": Fault.LATE,
    "stale": Fault.STALE,
    "backwards": Fault.STALE,
    "nan_x": Fault.NON_FINITE,
    "inf_v": Fault.NON_FINITE,
    "inf_F": Fault.NON_FINITE,
    "range_x": Fault.OUT_OF_RANGE,
    "range_v": Fault.OUT_OF_RANGE,
    "range_F": Fault.OUT_OF_RANGE,
}


# --------------------------------------------------------------- clamp_current

@pytest.mark.parametrize("I, expected", [
    (math.nan, 0.0), (-1.0, 0.0), (-math.inf, 0.0), (math.inf, 0.6), (0.3, 0.3), (0.6, 0.6), (7.0, 0.6),
])
def test_clamp_current(I, expected):
    assert clamp_current(I, 0.6) == expected


@pytest.mark.parametrize("I, expected", [
    (math.nan, 0.0), (-1.0, 0.0), (-math.inf, 0.0), (math.inf, I_MAX), (0.3, 0.3), (5.0, I_MAX),
])
def test_limit_clamps_without_slew(I, expected):
    sup = SafetySupervisor(cfg())
    assert sup.check_sample(S(1), 0.0) is not None
    assert sup.limit(I) == expected


# ------------------------------------------------------------ hold-over / fault

@pytest.mark.parametrize("hold", [0, 1, 3, 5])
@pytest.mark.parametrize("kind", sorted(BAD_KINDS))
def test_fault_exactly_after_hold(kind, hold):
    sup = SafetySupervisor(cfg(hold_ticks=hold))
    f = Feed(sup, seq0=100)
    for _ in range(4):
        f.good()
    _, out, last_good = f.good(I=0.5)
    assert out == 0.5 and sup.state is SafetyState.OK
    for i in range(hold):  # bad ticks 1..hold: the law still runs, on the last good sample
        used, out = f.bad(kind)
        assert used is last_good, i
        assert out == 0.5
        assert sup.state is SafetyState.HOLDING
        assert sup.fault is Fault.NONE and sup.reason == ""
    used, out = f.bad(kind, I=0.9)  # bad tick hold+1: FAULT, 0 A
    assert used is None and out == 0.0
    assert sup.state is SafetyState.FAULT and sup.in_fault
    assert sup.fault == BAD_KINDS[kind]
    assert sup.reason and "latched" in sup.reason
    c = sup.counters()
    assert c.faults_entered == 1 and c.holds_used == hold and c.bad == hold + 1
    assert c.ticks_in_fault == 1 and c.longest_bad_run == hold + 1


def test_hold_zero_faults_on_first_bad_sample():
    sup = SafetySupervisor(cfg(hold_ticks=0))
    f = Feed(sup)
    f.good()
    used, out = f.bad("missing")
    assert used is None and out == 0.0 and sup.in_fault


def test_counters_by_kind():
    sup = SafetySupervisor(cfg(hold_ticks=100))
    f = Feed(sup)
    f.good()
    for kind in ["missing", "missing", "late", "stale", "nan_x", "range_v"]:
        f.bad(kind)
    c = sup.counters()
    assert (c.good, c.missing, c.late, c.stale, c.non_finite, c.out_of_range) == (1, 2, 1, 1, 1, 1)
    assert c.bad == 6 and c.holds_used == 6 and c.faults_entered == 0
    d = c.as_dict()
    assert d["bad"] == 6 and d["missing"] == 2
    assert isinstance(c, SafetyCounters)


@given(st.lists(st.integers(min_value=1, max_value=5), min_size=1, max_size=30),
       st.integers(min_value=0, max_value=5),
       st.sampled_from(sorted(BAD_KINDS)))
@settings(max_examples=60, deadline=None)
def test_intermittent_bad_shorter_than_hold_never_faults(bursts, hold_extra, kind):
    hold = max(bursts) + hold_extra
    sup = SafetySupervisor(cfg(hold_ticks=hold))
    f = Feed(sup)
    f.good()
    for n in bursts:
        for _ in range(n):
            used, out = f.bad(kind)
            assert used is not None and out == 0.5
        used, out, s = f.good()
        assert used is s and out == 0.5
    assert sup.counters().faults_entered == 0
    assert sup.counters().longest_bad_run == max(bursts)


def test_one_good_sample_restarts_the_hold():
    sup = SafetySupervisor(cfg(hold_ticks=2))
    f = Feed(sup)
    f.good()
    for _ in range(5):
        f.bad("missing")
        f.bad("nan_x")  # a mixed run of 2 is still within the hold
        f.good()
    assert not sup.in_fault
    f.bad("missing"); f.bad("late")
    used, _ = f.bad("range_x")
    assert used is None and sup.fault == Fault.MISSING | Fault.LATE | Fault.OUT_OF_RANGE


def test_starting_outputs_zero_and_bad_start_faults():
    sup = SafetySupervisor(cfg(hold_ticks=2))
    assert sup.state is SafetyState.STARTING
    assert sup.limit(0.7) == 0.0  # limit before any check: 0 A
    for _ in range(2):  # nothing to hold yet: 0 A, but not (yet) a fault
        assert sup.check_sample(None) is None
        assert sup.limit(0.7) == 0.0
        assert sup.state is SafetyState.STARTING
    assert sup.check_sample(None) is None
    assert sup.in_fault and sup.fault is Fault.MISSING


def test_first_sample_starts_running():
    sup = SafetySupervisor(cfg())
    s = S(12345)
    assert sup.check_sample(s, 0.0) is s
    assert sup.state is SafetyState.OK and sup.limit(0.4) == 0.4


# ------------------------------------------------------------------- staleness

@pytest.mark.parametrize("prev, new, advancing", [
    (2**32 - 1, 0, True),  # wrap-around
    (2**32 - 3, 5, True),
    (10, 11, True),
    (10, 10 + 2**31 - 1, True),  # largest forward jump
    (10, 10 + 2**31, False),  # half the ring: ambiguous → not advancing
    (10, 10, False),  # repeated
    (10, 9, False),  # backwards
    (0, 2**32 - 1, False),  # backwards across the wrap
])
def test_seq_wraparound(prev, new, advancing):
    sup = SafetySupervisor(cfg(hold_ticks=0))
    assert sup.check_sample(S(prev), 0.0) is not None
    used = sup.check_sample(S(new), 0.0)
    assert (used is not None) == advancing
    assert sup.in_fault == (not advancing)
    if not advancing:
        assert sup.fault is Fault.STALE


def test_stale_is_judged_against_last_good_sample():
    sup = SafetySupervisor(cfg(hold_ticks=5))
    assert sup.check_sample(S(10), 0.0) is not None
    assert sup.check_sample(S(11, x_m=math.nan), 0.0) is not None  # bad (held): not a reference
    assert sup.check_sample(S(11), 0.0).seq == 11  # advancing vs 10: good
    assert sup.counters().stale == 0


# -------------------------------------------------------- non-finite / ranges

def test_force_nan_allowed_without_load_cell_required_with():
    s = S(1, F_N=math.nan)
    assert SafetySupervisor(cfg()).check_sample(s, 0.0) is s
    sup = SafetySupervisor(cfg(require_force=True, hold_ticks=0))
    assert sup.check_sample(s, 0.0) is None and sup.fault is Fault.NON_FINITE
    sup = SafetySupervisor(cfg(require_force=True))
    assert sup.check_sample(S(1, F_N=10.0), 0.0) is not None


def test_ranges_optional_and_inclusive():
    huge = S(1, x_m=1e9, v_mps=-1e9, F_N=1e12)
    assert SafetySupervisor(SafetyConfig(I_max=1.0)).check_sample(huge, 0.0) is huge
    sup = SafetySupervisor(cfg(hold_ticks=0))
    assert sup.check_sample(S(1, x_m=0.02, v_mps=-1.0, F_N=2000.0), 0.0) is not None


def test_age_unchecked_when_not_configured():
    sup = SafetySupervisor(cfg(max_age_s=None, hold_ticks=0))
    assert sup.check_sample(S(1), 10.0) is not None


def test_device_status_mask():
    sup = SafetySupervisor(cfg(status_fault_mask=0b11, hold_ticks=0))
    assert sup.check_sample(S(1, status=0b1000), 0.0) is not None
    assert sup.check_sample(S(2, status=0b10), 0.0) is None
    assert sup.fault is Fault.DEVICE_STATUS and sup.counters().device_status == 1
    # mask 0 ignores status; objects without .status are fine
    sup = SafetySupervisor(cfg(hold_ticks=0))
    assert sup.check_sample(S(1, status=0xFF), 0.0) is not None
    ns = SimpleNamespace(seq=1, x_m=0.0, v_mps=0.0, F_N=math.nan)
    assert SafetySupervisor(cfg(status_fault_mask=1)).check_sample(ns, 0.0) is ns


# --------------------------------------------------------------------- recovery

@pytest.mark.parametrize("resume_n", [1, 3, 10])
def test_auto_resume_after_exactly_n_good(resume_n):
    sup = SafetySupervisor(cfg(hold_ticks=1, auto_resume=True, resume_good_ticks=resume_n))
    f = Feed(sup)
    f.good()
    f.bad("missing"); f.bad("missing")
    assert sup.in_fault and "auto-resume" in sup.reason
    f.bad("missing")  # bad in fault: still 0 A
    for _ in range(resume_n - 1):
        used, out, _ = f.good()
        assert used is None and out == 0.0 and sup.in_fault
    f.bad("nan_x")  # a bad sample restarts the good count
    for _ in range(resume_n - 1):
        used, out, _ = f.good()
        assert used is None and sup.in_fault
    used, out, s = f.good(I=0.3)
    assert used is s and out == 0.3
    assert sup.state is SafetyState.OK and sup.fault is Fault.NONE and sup.reason == ""
    c = sup.counters()
    assert c.resumes == 1 and c.faults_entered == 1
    assert c.ticks_in_fault == 1 + 1 + 1 + 2 * (resume_n - 1)


def test_latched_stays_safe_until_reset():
    sup = SafetySupervisor(cfg(hold_ticks=0, auto_resume=False))
    f = Feed(sup)
    f.good()
    f.bad("late")
    for _ in range(50):
        used, out, _ = f.good()
        assert used is None and out == 0.0 and sup.in_fault
    assert sup.fault is Fault.LATE
    sup.reset()
    assert sup.state is SafetyState.STARTING and sup.fault is Fault.NONE
    used, out, s = f.good(I=0.2)
    assert used is s and out == 0.2
    assert sup.counters().resets == 1 and sup.counters().resumes == 0


def test_reset_forgets_seq_reference():
    sup = SafetySupervisor(cfg(hold_ticks=0))
    sup.check_sample(S(1_000_000), 0.0)
    assert sup.check_sample(S(0), 0.0) is None  # DAQ restarted its counter: stale
    sup.reset()
    assert sup.check_sample(S(0), 0.0) is not None


def test_driver_failed_latches_even_with_auto_resume():
    sup = SafetySupervisor(cfg(auto_resume=True, resume_good_ticks=1))
    f = Feed(sup)
    f.good()
    sup.driver_failed()
    assert sup.in_fault and sup.fault is Fault.DRIVER and "driver" in sup.reason
    assert sup.limit(0.5) == 0.0
    for _ in range(20):
        used, out, _ = f.good()
        assert used is None and out == 0.0
    assert sup.counters().faults_entered == 1
    sup.driver_failed()  # again while in fault: not a new fault
    assert sup.counters().faults_entered == 1
    sup.reset()
    assert f.good()[0] is not None


def test_driver_failure_during_sample_fault_adds_bit_and_latches():
    sup = SafetySupervisor(cfg(hold_ticks=0, auto_resume=True, resume_good_ticks=1))
    f = Feed(sup)
    f.good()
    f.bad("missing")
    sup.driver_failed()
    assert sup.fault == Fault.MISSING | Fault.DRIVER
    assert f.good()[0] is None  # would have auto-resumed without the driver fault


# ------------------------------------------------------------------------- slew

def test_slew_both_directions_and_fault_bypass():
    slew = 100.0  # A/s → 0.1 A per 1 ms tick
    sup = SafetySupervisor(cfg(max_slew_A_per_s=slew, hold_ticks=1))
    f = Feed(sup)
    outs = [f.good(I=1.0)[1] for _ in range(12)]
    assert outs[:10] == pytest.approx([0.1 * (k + 1) for k in range(10)])
    assert outs[10:] == [1.0, 1.0]
    outs = [f.good(I=0.0)[1] for _ in range(3)]
    assert outs == pytest.approx([0.9, 0.8, 0.7])
    assert f.good(I=math.nan)[1] == pytest.approx(0.6)  # NaN → 0 A target, still slewed
    assert sup.counters().cmd_non_finite == 1
    assert f.bad("missing", I=1.0)[1] == pytest.approx(0.7)  # hold: slewed as usual
    assert f.bad("missing", I=1.0)[1] == 0.0  # fault: straight to 0 A
    sup.reset()
    assert f.good(I=1.0)[1] == pytest.approx(0.1)  # ramps up again from 0 A


def test_driver_fault_output_zero_not_slewed():
    sup = SafetySupervisor(cfg(max_slew_A_per_s=1.0))
    f = Feed(sup)
    f.good(I=0.0)
    sup._last_out = 0.8  # pretend we got there (slow ramp)
    sup.driver_failed()
    assert sup.limit(0.8) == 0.0 and sup.last_output_A == 0.0


# ---------------------------------------------------------------------- config

@pytest.mark.parametrize("kw", [
    dict(I_max=0.0), dict(I_max=math.nan), dict(I_max=math.inf),
    dict(I_max=1.0, max_slew_A_per_s=0.0), dict(I_max=1.0, max_slew_A_per_s=math.nan),
    dict(I_max=1.0, hold_ticks=-1), dict(I_max=1.0, hold_ticks=1.5), dict(I_max=1.0, hold_ticks=True),
    dict(I_max=1.0, max_age_s=0.0), dict(I_max=1.0, max_age_s=math.nan),
    dict(I_max=1.0, x_range_m=(1.0, -1.0)), dict(I_max=1.0, F_range_N=(math.nan, 1.0)),
    dict(I_max=1.0, resume_good_ticks=0), dict(I_max=1.0, dt_s=0.0),
])
def test_config_rejects_nonsense(kw):
    with pytest.raises(ValueError):
        SafetyConfig(**kw)


def test_supervisor_has_slots():
    sup = SafetySupervisor(cfg())
    with pytest.raises(AttributeError):
        sup.foo = 1  # type: ignore[attr-defined]


# ----------------------------------------------------------- property: any input

_any_float = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-0.05, max_value=0.05),
    st.sampled_from([0.0, math.nan, math.inf, -math.inf, 1e308, -1e308]),
)
_small = st.floats(min_value=-0.02, max_value=0.02)
_good_sample = st.tuples(st.just(1), _small, _small, st.one_of(st.just(math.nan), st.floats(-100.0, 100.0)))
_any_sample = st.tuples(
    st.sampled_from([1, 1, 1, 0, -1, 2**31, 2**31 - 1, 7]), _any_float, _any_float, _any_float,
)
# mostly valid samples, so that runs of good samples (auto-resume) happen too
_sample = st.one_of(_good_sample, _good_sample, _good_sample, _good_sample, st.none(), _any_sample)
_tick = st.tuples(
    _sample,
    st.one_of(st.just(1e-4), st.just(1e-4), st.floats(min_value=0.0, max_value=0.02), st.just(math.nan)),  # age
    st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(min_value=-0.5, max_value=1.5)),
    st.integers(min_value=0, max_value=199),  # rare events: driver failure / reset
)


@given(
    ticks=st.lists(_tick, max_size=150),
    hold=st.integers(min_value=0, max_value=6),
    slew=st.one_of(st.none(), st.floats(min_value=1.0, max_value=2000.0)),
    auto=st.booleans(),
    resume_n=st.integers(min_value=1, max_value=5),
    seq0=st.sampled_from([0, 2**32 - 3, 12345]),
)
@settings(max_examples=300, deadline=None)
def test_output_always_safe(ticks, hold, slew, auto, resume_n, seq0):
    c = SafetyConfig(I_max=0.6, max_slew_A_per_s=slew, hold_ticks=hold, max_age_s=5e-3,
                     x_range_m=(-0.03, 0.03), v_range_mps=(-2.0, 2.0), F_range_N=(-3000.0, 3000.0),
                     auto_resume=auto, resume_good_ticks=resume_n, dt_s=DT)
    sup = SafetySupervisor(c)
    step = math.inf if slew is None else slew * DT
    seq = seq0
    prev_out = 0.0  # the last current commanded
    bad_run = 0
    for s, age, I_cmd, ev in ticks:
        if ev == 0:
            sup.driver_failed()
        elif ev == 1:
            sup.reset()
            bad_run = 0
            prev_out = 0.0  # re-armed: output restarts from 0 A
        if s is None:
            sample = None
        else:
            seq = (seq + s[0]) % 2**32
            sample = S(seq, *s[1:])
        used = sup.check_sample(sample, age)
        out = sup.limit(I_cmd if used is not None else 0.0)

        assert isinstance(out, float) and math.isfinite(out) and 0.0 <= out <= 0.6
        if sup.in_fault:
            assert used is None and out == 0.0
        if used is None:
            assert out == 0.0  # forced 0 A: not slew-limited
        else:
            # the law only ever sees a sample that passed every check
            assert math.isfinite(used.x_m) and -0.03 <= used.x_m <= 0.03
            assert math.isfinite(used.v_mps) and -2.0 <= used.v_mps <= 2.0
            assert not math.isinf(used.F_N)
            assert abs(out - prev_out) <= step + 1e-12
        prev_out = out
        # never more than hold_ticks consecutive bad samples without a fault
        if sup.in_fault or (sample is not None and used is sample):
            bad_run = 0
        else:
            bad_run += 1
            assert bad_run <= hold
    cnt = sup.counters()
    assert cnt.good + cnt.bad == len(ticks)
    event(f"faults={min(cnt.faults_entered, 2)} resumes={min(cnt.resumes, 1)} holds={min(cnt.holds_used, 1)}")


def test_repeated_seq_while_recovering_does_not_restart_the_resume_count():
    """Exchange links repeat a seq now and then in normal running; in FAULT that
    is neither a good nor a bad sample for resuming. A frozen seq never resumes."""
    from types import SimpleNamespace as NS

    sup = SafetySupervisor(SafetyConfig(I_max=0.6, hold_ticks=0, auto_resume=True, resume_good_ticks=4))
    ok = lambda seq: NS(seq=seq, x_m=0.0, v_mps=0.1, F_N=float("nan"), status=0)  # noqa: E731
    sup.check_sample(ok(1))
    assert sup.check_sample(None) is None and sup.in_fault
    # good, repeat, good, repeat, good, good -> resumes on the 4th *fresh* sample
    seqs = [2, 2, 3, 3, 4, 5]
    out = [sup.check_sample(ok(s)) for s in seqs]
    assert [o is not None for o in out] == [False, False, False, False, False, True]
    # a frozen seq after a fault never brings the current back
    sup2 = SafetySupervisor(SafetyConfig(I_max=0.6, hold_ticks=0, auto_resume=True, resume_good_ticks=4))
    sup2.check_sample(ok(1))
    sup2.check_sample(None)
    assert all(sup2.check_sample(ok(7 if i else 6)) is None for i in range(50))
    assert sup2.in_fault


def test_a_fault_that_cleared_before_the_poll_is_reported_with_its_kind_and_reason():
    """The monitor polls the supervisor off the loop; a fault that auto-resumed
    in between is still reported by kind and reason, not as '?'."""
    from mrctl.daemon.faultwatch import FaultWatch

    sup = SafetySupervisor(cfg(hold_ticks=0, auto_resume=True, resume_good_ticks=1))
    f = Feed(sup)
    f.good()
    f.bad("missing")
    assert sup.in_fault
    f.good()
    f.good()
    assert not sup.in_fault and sup.reason == ""
    said: list[str] = []
    FaultWatch(sup, lambda msg, prio: said.append(msg), lambda: 5).check()
    assert said and "FAULT ?" not in said[0] and "no reason given" not in said[0], said
    assert sup.last_fault.name in said[0] and sup.last_reason and sup.last_reason in said[0]
