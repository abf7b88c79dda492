"""Eq (6)–(11) and Table I against the spec's sanity values."""

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mrctl.model.mapping import params_from_mapping
from mrctl.model.params import TABLE_I, LuGreParams, langevin


def test_sanity_values_from_spec():
    assert TABLE_I.Fc(0.0) == 2.90
    assert TABLE_I.Fc(0.25) == pytest.approx(14.05, abs=0.01)
    assert TABLE_I.Fc(0.5) == pytest.approx(30.02, abs=0.01)


def test_linear_laws_match_table_I():
    p = TABLE_I
    assert p.sigma0(0.5) == pytest.approx(1.396e5 * 0.5 + 8.96e4)
    assert p.sigma1(0.0) == -289.1  # negative below ~0.26 A, as identified
    assert p.sigma1(0.3) > 0.0
    assert p.sigma2(1.0) == pytest.approx(99.52 + 14.55)
    assert p.Fs(0.2) == pytest.approx(13.8 * 0.2 + 0.6466)
    assert p.vs(0.5) == pytest.approx(-0.0164 * 0.5 + 0.0281)


@pytest.mark.parametrize("I", [1e-300, 1e-12, 1e-6, 1e-3, 0.0088, 0.00881, 0.0089, 0.1, 0.6, -1e-9])
def test_Fc_exact_and_finite_at_and_near_zero(I):
    """Against a 50-digit evaluation of (6): the naive coth(x) - 1/x loses
    every digit near 0; the series branch must not."""
    import mpmath
    mpmath.mp.dps = 50
    x = mpmath.mpf(I) / mpmath.mpf(TABLE_I.Bc)
    L = mpmath.coth(x) - 1 / x
    ref = float(mpmath.mpf(TABLE_I.Ac) * L * L + mpmath.mpf(TABLE_I.F0))
    Fc = TABLE_I.Fc(I)
    assert math.isfinite(Fc)
    assert Fc == pytest.approx(ref, rel=1e-13)
    # the part above F0 too, where cancellation would show first
    above = float(mpmath.mpf(TABLE_I.Ac) * L * L)
    if above > 1e-9:
        assert Fc - TABLE_I.F0 == pytest.approx(above, rel=1e-6)


def test_langevin_series_joins_the_closed_form_smoothly():
    # at the switch point both forms must agree to near machine precision
    for x in (0.0499999, 0.05, 0.0500001, -0.05):
        closed = 1.0 / math.tanh(x) - 1.0 / x
        assert langevin(x) == pytest.approx(closed, rel=1e-12)
    assert langevin(0.0) == 0.0


@given(st.floats(min_value=0.0, max_value=2.0))
def test_Fc_even_monotone_and_bounded(I):
    p = TABLE_I
    assert p.Fc(I) == pytest.approx(p.Fc(-I), rel=1e-15)
    assert p.F0 <= p.Fc(I) <= p.F0 + p.Ac
    assert p.Fc(I + 1e-3) >= p.Fc(I)


def test_g_positive_over_the_operating_range():
    p = TABLE_I
    for i in range(101):
        I = i / 100.0
        for v in (-0.5, -0.01, 0.0, 1e-6, 0.02, 0.5):
            assert p.g(v, I) > 0.0
    assert p.check_range(1.0) == []


def test_check_range_names_the_failing_law():
    bad = TABLE_I.with_overrides(vsB=0.01)  # vs(I) < 0 above 0.61 A
    problems = bad.check_range(1.0)
    assert len(problems) == 1 and problems[0].startswith("vs(I)")
    assert bad.check_range(0.5) == []


def test_params_from_mapping_overrides_and_errors():
    p = params_from_mapping({"F0": 3, "Ac": 60.0})
    assert p.F0 == 3.0 and p.Ac == 60.0 and p.Bc == TABLE_I.Bc
    with pytest.raises(ValueError, match="^sigma9: unknown parameter"):
        params_from_mapping({"sigma9": 1.0})
    with pytest.raises(ValueError, match="^F0: must be a number"):
        params_from_mapping({"F0": "three"})
    with pytest.raises(ValueError, match="^F0: must be a number"):
        params_from_mapping({"F0": True})
    with pytest.raises(ValueError, match="^Ac: must be finite"):
        params_from_mapping({"Ac": float("nan")})


def test_names_are_the_spec_names():
    assert LuGreParams.names() == (
        "F0", "Ac", "Bc", "sigma0A", "sigma0B", "sigma1A", "sigma1B",
        "sigma2A", "sigma2B", "FsA", "FsB", "vsA", "vsB",
    )
