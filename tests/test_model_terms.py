"""The optional model terms through the chain: parameters, model, plant, inverse laws.

σ1(v) = σ1·exp(−(v/v_d)²), a falling input lag beside the rising one, and
the hysteretic (Dahl) stiffness with a stiffness per direction: each is off
at 0 and changes no bit then; on, the model computes what its equations say,
the plant feels it, and the laws invert it (docs/identification.md, "Model
terms").
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from mrctl.laws.base import Measurement
from mrctl.laws.closed import ClosedLoopInverse
from mrctl.laws.inverse import PaperInverse, SmoothInverse
from mrctl.model.lugre import LuGreModel, force
from mrctl.model.mapping import params_from_mapping
from mrctl.model.params import TABLE_I, LuGreParams
from mrctl.model.plant import DamperPlant, DriverLag

DT = 1e-3
EXTRAS = TABLE_I.with_overrides(sigma1_vd=0.04, k_hys_pos=150.0, k_hys_neg=600.0, x_hys=0.004)


def test_off_by_default_and_written_only_when_on():
    assert TABLE_I.extras() == {} and not TABLE_I.has_hysteresis
    assert list(TABLE_I.as_dict()) == list(LuGreParams.all_names())[:16]  # the sixteen keys it always had
    assert EXTRAS.extras() == {"sigma1_vd": 0.04, "k_hys_pos": 150.0, "k_hys_neg": 600.0, "x_hys": 0.004}
    assert params_from_mapping(EXTRAS.as_dict()) == EXTRAS
    assert TABLE_I.tau_fall() == 0.0 and TABLE_I.with_overrides(tau_input=0.004).tau_fall() == 0.004
    assert TABLE_I.with_overrides(tau_input=0.004, tau_input_fall=0.02).tau_fall() == 0.02


@pytest.mark.parametrize("data, message", [
    ({"sigma1_vd": -0.1}, "sigma1_vd: must be >= 0 m/s"),
    ({"tau_input_fall": -1e-3}, "tau_input_fall: must be >= 0 s"),
    ({"k_hys_neg": 500.0}, "x_hys: must be > 0 m when k_hys_pos or k_hys_neg is set"),
    ({"k_hys_pos": 500.0, "x_hys": -0.01}, "x_hys: must be >= 0 m"),
])
def test_meaningless_terms_are_refused_naming_the_key(data, message):
    with pytest.raises(ValueError, match=message):
        params_from_mapping(data)


def _raw_zdot(p, z, v, I):
    """ż from eq (2) alone, without σ1's weight (the model's zdot() carries it when sigma1_vd is set)."""
    return LuGreModel(replace(p, sigma1_vd=0.0), z0=z).zdot(v, I)


@settings(max_examples=200, deadline=None)
@given(st.floats(-5e-4, 5e-4), st.floats(-0.3, 0.3), st.floats(0.0, 0.6))
def test_bristle_damping_fades_with_velocity(z, v, I):
    """F = σ0·z + σ1·ż·exp(−(v/v_d)²) + σ2·v; v_d off is Table I bit for bit."""
    p = TABLE_I.with_overrides(sigma1_vd=0.04)
    m = LuGreModel(p, z0=z)
    zdot = _raw_zdot(p, z, v, I)
    want = p.sigma0(I) * z + p.sigma1(I) * zdot * math.exp(-(v / 0.04) ** 2) + p.sigma2(I) * v
    assert m.zdot(v, I) == pytest.approx(zdot * math.exp(-(v / 0.04) ** 2), rel=1e-12, abs=1e-15)
    assert m.force(v, I) == pytest.approx(want, rel=1e-12, abs=1e-9)
    assert force(p, z, v, I) == pytest.approx(want, rel=1e-12, abs=1e-9)
    assert LuGreModel(replace(p, sigma1_vd=0.0), z0=z).force(v, I) == LuGreModel(TABLE_I, z0=z).force(v, I)


def test_hysteretic_stiffness_state_is_exact_and_bounded():
    """At constant v > 0 from zh = 0: zh = x_h·(1 − e^(−v·t/x_h)), force k_pos·zh;
    reversed, the force is k_neg·zh; |zh| never exceeds x_h."""
    p = TABLE_I.with_overrides(k_hys_pos=150.0, k_hys_neg=600.0, x_hys=0.004)
    m = LuGreModel(p, v0=0.02)
    v = 0.02
    for k in range(1, 401):
        m.advance(v, 0.2, DT)
        assert m.zh == pytest.approx(0.004 * (1.0 - math.exp(-v * k * DT / 0.004)), rel=1e-12)
    assert m.hys_force(v) == pytest.approx(150.0 * m.zh, rel=1e-15)
    assert m.force(v, 0.2) - LuGreModel(TABLE_I, z0=m.z).force(v, 0.2) == pytest.approx(150.0 * m.zh, abs=1e-9)
    zh = m.zh
    m.advance(-v, 0.2, DT)  # mid-step velocity 0: zh holds, the negative direction's stiffness acts
    assert m.zh == zh and m.hys_force(-v) == pytest.approx(600.0 * zh, rel=1e-15)
    for _ in range(3000):
        m.advance(-0.3, 0.2, DT)
        assert abs(m.zh) <= 0.004
    assert m.zh == pytest.approx(-0.004, rel=1e-6)
    m.reset()
    assert m.zh == 0.0


@settings(max_examples=100, deadline=None)
@given(st.floats(-5e-4, 5e-4), st.floats(-0.1, 0.1), st.floats(-2e-3, 2e-3), st.floats(0.0, 0.6),
       st.integers(1, 5))
def test_look_ahead_with_the_terms_is_advance_then_force(z0, v0, dv, I, n):
    """The closed law's horizon is the model's, σ1(v) included; the
    hysteretic force (independent of I) is held, so it is left out."""
    mod = LuGreModel(EXTRAS, z0=z0, v0=v0)
    out, out1 = [math.nan] * n, [math.nan] * n
    mod.look_ahead(v0, dv, I, 0.02, DT, LuGreModel(EXTRAS), out, out1)
    for cur, got in ((I, out), (I + 0.02, out1)):
        ref = LuGreModel(EXTRAS, z0=z0, v0=v0)
        v = v0
        for j in range(n):
            v = v + dv
            ref.advance(v, cur, DT)
            assert got[j] == pytest.approx(ref.force(v, cur) - ref.hys_force(v), rel=1e-13, abs=1e-10)


def test_the_driver_rises_and_falls_with_its_own_time_constants():
    lag = DriverLag(0.004, DT, 0.012)
    for _ in range(10):
        lag.update(1.0)
    assert lag.I == pytest.approx(1.0 - math.exp(-10 * DT / 0.004), rel=1e-12)
    top = lag.I
    for _ in range(10):
        lag.update(0.0)
    assert lag.I == pytest.approx(top * math.exp(-10 * DT / 0.012), rel=1e-12)
    same = DriverLag(0.004, DT)
    assert same.alpha_fall == same.alpha  # one time constant: the arithmetic of before
    plant = DamperPlant(TABLE_I.with_overrides(tau_input=0.004, tau_input_fall=0.012), DT)
    assert (plant.driver.alpha, plant.driver.alpha_fall) == (lag.alpha, lag.alpha_fall)
    imposed = DamperPlant(TABLE_I.with_overrides(tau_input=0.004, tau_input_fall=0.012), DT, driver_tau_s=0.002)
    assert imposed.driver.alpha_fall == imposed.driver.alpha  # a bench's driver_tau_s: the same both ways


# the laws invert the model with the terms: exactly (paper, smooth at steady current) -----------------------
states = dict(z=st.floats(-6e-4, 6e-4), v=st.floats(-0.3, 0.3), I=st.floats(0.0, 1.0),
              zh=st.floats(-0.004, 0.004))


def _at(cls, z, v, I, zh):
    law = cls(EXTRAS, 1.0, DT)
    law.reset(z0=z, v0=v, I0=I)
    law.model.zh = zh
    return law


def _frozen(z, v, I, I_zdot, zh):
    """Eq (1) with ż at the previous current (eq 12's assumption), σ1 weighted, plus the hysteretic force."""
    m = LuGreModel(EXTRAS, z0=z)
    m.zh = zh
    zdot = _raw_zdot(EXTRAS, z, v, I_zdot) * math.exp(-(v / 0.04) ** 2)
    return EXTRAS.sigma0(I) * z + EXTRAS.sigma1(I) * zdot + EXTRAS.sigma2(I) * v + m.hys_force(v)


@settings(max_examples=300, deadline=None)
@given(**states, I_true=st.floats(0.0, 1.0))
def test_paper_law_inverts_the_model_with_the_terms(z, v, I, zh, I_true):
    law = _at(PaperInverse, z, v, I, zh)
    w = math.exp(-(v / 0.04) ** 2)
    D = EXTRAS.sigma0A * z + EXTRAS.sigma1A * _raw_zdot(EXTRAS, z, v, I) * w + EXTRAS.sigma2A * v
    assume(abs(D) > 0.5)
    assert law.current(Measurement(v=v), _frozen(z, v, I_true, I, zh)) == pytest.approx(I_true, abs=1e-8)


@settings(max_examples=300, deadline=None)
@given(**states)
def test_smooth_law_recovers_the_current_at_steady_current_with_the_terms(z, v, I, zh):
    law = _at(SmoothInverse, z, v, I, zh)
    assert law.current(Measurement(v=v), _frozen(z, v, I, I, zh)) == pytest.approx(I, abs=1e-9)


@pytest.mark.parametrize("cls", [SmoothInverse, ClosedLoopInverse])
def test_the_laws_state_is_the_plants_with_the_terms(cls):
    """The tick protocol holds with σ1(v) and the hysteretic state: without
    a lag, the law's z and zh are the plant's, bit for bit."""
    plant = DamperPlant(EXTRAS, DT)
    law = cls(EXTRAS, 0.6, DT)
    for k in range(3000):
        v = 0.0628 * math.cos(2 * math.pi * k * DT)
        I = law.current(Measurement(v=v, k=k, I_cmd=law.I_prev, F=plant.F if k else math.nan), 500.0 * v)
        plant.tick(v, I)
        assert (law.model.z, law.model.zh) == (plant.model.z, plant.model.zh)
    assert max(abs(plant.model.zh), 1e-9) > 1e-3  # the stroke (10 mm) saturates it


def _track(params, lag_s=None, law="smooth", seconds=2.0):
    """Force NRMSE of a law on the plant of ``params`` (a 1 Hz, 10 mm sine, demand 800 N·s/m · v)."""
    plant = DamperPlant(params, DT)
    kw = {} if lag_s is None else {"lag_s": lag_s}
    ctl = (SmoothInverse if law == "smooth" else ClosedLoopInverse)(params, 1.0, DT, max_slew_A_per_s=200.0, **kw)
    err = []
    ref = []
    I = 0.0
    for k in range(int(seconds / DT)):
        v = 0.0628 * math.cos(2 * math.pi * k * DT)
        F_des = 800.0 * v
        F = plant.F
        I = ctl.current(Measurement(v=v, k=k, I_cmd=I, F=F if k else math.nan), F_des)
        ctl.applied(I)
        plant.tick(v, I)
        if k * DT > 0.5:
            err.append(plant.F - F_des)
            ref.append(F_des)
    return math.sqrt(sum(e * e for e in err) / len(err)) / (max(ref) - min(ref))


def test_the_fall_lag_compensated_tracks_better_than_one_time_constant():
    """A coil that rises in 4 ms and falls in 20 ms: the laws that know both
    track a viscous demand better than the ones told the rise alone."""
    p = TABLE_I.with_overrides(tau_input=0.004, tau_input_fall=0.020)
    for law in ("smooth", "closed"):
        both = _track(p, law=law)
        rise_only = _track(p, lag_s=0.004, law=law)
        assert both < 0.8 * rise_only, (law, both, rise_only)


def test_the_hysteretic_force_is_compensated():
    """A plant with the hysteretic stiffness: the law that knows it tracks
    better than Table I's law on the same plant."""
    p = TABLE_I.with_overrides(k_hys_pos=200.0, k_hys_neg=1500.0, x_hys=0.01)
    plant_p = p
    known = _track(plant_p)
    plant = DamperPlant(plant_p, DT)
    ctl = SmoothInverse(TABLE_I, 1.0, DT, max_slew_A_per_s=200.0)
    err, ref = [], []
    for k in range(2000):
        v = 0.0628 * math.cos(2 * math.pi * k * DT)
        I = ctl.current(Measurement(v=v), 800.0 * v)
        plant.tick(v, I)
        if k * DT > 0.5:
            err.append(plant.F - 800.0 * v)
            ref.append(800.0 * v)
    unaware = math.sqrt(sum(e * e for e in err) / len(err)) / (max(ref) - min(ref))
    assert known < 0.5 * unaware, (known, unaware)


def test_the_field_lags_the_drivers_current():
    """tau_field: the current monitor (I_applied) shows the driver's lag alone, the
    damper feels the field's too; without it the plant is what it was, bit for bit."""
    p = TABLE_I.with_overrides(tau_input=0.003, tau_field=0.010)
    plant = DamperPlant(p, DT)
    for _ in range(20):
        plant.tick(0.05, 0.5)
    assert plant.I_applied == pytest.approx(0.5 * (1.0 - math.exp(-20 * DT / 0.003)), rel=1e-12)
    assert plant.I_field < plant.I_applied - 0.05  # two lags in series: behind after 20 ms
    ref = DriverLag(0.010, DT)
    drv = DriverLag(0.003, DT)
    for _ in range(20):
        ref.update(drv.update(0.5))
    assert plant.I_field == ref.I
    a, b = DamperPlant(TABLE_I.with_overrides(tau_input=0.003), DT), DamperPlant(TABLE_I, DT, driver_tau_s=0.003)
    for k in range(200):
        v = 0.06 * math.cos(2 * math.pi * k * DT)
        assert a.tick(v, 0.3) == b.tick(v, 0.3) and a.I_field == a.I_applied


def test_laws_told_the_force_lag_compensate_driver_and_field():
    """The laws compensate tau_input + tau_field as one lag: on a plant whose field lags 10 ms behind a
    3 ms driver, smooth told both tracks better than told the driver's lag alone (bench/force_lag.py)."""
    plant_p = TABLE_I.with_overrides(tau_input=0.003, tau_field=0.010)
    both = _track_told(plant_p, plant_p)
    driver_only = _track_told(plant_p, TABLE_I.with_overrides(tau_input=0.003))
    assert both < 0.7 * driver_only, (both, driver_only)
    assert SmoothInverse(plant_p, 1.0, DT).lag_s == pytest.approx(0.013)


def _track_told(plant_p, law_p, seconds=2.0):
    plant = DamperPlant(plant_p, DT)
    ctl = SmoothInverse(law_p, 1.0, DT, max_slew_A_per_s=200.0)
    err, ref = [], []
    for k in range(int(seconds / DT)):
        v = 0.0628 * math.cos(2 * math.pi * k * DT)
        I = ctl.current(Measurement(v=v), 800.0 * v)
        ctl.applied(I)
        plant.tick(v, I)
        if k * DT > 0.5:
            err.append(plant.F - 800.0 * v)
            ref.append(800.0 * v)
    return math.sqrt(sum(e * e for e in err) / len(err)) / (max(ref) - min(ref))
