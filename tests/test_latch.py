"""Latched faults and the explicit re-arm (issue: a bench you can leave powered).

An E-stop or a device watchdog trip in a sample's status latches at once (no
hold, whatever ``auto_resume`` says); a run of bad samples longer than
``latch_after_ticks`` (a link loss) latches; a latch stays at 0 A until a
re-arm, which takes only on a good sample without the cause, within
``arm_wait_ticks``, and the output then ramps up from 0 A at the slew limit.
Everything on a virtual tick count: no clock is read.
"""

from __future__ import annotations

import math

import pytest

from mrctl.core.safety import ARM_DONE, ARM_REFUSED, Fault, SafetyConfig, SafetyState, SafetySupervisor
from mrctl.core.safety_config import AUTO_SLEW_A_PER_S, LATCH_STATUS, resolve_slew
from mrctl.io.base import Sample, Status

DT = 1e-3
ESTOP = int(Status.ESTOP)
TRIPPED = int(Status.WATCHDOG_TRIPPED)


def sup_for(**kw) -> SafetySupervisor:
    base = dict(I_max=1.0, hold_ticks=3, auto_resume=True, resume_good_ticks=2, max_slew_A_per_s=50.0, dt_s=DT,
                latch_status_mask=LATCH_STATUS, latch_after_ticks=50, arm_wait_ticks=20)
    base.update(kw)
    return SafetySupervisor(SafetyConfig(**base))


class Bench:
    """Feeds a supervisor one tick at a time and keeps what it commanded."""

    def __init__(self, sup: SafetySupervisor) -> None:
        self.sup = sup
        self.k = 0
        self.seq = 0
        self.out: list[float] = []

    def tick(self, status: int = 0, missing: bool = False, I_law: float = 0.8) -> float:
        sup = self.sup
        if missing:
            ok = sup.check_missing(self.k)
        else:
            self.seq += 1
            ok = sup.check(self.k, self.seq, 0.001, 0.1, math.nan, status, math.nan, 0.0)
        I = sup.limit(I_law if ok else 0.0)
        self.out.append(I)
        self.k += 1
        return I

    def run(self, n: int, **kw) -> list[float]:
        return [self.tick(**kw) for _ in range(n)]


def test_estop_latches_at_once_with_auto_resume_and_holds_zero_until_armed():
    b = Bench(sup_for())
    b.run(40)  # ramped up to the law's 0.8 A at 0.05 A per tick
    assert b.out[-1] == pytest.approx(0.8)
    assert b.tick(status=ESTOP) == 0.0  # the tick the E-stop is read: 0 A, no hold
    sup = b.sup
    assert sup.in_fault and sup.latched and sup.latch_cause == "estop"
    assert sup.shown_state is SafetyState.LATCHED and sup.state is SafetyState.FAULT
    assert sup.fault_bits & int(Fault.ESTOP) and sup.fault_bits & int(Fault.LATCHED)
    b.run(5, status=ESTOP)
    assert b.run(200) == [0.0] * 200  # the E-stop closed, good samples, auto_resume: still 0 A
    c = sup.counters()
    assert c.latches == 1 and c.estop == 6 and c.ticks_latched == 206 and c.resumes == 0


def test_rearm_takes_on_a_good_sample_and_ramps_up_at_the_slew_limit():
    b = Bench(sup_for())
    b.run(20)
    b.tick(status=ESTOP)
    b.run(10)
    b.sup.request_arm()
    ramp = b.run(20)
    assert b.sup.arm_state == ARM_DONE and "re-armed" in b.sup.arm_message
    assert not b.sup.in_fault and b.sup.shown_state is SafetyState.OK
    steps = [y - x for x, y in zip([0.0] + ramp, ramp)]
    assert max(steps) <= 50.0 * DT + 1e-12  # from 0 A, never faster than the slew limit
    assert ramp[0] == pytest.approx(0.05) and ramp[15] == pytest.approx(0.8)
    assert b.sup.counters().arms == 1


