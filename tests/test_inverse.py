"""Inverse laws: exact recovery without plant lag, clamps, and the spike fix."""

import math

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from mrctl.laws.base import Measurement
from mrctl.laws.inverse import ConstantCurrent, PaperInverse, ScheduleCurrent, SmoothInverse
from mrctl.model.lugre import LuGreModel
from mrctl.model.params import TABLE_I
from mrctl.model.plant import DamperPlant
from mrctl.core.safety import clamp_current


def _m(v: float, x: float = 0.0) -> Measurement:
    """The sample a law sees: velocity v (m/s), displacement x (m)."""
    return Measurement(v=v, x=x)

DT = 1e-3
I_MAX = 1.0


def _law_at_state(cls, z, v, I_prev, **kw):
    law = cls(TABLE_I, I_MAX, DT, **kw)
    law.reset(z0=z, v0=v, I0=I_prev)  # first tick after reset: z is used as given
    return law


def _force_with_frozen_zdot(z, v, I, I_zdot):
    """Eq (1) with the eq (12) assumption: ż computed with the previous current."""
    p = TABLE_I
    m = LuGreModel(p, z0=z)
    zdot = m.zdot(v, I_zdot)
    return p.sigma0(I) * z + p.sigma1(I) * zdot + p.sigma2(I) * v


# physically reachable states: |z| below the sliding bound ~ (Fc+Ac)/σ0
states = dict(
    z=st.floats(min_value=-6e-4, max_value=6e-4),
    v=st.floats(min_value=-0.5, max_value=0.5),
    I=st.floats(min_value=0.0, max_value=I_MAX),
)


@settings(max_examples=300, deadline=None)
@given(**states)
def test_paper_law_recovers_the_current_of_a_lag_free_plant(z, v, I):
    """With the plant at the law's state and the current unchanged since the
    last tick (so eq 12's lagged Fc is exact), eq (12) returns that current."""
    law = _law_at_state(PaperInverse, z, v, I)
    D = TABLE_I.sigma0A * z + TABLE_I.sigma1A * law.model.zdot(v, I) + TABLE_I.sigma2A * v
    assume(abs(D) > 0.5)  # eq (12) is ill-conditioned where ∂F/∂I vanishes
    F = _force_with_frozen_zdot(z, v, I, I)
    assert law.current(_m(v), F) == pytest.approx(I, abs=1e-9)


@settings(max_examples=300, deadline=None)
@given(**states, I_true=st.floats(min_value=0.0, max_value=I_MAX))
def test_paper_law_inverts_its_own_force_model_for_any_new_current(z, v, I, I_true):
    law = _law_at_state(PaperInverse, z, v, I)
    D = TABLE_I.sigma0A * z + TABLE_I.sigma1A * law.model.zdot(v, I) + TABLE_I.sigma2A * v
    assume(abs(D) > 0.5)
    F = _force_with_frozen_zdot(z, v, I_true, I)
    assert law.current(_m(v), F) == pytest.approx(I_true, abs=1e-8)


@settings(max_examples=300, deadline=None)
@given(**states)
def test_smooth_law_recovers_the_current_exactly_at_steady_current(z, v, I):
    law = _law_at_state(SmoothInverse, z, v, I)
    F = _force_with_frozen_zdot(z, v, I, I)
    assert law.current(_m(v), F) == pytest.approx(I, abs=1e-9)  # no regularisation bias here


@settings(max_examples=300, deadline=None)
@given(**states, I_true=st.floats(min_value=0.0, max_value=I_MAX))
def test_smooth_law_moves_toward_the_true_current_within_its_slew_bound(z, v, I, I_true):
    law = _law_at_state(SmoothInverse, z, v, I)
    F = _force_with_frozen_zdot(z, v, I_true, I)
    I_new = law.current(_m(v), F)
    assert abs(I_new - I) <= law.max_step_A + 1e-12
    assert abs(I_new - I_true) <= abs(I - I_true) + 1e-12  # never further away
    if abs(I_true - I) <= law.max_step_A:
        D = TABLE_I.sigma0A * z + TABLE_I.sigma1A * law.model.zdot(v, I) + TABLE_I.sigma2A * v
        if D * D > 1e4 * law.eps2:  # strong authority: regularisation negligible
            assert I_new == pytest.approx(I_true, abs=1e-3 * abs(I_true - I) + 1e-9)


def test_closed_loop_law_state_equals_plant_state_without_lag():
    """The tick protocol is shared: the inverse's z is the plant's z, exactly."""
    plant = DamperPlant(TABLE_I, DT, driver_tau_s=0.0)
    law = SmoothInverse(TABLE_I, 0.6, DT)
    for k in range(3000):
        t = k * DT
        v = 0.0628 * math.cos(2 * math.pi * t)
        I = law.current(_m(v), 500.0 * v)
        plant.tick(v, I)
        assert law.model.z == plant.model.z


def test_paper_clamps_and_non_finite_results():
    law = _law_at_state(PaperInverse, 0.0, 0.0, 0.0)
    # z = v = 0: denominator exactly 0 → ±inf or NaN, clamped to I_max / 0 A
    assert law.current(_m(0.0), 5.0) == I_MAX
    law = _law_at_state(PaperInverse, 0.0, 0.0, 0.0)
    assert law.current(_m(0.0), -5.0) == 0.0
    law = _law_at_state(PaperInverse, 0.0, 0.0, 0.0)
    assert law.current(_m(0.0), 0.0) == 0.0  # 0/0 = NaN → the safe side
    law = _law_at_state(PaperInverse, 2e-5, 0.05, 0.2)
    assert law.current(_m(0.05), 1e6) == I_MAX
    law = _law_at_state(PaperInverse, 2e-5, 0.05, 0.2)
    assert law.current(_m(0.05), -1e6) == 0.0


@pytest.mark.parametrize("cls", [PaperInverse, SmoothInverse])
def test_nan_demand_gives_zero_current(cls):
    law = _law_at_state(cls, 2e-5, 0.05, 0.3)
    assert law.current(_m(0.05), math.nan) == 0.0


def test_safety_clamp():
    assert clamp_current(math.nan, 0.6) == 0.0
    assert clamp_current(-1.0, 0.6) == 0.0
    assert clamp_current(math.inf, 0.6) == 0.6
    assert clamp_current(-math.inf, 0.6) == 0.0
    assert clamp_current(0.3, 0.6) == 0.3


def test_constant_law_and_argument_checks():
    law = ConstantCurrent(0.25, 0.6)
    assert law.current(_m(0.1), 99.0) == 0.25
    with pytest.raises(ValueError):
        ConstantCurrent(0.7, 0.6)
    with pytest.raises(ValueError):
        PaperInverse(TABLE_I, 0.0, DT)
    with pytest.raises(ValueError):
        SmoothInverse(TABLE_I, 0.6, DT, max_slew_A_per_s=0.0)


def test_schedule_law_steps_through_currents_then_zero():
    law = ScheduleCurrent([0.1, 0.3], step_s=0.002, I_max=0.6, dt=DT)
    assert [law.current(_m(0.0), 0.0) for _ in range(6)] == [0.1, 0.1, 0.3, 0.3, 0.0, 0.0]
    law.reset()
    assert law.current(_m(0.0), 0.0) == 0.1
    with pytest.raises(ValueError):
        ScheduleCurrent([0.1, 0.9], 1.0, 0.6, DT)
