"""Velocity from displacement: the Kalman observer, alone, in simulate and in the controller."""

import math
import random
from pathlib import Path

import numpy as np
import pytest

from mrctl.config import load_yaml, validate_experiment
from mrctl.core.controller import Controller
from mrctl.core.safety import SafetyConfig, SafetySupervisor
from mrctl.estimation import KinematicObserver
from mrctl.estimation.observer import steady_state_gain
from mrctl.experiment import build
from mrctl.io.base import Sample
from mrctl.laws.demand import Viscous
from mrctl.laws.inverse import SmoothInverse
from mrctl.model.params import TABLE_I
from mrctl.model.plant import Sensors
from mrctl.offline.simulate import simulate

EXP = Path(__file__).resolve().parents[1] / "config" / "experiments"
DT = 1e-3
W = 2 * math.pi


def _motion(n, f=1.0, amp=0.010):
    t = np.arange(n) * DT
    return t, amp * np.sin(W * f * t), amp * W * f * np.cos(W * f * t)


def test_converges_from_a_wrong_start():
    t, x, v = _motion(400)
    obs = KinematicObserver(DT, 2e-6, 1.0)
    obs.update(x[0] + 1e-4)  # 0.1 mm off, and it starts at rest while v = 63 mm/s
    err = np.array([obs.update(xk) - vk for xk, vk in zip(x[1:].tolist(), v[1:].tolist())])
    assert abs(err[0]) > 0.02
    settled = np.flatnonzero(np.abs(err) > 1e-3)
    assert settled[-1] < 150  # within 1 mm/s after 150 ms, and stays there
    assert np.max(np.abs(err[200:])) < 2e-4


@pytest.mark.parametrize("f, amp", [(1.0, 0.010), (5.0, 0.002)])
def test_noise_and_delay_against_the_true_velocity(f, amp):
    """LVDT noise 2 um + 1 um steps: the velocity a finite difference would give
    has 2.8 mm/s of noise; the observer, well under 1 mm/s and no lag to speak of."""
    t, x, v = _motion(4001, f, amp)
    s = Sensors(3, x_noise_m=2e-6, x_lsb_m=1e-6)
    xm = np.array([s.x(xk) for xk in x.tolist()])
    obs = KinematicObserver(DT, 2e-6, 1.0)
    vh = np.array([obs.update(xk) for xk in xm.tolist()])
    w = t >= 1.0
    # fit vh = a·cos + b·sin: gain and phase against the true velocity, and the rest is noise
    M = np.column_stack([np.cos(W * f * t[w]), np.sin(W * f * t[w])])
    (a, b), *_ = np.linalg.lstsq(M, vh[w], rcond=None)
    gain = math.hypot(a, b) / (amp * W * f)
    delay_s = math.atan2(b, a) / (W * f)  # v̂ ≈ G·v(t − delay)
    noise = np.std(vh[w] - M @ np.array([a, b]))
    fd_noise = np.std(np.diff(xm[w]) / DT - v[w][1:])
    assert fd_noise > 2.5e-3 and noise < 0.4e-3 and noise < fd_noise / 8
    assert abs(gain - 1.0) < 0.04 and abs(delay_s) < 2e-4


def test_fusing_the_velocity_channel_and_its_gaps():
    t, x, v = _motion(3000)
    rng = random.Random(1)
    fused = KinematicObserver(DT, 2e-6, 1.0, v_noise_mps=0.002)
    assert len(fused.kxv) == 3 and len(fused.kxv[0]) == 2
    out = [fused.update(xk + rng.gauss(0, 2e-6), vk + rng.gauss(0, 0.002) if k % 7 else math.nan)
           for k, (xk, vk) in enumerate(zip(x.tolist(), v.tolist()))]
    assert np.std(np.array(out[1000:]) - v[1000:]) < 0.5e-3


def test_nan_displacement_predicts_and_gaps_use_the_elapsed_time():
    obs = KinematicObserver(DT, 2e-6, 1.0)
    t, x, v = _motion(500)
    for xk in x[:400].tolist():
        obs.update(xk)
    assert obs.update(math.nan) == pytest.approx(float(v[400]), abs=5e-4)  # a prediction, finite
    # 10 ticks skipped after it: one update 11 ticks on lands on the velocity then
    vh = obs.update(float(x[411]), ticks=11)
    assert vh == pytest.approx(float(v[411]), abs=1e-3)
    assert math.isnan(KinematicObserver(DT, 2e-6, 1.0).update(math.nan))  # nothing to say yet


def test_gains_are_the_steady_state_kalman_gains():
    K = steady_state_gain(DT, 1.0, 2e-6)
    assert K.shape == (3, 1) and 0 < K[0, 0] < 1 and K[1, 0] > 0 and K[2, 0] > 0
    # a noisier LVDT trusts the model more
    assert steady_state_gain(DT, 1.0, 2e-5)[1, 0] < K[1, 0]
    for bad in ((0.0, 2e-6, 1.0), (DT, -1.0, 1.0), (DT, 2e-6, math.inf)):
        with pytest.raises(ValueError):
            KinematicObserver(*bad)
    with pytest.raises(ValueError):
        KinematicObserver(DT, 2e-6, 1.0, v_noise_mps=0.0)


def test_displacement_only_in_simulate():
    data = load_yaml(EXP / "fig5.yaml")
    data["plant"] = {"sensors": {"x_noise_m": 2e-6, "x_lsb_m": 1e-6, "velocity": False}}
    with pytest.raises(Exception, match="sensing.velocity: observer"):
        validate_experiment(data, EXP)
    data["sensing"] = {"velocity": "observer"}
    res = simulate(build(validate_experiment(data, EXP)), 2.0)
    c = res.columns
    w = c["t"] >= 0.5
    assert np.all(np.isfinite(c["v_meas"]))  # the velocity the laws saw: the estimate
    assert np.std(c["v_meas"][w] - c["v"][w]) < 0.5e-3
    assert res.summary["force_nrmse"] < 0.01