def test_rearm_is_refused_while_the_cause_is_still_there():
    b = Bench(sup_for(arm_wait_ticks=20))
    b.run(5)
    b.tick(status=ESTOP)
    b.sup.request_arm()
    assert b.run(25, status=ESTOP) == [0.0] * 25
    assert b.sup.arm_state == ARM_REFUSED and "E-stop" in b.sup.arm_message
    assert b.sup.latched and b.sup.counters().arms_refused == 1
    b.run(30)  # the E-stop closes later: the refused request does not re-arm by itself
    assert b.sup.latched and b.out[-1] == 0.0


def test_device_watchdog_trip_latches_like_the_estop():
    b = Bench(sup_for())
    b.run(10)
    assert b.tick(status=TRIPPED) == 0.0
    assert b.sup.latched and b.sup.latch_cause == "device watchdog"
    assert b.run(50) == [0.0] * 50


def test_a_short_link_loss_auto_resumes_and_a_long_one_latches():
    b = Bench(sup_for(latch_after_ticks=50))
    b.run(20)
    b.run(30, missing=True)  # 30 ticks: FAULT after the hold, not latched
    assert b.sup.in_fault and not b.sup.latched
    resumed = b.run(10)
    assert not b.sup.in_fault and resumed[-1] > 0.0
    b.run(51, missing=True)  # longer than latch_after_ticks
    assert b.sup.latched and b.sup.latch_cause == "link loss"
    assert b.run(100) == [0.0] * 100
    b.sup.request_arm()
    assert b.tick() == pytest.approx(0.05)  # the link is back: the re-arm takes, from 0 A up


def test_without_latch_settings_the_in_process_bench_behaves_as_before():
    b = Bench(sup_for(latch_status_mask=0, latch_after_ticks=None))
    b.run(10)
    b.tick(status=ESTOP)  # no latching bits on the in-process bench: a good sample
    b.run(500, missing=True)
    assert not b.sup.latched
    assert b.run(10)[-1] > 0.0  # auto_resume as configured


def test_auto_resume_false_latches_every_fault_and_arm_clears_it():
    b = Bench(sup_for(auto_resume=False))
    b.run(10)
    b.run(5, missing=True)
    assert b.sup.latched and b.run(50) == [0.0] * 50
    b.sup.request_arm()
    b.run(1)
    assert not b.sup.in_fault


def test_arm_when_not_latched_says_so():
    sup = sup_for()
    Bench(sup).run(3)
    sup.request_arm()
    assert sup.arm_state == ARM_DONE and sup.arm_message.startswith("nothing to re-arm")


def test_recovery_after_every_fault_kind_never_steps_faster_than_the_slew():
    """Whatever the fault (hold, fault, resume, latch, re-arm), no tick's rise
    exceeds slew x period: the first tick, every resume and the re-arm ramp."""
    step = 50.0 * DT
    b = Bench(sup_for())
    pattern = ([{}] * 30 + [{"missing": True}] * 2 + [{}] * 10 + [{"missing": True}] * 10 + [{}] * 30
               + [{"status": ESTOP}] + [{}] * 10 + ["arm"] + [{}] * 30 + [{"missing": True}] * 60 + [{}] * 5
               + ["arm"] + [{}] * 30)
    for p in pattern:
        if p == "arm":
            b.sup.request_arm()
        else:
            b.tick(**p)
    rises = [y - x for x, y in zip([0.0] + b.out, b.out)]
    assert max(rises) <= step + 1e-12
    assert b.sup.counters().arms == 2 and b.out[-1] == pytest.approx(0.8)


def test_auto_slew_is_on_for_real_links_and_off_for_the_in_process_bench():
    assert resolve_slew("auto", True) == AUTO_SLEW_A_PER_S
    assert resolve_slew("auto", False) is None
    assert resolve_slew(None, True) is None and resolve_slew(20, True) == 20.0


# -- safety.estop: what each backend can read ---------------------------------------------------
ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


def _check(tmp_path, name: str, estop: dict | None, **backend) -> list[str]:
    import yaml

    from mrctl.config import ConfigError, load_experiment

    data = yaml.safe_load((ROOT / "config" / "experiments" / name).read_text())
    data["safety"].pop("estop", None)
    if estop is not None:
        data["safety"]["estop"] = estop
    data["backend"].update(backend)
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    try:
        load_experiment(p)
    except ConfigError as exc:
        return [e for e in exc.errors if "estop" in e]
    return []


