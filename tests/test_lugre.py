"""Forward model: integrator accuracy against a fine-step reference, and stability."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mrctl.model.lugre import LuGreModel, advance_z, force
from mrctl.model.params import TABLE_I

from scipy import integrate as scipy_integrate

DT = 1e-3


def _reference_force(I, vmax, f, T):
    """Radau with tight tolerances on the continuous v(t): the 'fine-step' truth."""
    p = TABLE_I

    def vf(t):
        return vmax * math.cos(2 * math.pi * f * t)

    def rhs(t, y):
        v = vf(t)
        return [v - p.sigma0(I) * abs(v) * y[0] / p.g(v, I)]

    ts = np.arange(int(round(T / DT)) + 1) * DT
    sol = scipy_integrate.solve_ivp(rhs, (0, ts[-1]), [0.0], method="Radau", t_eval=ts,
                                    rtol=1e-10, atol=1e-14, max_step=5e-4)
    assert sol.success
    return ts, vf, np.array([force(p, z, vf(t), I) for z, t in zip(sol.y[0], ts)])


@pytest.mark.parametrize("I", [0.0, 0.05, 0.3, 0.6, 1.0])
@pytest.mark.parametrize("vmax,f", [(0.5, 8.0), (0.5, 2.0), (0.0628, 1.0)])
def test_1ms_step_matches_fine_reference(I, vmax, f):
    """Max force error below 0.5 % of the force's peak-to-peak at dt = 1 ms,
    including 0 A at 0.5 m/s where σ0|v|/g·dt ≈ 15 (explicit RK4 diverges)."""
    ts, vf, F_ref = _reference_force(I, vmax, f, T=1.25 / f)
    m = LuGreModel(TABLE_I, v0=vf(0.0))
    F = [m.force(vf(0.0), I)]
    for t in ts[1:]:
        m.advance(vf(t), I, DT)
        F.append(m.force(vf(t), I))
    err = np.max(np.abs(np.array(F) - F_ref))
    assert err < 0.005 * np.ptp(F_ref), f"max error {err:.4g} N"


def test_stiffness_is_real_at_low_current():
    p = TABLE_I
    a = p.sigma0(0.0) * 0.5 / p.g(0.5, 0.0)
    assert a * DT > 10  # beyond any explicit method's stability region


def test_advance_z_is_the_exact_solution():
    z0, v, a, h = 1e-5, 0.3, 2500.0, 1e-3
    exact = v / a + (z0 - v / a) * math.exp(-a * h)
    assert advance_z(z0, v, a, h) == pytest.approx(exact, rel=1e-14)
    # a = 0 (v = 0 or tiny): ż = v, z grows linearly, no 0/0
    assert advance_z(z0, 0.0, 0.0, h) == z0
    assert advance_z(z0, 1e-9, 1e-12, h) == pytest.approx(z0 + 1e-12, rel=1e-9)


velocities = st.lists(st.floats(min_value=-0.5, max_value=0.5, allow_nan=False), min_size=1, max_size=200)


@settings(max_examples=200, deadline=None)
@given(I=st.floats(min_value=0.0, max_value=1.0), vs=velocities, z0=st.floats(min_value=-1e-3, max_value=1e-3))
def test_z_never_leaves_its_invariant_bound(I, vs, z0):
    """Stability for any velocity sequence, including jumps: each update is a
    convex combination of z and the sliding value ±g/σ0, so |z| can never
    exceed max(|z0|, max g/σ0). An unstable integrator would blow through it."""
    p = TABLE_I
    bound = max(abs(z0), max(p.g(0.0, I), p.Fc(I)) / p.sigma0(I)) * (1 + 1e-12)
    m = LuGreModel(p, z0=z0)
    for v in vs:
        z = m.advance(v, I, DT)
        assert math.isfinite(z) and abs(z) <= bound
        assert math.isfinite(m.force(v, I))


def test_zero_velocity_holds_z():
    m = LuGreModel(TABLE_I, z0=2e-5)
    for _ in range(10):
        m.advance(0.0, 0.3, DT)
    assert m.z == 2e-5


def test_substeps_converge_to_reference():
    ts, vf, F_ref = _reference_force(0.0, 0.5, 2.0, T=1.0)
    errs = []
    for n in (1, 4):
        m = LuGreModel(TABLE_I, v0=vf(0.0), substeps=n)
        F = [m.force(vf(0.0), 0.0)]
        for t in ts[1:]:
            m.advance(vf(t), 0.0, DT)
            F.append(m.force(vf(t), 0.0))
        errs.append(np.max(np.abs(np.array(F) - F_ref)))
    assert errs[1] < errs[0] / 4


@settings(max_examples=200, deadline=None)
@given(st.floats(-5e-4, 5e-4), st.floats(-0.1, 0.1), st.floats(-2e-3, 2e-3), st.floats(0.0, 0.6),
       st.sampled_from([0.0, 1e-3, 0.02]), st.integers(1, 5))
def test_look_ahead_is_advance_then_force_bit_for_bit(z0, v0, dv, I, dI, n):
    """The closed law's horizon: both fused trajectories are exactly what a
    model advanced tick by tick at the held current gives, and the state
    they start from is left as it was."""
    mod = LuGreModel(TABLE_I, z0=z0, v0=v0)
    out, out1 = [math.nan] * n, [math.nan] * n
    mod.look_ahead(v0, dv, I, dI, 1e-3, LuGreModel(TABLE_I), out, out1)
    assert (mod.z, mod.v_prev) == (z0, v0)
    for cur, got in ((I, out), (I + dI, out1)):
        ref = LuGreModel(TABLE_I, z0=z0, v0=v0)
        v = v0
        for j in range(n):
            v = v + dv
            ref.advance(v, cur, 1e-3)
            assert got[j] == ref.force(v, cur)