class XOnlyLink:
    """A split link whose DAQ has no velocity channel (v is NaN)."""

    split = True
    host_clocked = False
    true_force_N = math.nan

    def __init__(self):
        self.k = -1
        self.writes = []

    def read(self):
        self.k += 1
        t = self.k * DT
        return Sample(self.k, t, 0.01 * math.sin(W * t), math.nan, math.nan, 0)

    def write(self, I):
        self.writes.append(I)


def test_controller_applies_the_observer_before_the_safety_checks():
    link = XOnlyLink()
    sup = SafetySupervisor(SafetyConfig(I_max=0.6, hold_ticks=0))
    ctl = Controller(link, SmoothInverse(TABLE_I, 0.6, DT), Viscous(500.0), sup, DT,
                     observer=KinematicObserver(DT, 2e-6, 1.0))
    for k in range(300):
        ctl.tick(k, 0)
    assert sup.counters().non_finite == 0 and sup.counters().faults_entered == 0
    assert ctl.last_v == pytest.approx(0.01 * W * math.cos(W * 299 * DT), abs=2e-3)
    assert max(link.writes) > 0.1
    # without it, the same DAQ is a non-finite sample every tick: 0 A
    link2 = XOnlyLink()
    sup2 = SafetySupervisor(SafetyConfig(I_max=0.6, hold_ticks=0))
    ctl2 = Controller(link2, SmoothInverse(TABLE_I, 0.6, DT), Viscous(500.0), sup2, DT)
    for k in range(50):
        ctl2.tick(k, 0)
    assert max(link2.writes) == 0.0 and sup2.counters().non_finite > 0


def test_updates_several_ticks_apart_stay_stable():
    """A loop that keeps skipping deadlines feeds the observer every 4+ ticks:
    with the one-tick gains over the gap the update diverged (1e42 m/s at
    250 Hz, every 4 ticks); with the gap's own steady-state gains it tracks."""
    import math

    from mrctl.estimation.observer import KinematicObserver

    dt = 0.004
    for gap in (4, 6, 10):
        obs = KinematicObserver(dt, 2e-6, 1.0)
        t, worst = 0.0, 0.0
        for i in range(600):
            n = gap if i > 100 else 1
            t += n * dt
            v = obs.update(0.01 * math.sin(2 * math.pi * t), math.nan, n)
            if i > 100:
                worst = max(worst, abs(v - 0.02 * math.pi * math.cos(2 * math.pi * t)))
        assert worst < 2e-3, (gap, worst)


def _irregular_times(n: int, dt: float) -> list[float]:
    """Sample times of a DAQ that serves the latest of its own 1 ms conversions to a 2 ms loop
    (the emulated T7 at 500 Hz): 1, 2 and 3 ms apart, on no grid of dt."""
    rnd = random.Random(7)
    t, out = 0.0, []
    for _ in range(n):
        t += rnd.choice((0.001, 0.002, 0.002, 0.003))
        out.append(t)
    return out


def test_a_fractional_step_predicts_over_the_real_time_between_samples():
    dt = 0.002
    times = _irregular_times(1500, dt)
    errs = {}
    for use_h in (False, True):
        obs = KinematicObserver(dt, 2e-6, 1.0)
        prev, e = 0.0, []
        for i, t in enumerate(times):
            d = t - prev
            prev = t
            n = max(1, int(d / dt + 0.5))
            v = obs.update(0.01 * math.sin(W * t), math.nan, n, d if use_h else 0.0)
            if i > 200:
                e.append(v - 0.01 * W * math.cos(W * t))
        errs[use_h] = math.sqrt(sum(x * x for x in e) / len(e))
    assert errs[True] < 0.2 * errs[False], errs  # rounding 1 or 3 ms to whole ticks is the error
    assert errs[True] < 1e-3, errs


def test_a_whole_number_of_ticks_as_h_is_the_same_update_bit_for_bit():
    a, b = KinematicObserver(0.002, 2e-6, 1.0), KinematicObserver(0.002, 2e-6, 1.0)
    for i in range(300):
        n = 1 + i % 3
        x = 0.01 * math.sin(W * 0.002 * i)
        assert a.update(x, math.nan, n) == b.update(x, math.nan, n, 0.002 * n)


class StampedXLink(XOnlyLink):
    """x sampled at the device's own times (t_dev), not on the controller's tick grid."""

    def __init__(self, times):
        super().__init__()
        self.times = times

    def read(self):
        self.k += 1
        t = self.times[self.k]
        return Sample(self.k, t, 0.01 * math.sin(W * t), math.nan, math.nan, 0)


def test_the_controller_steps_the_observer_by_the_device_time_between_samples():
    """Device stamps between the ticks (1-3 ms apart at 500 Hz): the observer predicts over the
    stamps' real step, so its velocity follows the motion as closely as on a regular grid."""
    dt = 0.002
    times = _irregular_times(800, dt)
    link = StampedXLink(times)
    sup = SafetySupervisor(SafetyConfig(I_max=0.6, hold_ticks=0))
    ctl = Controller(link, SmoothInverse(TABLE_I, 0.6, dt), Viscous(500.0), sup, dt,
                     observer=KinematicObserver(dt, 2e-6, 1.0))
    worst = 0.0
    for k in range(800):
        ctl.tick(k, 0)
        if k > 200:
            worst = max(worst, abs(ctl.last_v - 0.01 * W * math.cos(W * times[k])))
    assert sup.counters().faults_entered == 0
    assert worst < 2e-3, worst
