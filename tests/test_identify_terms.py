"""Identification of the optional model terms, on records made by our own plant.

A broadband record from a damper whose input falls slower than it rises,
whose bristle damping fades with velocity and which has a hysteretic
stiffness per direction; a constant-input record from one with the
hysteretic stiffness. The fits with the terms must recover them and predict
the held-out data at the noise floor where the fits without them cannot; the
written set carries them to the plant (docs/identification.md, "Model terms").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from identify_synth import TRUTH, broadband_record, sine_levels_record, write_csv
from mrctl.config import load_params_file
from mrctl.config.dataset import load_dataset
from mrctl.errors import MrctlError
from mrctl.model.plant import DamperPlant
from mrctl.offline.identify import identify_dataset
from mrctl.offline.identify.bbmodel import SpanData, felt_input, from_params, simulate
from mrctl.offline.identify.result import write_result

BB_TRUTH = replace(TRUTH, tau_input=0.004, tau_input_fall=0.015, sigma1_vd=0.05, k_hys_pos=2.0e4,
                   k_hys_neg=3.0e4, x_hys=0.0015)
SINE_TRUTH = replace(TRUTH, tau_input=0.0, k_hys_pos=500.0, k_hys_neg=3000.0, x_hys=0.008)

BB = """version: 1
protocol: broadband
input: voltage
columns: {time: t, displacement: x, force: F, input: u}
sample_rate_hz: 3000
resample_hz: 1000
motion_band_hz: 15
files: [{path: bb.csv, name: bb}]
fit: {starts: 2, max_nfev: 40}
"""


def test_the_simulation_with_the_terms_is_the_plant_tick_by_tick():
    """The fit's batched model (a rise and a fall lag, σ1(v), the hysteretic
    stiffness) equals DamperPlant after its warm-up."""
    dt, n = 1e-3, 3000
    rng = np.random.default_rng(0)
    t = np.arange(n) * dt
    x = 0.005 * np.sin(2 * np.pi * 1.3 * t) + 0.002 * np.sin(2 * np.pi * 4.1 * t)
    v = 2 * np.pi * (0.005 * 1.3 * np.cos(2 * np.pi * 1.3 * t) + 0.002 * 4.1 * np.cos(2 * np.pi * 4.1 * t))
    u = np.repeat(rng.choice([0.0, 1.0, 2.0], n // 50), 50)
    plant = DamperPlant(BB_TRUTH, dt)
    F = np.array([plant.tick(vk, uk, xk) for vk, uk, xk in zip(v, u, x)])
    P = from_params(BB_TRUTH, 0.0, 2.0)
    Fs = simulate(P[None], SpanData(u, v, x, np.zeros(n), dt), 0.0, 2.0)[0]
    assert np.max(np.abs(Fs - F)[500:]) < 1e-8 * np.ptp(F)


def test_the_rise_and_fall_lag_is_the_drivers_exactly():
    """The nonlinear lag solved by passes of the scan is the driver's recursion."""
    rng = np.random.default_rng(3)
    u = np.repeat(rng.uniform(0.0, 2.0, 200), rng.integers(1, 40, 200))
    plant = DamperPlant(replace(TRUTH, tau_input=0.003, tau_input_fall=0.02), 1e-3)
    plant.driver.I = u[0]  # settled at the first command, as felt_input starts
    want = [plant.driver.update(float(q)) for q in u]
    assert np.allclose(felt_input(u, 0.003, 1e-3, 0.02), want, rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def bb(tmp_path_factory):
    d = tmp_path_factory.mktemp("bbx")
    write_csv(d / "bb.csv", broadband_record(params=BB_TRUTH), {"t": "t", "x": "x", "F": "F", "u": "u"})
    (d / "ds.yaml").write_text(BB + "model: {lag_fall: true, sigma1_v: true, hysteresis: true}\n")
    (d / "plain.yaml").write_text(BB)
    return d


def test_broadband_fit_recovers_the_terms(bb, tmp_path):
    res = identify_dataset(bb / "ds.yaml")
    p = res.params
    assert p.tau_input == pytest.approx(0.004, rel=0.15)
    assert p.tau_input_fall == pytest.approx(0.015, rel=0.15)
    assert p.k_hys_neg * p.x_hys == pytest.approx(3.0e4 * 0.0015, rel=0.25)  # the saturated force
    (score,) = res.holdout
    plain = identify_dataset(bb / "plain.yaml").holdout[0]
    # 1 N noise on ~330 N: the terms' fit at the floor, the plain fit well above
    assert score.nrmse < 0.006 and plain.nrmse > 2.0 * score.nrmse, (score.nrmse, plain.nrmse)
    write_result(res, tmp_path / "p.yaml")
    assert load_params_file(tmp_path / "p.yaml").extras() == pytest.approx(p.extras())


@pytest.fixture(scope="module")
def sine(tmp_path_factory):
    d = tmp_path_factory.mktemp("sinex")
    rec, segs = sine_levels_record([0.0, 1.0, 2.0], params=SINE_TRUTH, seed=5)
    rec2, segs2 = sine_levels_record([0.0, 1.0, 2.0], params=SINE_TRUTH, seed=6, freq_hz=1.5, amp_m=0.006)
    for name, r in (("a", rec), ("b", rec2)):
        write_csv(d / f"{name}.csv", r, {"t": "t", "x": "x", "F": "F", "u": "I"})
    head = ("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, force: F, input: I}\n"
            "files: [a.csv, b.csv]\n")
    (d / "ds.yaml").write_text(head + "model: {hysteresis: true}\n")
    (d / "plain.yaml").write_text(head)
    return d


def test_constant_input_fit_recovers_the_hysteretic_stiffness_per_level(sine, tmp_path):
    res = identify_dataset(sine / "ds.yaml")
    plain = identify_dataset(sine / "plain.yaml")
    assert res.details["hysteresis"]["x_hys_m"] == pytest.approx(SINE_TRUTH.x_hys, rel=0.15)
    for lv in res.details["levels"]:
        assert lv["k_hys_neg"] == pytest.approx(SINE_TRUTH.k_hys_neg, rel=0.10), lv["level"]
        assert abs(lv["k_hys_pos"] - SINE_TRUTH.k_hys_pos) < 0.1 * SINE_TRUTH.k_hys_neg, lv["level"]
    worst = max(s.nrmse_laws for s in res.holdout)
    assert worst < 0.01 and max(s.nrmse_laws for s in plain.holdout) > 2.0 * worst
    write_result(res, tmp_path / "p.yaml")
    p = load_params_file(tmp_path / "p.yaml")
    assert p.has_hysteresis and p.x_hys == res.params.x_hys
    if p.table is not None:  # per-level values in the table, as the offset and the stiffness
        assert p.table.has_hys()


@pytest.mark.parametrize("model, message", [
    ("{lag_fall: true}", "model.lag_fall: broadband only"),
    ("{sigma1_v: true}", "model.sigma1_v: broadband only"),
])
def test_broadband_terms_are_refused_for_constant_input(sine, model, message):
    text = (sine / "plain.yaml").read_text() + f"model: {model}\n"
    (sine / "bad.yaml").write_text(text)
    with pytest.raises(MrctlError, match=message):
        load_dataset(sine / "bad.yaml")


def test_a_falling_lag_without_the_lag_is_refused(bb):
    (bb / "bad.yaml").write_text(BB + "model: {lag: false, lag_fall: true}\n")
    with pytest.raises(MrctlError, match="model.lag_fall: needs model.lag"):
        load_dataset(bb / "bad.yaml")