@pytest.mark.parametrize("name, estop, backend, error", [
    ("hil_serial.yaml", {"input": "device"}, {}, None),
    ("hil_modbus_tcp.yaml", {"input": "device"}, {}, None),
    ("labjack_t7.yaml", {"input": "DIO4", "active": "high"}, {}, None),
    ("labjack_t7.yaml", {"input": "EIO0", "active": "low"}, {}, None),
    ("fig5.yaml", {"input": "device"}, {}, "the in-process simulated bench has no E-stop input"),
    ("hil_serial.yaml", {"input": "device", "active": "low"}, {}, "remove active"),
    ("hil_serial.yaml", {"input": "DIO4", "active": "high"}, {}, "needs backend.device"),
    ("labjack_t7.yaml", {"input": "device"}, {}, "has no E-stop of its own"),
    ("labjack_t7.yaml", {"input": "DIO4"}, {}, "safety.estop.active: required"),
    ("labjack_t7.yaml", {"input": "AIN4", "active": "high"}, {}, "not allowed"),
    ("hil_serial.yaml", {"active": "high"}, {}, "set without safety.estop.input"),
    ("hil_modbus_tcp.yaml", {"input": "device"},
     {"register_map": {"registers": {"x_m": {"table": "input", "address": 0, "type": "float32"},
                                     "current_setpoint_A": {"table": "holding", "address": 10,
                                                            "type": "float32"}}}},
     "has no status register"),
])
def test_estop_input_is_checked_against_the_backend(tmp_path, name, estop, backend, error):
    errors = _check(tmp_path, name, estop, **backend)
    if error is None:
        assert errors == []
    else:
        assert any(error in e for e in errors), errors


# -- the controller: the link's enable, a reload, mrctl arm -----------------------------------------
class _EstopLink:
    """An exchange device whose status says ESTOP on the ticks in ``estop``; it records what
    it was sent (current, the output enable) and whether a CLEAR_FAULTS was asked for."""

    split = False
    host_clocked = False
    true_force_N = math.nan

    def __init__(self, estop=()):
        self.k = 0
        self.estop = set(estop)
        self.sent: list[tuple[float, bool]] = []
        self.enabled = True
        self.clears = 0

    def exchange(self, I):
        self.sent.append((I, self.enabled))
        k, self.k = self.k, self.k + 1
        v = 0.0628 * math.cos(2 * math.pi * k * 1e-3)
        return Sample(k, k * 1e-3, 0.0, v, math.nan, ESTOP if k in self.estop else 0)

    def request_clear_faults(self):
        self.clears += 1
        return True


def _controller(link):
    from mrctl.core.controller import Controller
    from mrctl.laws.demand import Viscous
    from mrctl.laws.inverse import SmoothInverse
    from mrctl.model.params import TABLE_I

    sup = sup_for(I_max=0.6)
    law = lambda: SmoothInverse(TABLE_I, 0.6, 1e-3)  # noqa: E731
    return Controller(link, law(), Viscous(500.0), sup, 1e-3), sup, law


def test_the_controller_disables_the_output_while_latched_a_reload_does_not_rearm_arm_does():
    link = _EstopLink(estop=range(200, 220))
    ctl, sup, law = _controller(link)
    for k in range(400):
        ctl.tick(k, 0)
        if k == 300:  # a SIGHUP reload while latched: new laws at the tick boundary, still latched
            from mrctl.laws.demand import Viscous

            ctl.pending = (law(), Viscous(500.0))
    assert sup.latched and sup.latch_cause == "estop"
    assert all(I == 0.0 and not en for I, en in link.sent[202:401]), "0 A and the output disabled while latched"
    assert link.clears == 0
    ctl.arm_request = True  # mrctl arm, taken at the next tick boundary
    for k in range(400, 500):
        ctl.tick(k, 0)
    assert link.clears == 1 and not sup.in_fault and sup.arm_state == ARM_DONE
    sent = [I for I, _ in link.sent[401:]]
    assert link.sent[-1][1] and max(sent) > 0.1
    assert max(b - a for a, b in zip(sent, sent[1:])) <= 0.05 + 1e-12  # the slew limit, from 0 A
