"""Latency compensation: the velocity lead predicts ahead without amplifying noise."""

import math
import random

import numpy as np
import pytest

from mrctl.estimation import VelocityLead

DT = 1e-3
W = 2 * math.pi  # 1 Hz
LEAD = 1.5e-3


def _v(t):
    return 0.0628 * math.cos(W * t)


def test_lead_predicts_the_velocity_ahead():
    p = VelocityLead(LEAD, DT)
    err_lead, err_none = [], []
    for k in range(3000):
        t = k * DT
        vh = p.update(_v(t))
        if k > 100:
            err_lead.append(vh - _v(t + LEAD))
            err_none.append(_v(t) - _v(t + LEAD))
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(err_lead) < 0.1 * rms(err_none)


def test_noise_is_not_amplified_much():
    rng = random.Random(1)
    p = VelocityLead(LEAD, DT)
    out = [p.update(rng.gauss(0.0, 1e-4)) for _ in range(5000)]
    assert np.std(out[200:]) < 1.5e-4  # raw noise 1e-4; a plain difference would give ~2e-4


def test_skipped_ticks_and_nan():
    p = VelocityLead(LEAD, DT)
    p.update(0.0)
    p.update(0.01, ticks=10)  # 10 ticks apart: a = 1 m/s^2, not 10
    assert p.a_hat == pytest.approx(1.0 * p.alpha)
    assert math.isnan(p.update(math.nan))
    assert math.isfinite(p.update(0.02))
    with pytest.raises(ValueError):
        VelocityLead(-1.0, DT)
