"""Figures accumulated block by block equal their whole-column definitions
(mrctl/runlog/blockmetrics.py against metrics.tracking_summary,
ride.ride_summary and acceptance.row_figures)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mrctl.runlog.acceptance import row_figures
from mrctl.runlog.blockmetrics import ExactSum, FigureSet, RideFigures, RowFigures, TrackingFigures
from mrctl.runlog.metrics import tracking_summary
from mrctl.runlog.ride import ride_summary

DT = 1e-3
#: figures that are sums of squares: equal for one block, within rounding for several
SUMS = ("force_rmse_N", "force_nrmse", "rms_a_sprung_mps2", "rms_tyre_defl_m", "rms_stroke_m")


def _run(n: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    F_des = 300.0 * np.sin(2 * np.pi * t) + rng.normal(0, 5, n)
    F = F_des + rng.normal(0, 2, n)
    I = np.clip(rng.normal(0.3, 0.3, n), 0.0, 0.6)
    x = 0.01 * np.sin(2 * np.pi * t)
    F[rng.random(n) < 0.02] = math.nan  # no load cell reading
    x[(t > 0.3) & (t < 0.42)] = math.nan  # no usable sample: forced 0 A
    x[-5:] = math.nan  # still at 0 A when the run ends
    fault = np.where(rng.random(n) < 0.01, 8.0, 0.0)
    k = np.arange(n, dtype=float)
    k[n // 2:] += 3  # three skipped deadlines
    return {"t": t, "F_des": F_des, "F": F, "I": I, "x": x, "fault": fault, "k": k,
            "a_sprung": rng.normal(0, 1, n), "tyre_defl": rng.normal(0, 1e-3, n)}


def _blocks(cols: dict[str, np.ndarray], cuts: list[int]):
    edges = [0, *cuts, len(next(iter(cols.values())))]
    for a, b in zip(edges[:-1], edges[1:]):
        yield {c: v[a:b] for c, v in cols.items()}


def _whole(cols: dict[str, np.ndarray], settle_s: float, I_max: float) -> dict[str, float]:
    return {**tracking_summary(cols["t"], cols["F_des"], cols["F"], cols["I"], I_max, settle_s),
            **ride_summary(cols, settle_s), **row_figures(cols, DT)}


def _streamed(cols: dict[str, np.ndarray], cuts: list[int], settle_s: float, I_max: float) -> dict[str, float]:
    figs = FigureSet([TrackingFigures(settle_s, I_max), RideFigures(settle_s), RowFigures(DT)])
    for block in _blocks(cols, cuts):
        figs.add(block)
    return figs.result()


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def test_one_block_gives_the_same_floats():
    cols = _run(4001, 1)
    whole, streamed = _whole(cols, 1.0, 0.6), _streamed(cols, [], 1.0, 0.6)
    assert whole.keys() == streamed.keys()
    for key in whole:
        assert _same(whole[key], streamed[key]), key


@pytest.mark.parametrize("seed", range(6))
def test_any_cut_into_blocks_gives_the_same_figures(seed):
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(2, 5000))
    cols = _run(n, seed)
    # blocks of random sizes, some of one row, one cut at the window's start
    cuts = sorted(set(rng.integers(1, n, int(rng.integers(0, 40))).tolist()) | ({1000} if n > 1000 else set()))
    settle = float(rng.choice([0.0, 0.5, 1.0, n * DT]))  # the last: a window under 2 rows, the whole run instead
    whole, streamed = _whole(cols, settle, 0.6), _streamed(cols, cuts, settle, 0.6)
    assert whole.keys() == streamed.keys()
    for key in whole:
        if key in SUMS:
            assert streamed[key] == pytest.approx(whole[key], rel=1e-13, nan_ok=True), key
        else:
            assert _same(whole[key], streamed[key]), key


def test_stretches_across_blocks_and_at_the_end():
    n = 100
    cols = {"t": np.arange(n) * DT, "x": np.zeros(n), "fault": np.zeros(n), "k": np.arange(n, dtype=float)}
    cols["x"][10:40] = math.nan  # 30 ticks across three blocks
    cols["fault"][90:] = 1.0  # open at the end: lasts until the tick after the last
    figs = RowFigures(DT)
    for block in _blocks(cols, [15, 20, 95]):
        figs.add(block)
    out = figs.result()
    assert out["longest_zero_stretch_s"] == pytest.approx(30 * DT)
    assert out["fault_share"] == pytest.approx(0.1)
    assert out == row_figures(cols, DT)


def test_a_run_with_no_varying_force_has_no_nrmse():
    n = 3000
    cols = {"t": np.arange(n) * DT, "F_des": np.zeros(n), "F": np.ones(n), "I": np.full(n, 0.6)}
    figs = TrackingFigures(1.0, 0.6)
    for block in _blocks(cols, [700, 1500]):
        figs.add(block)
    out = figs.result()
    assert math.isnan(out["force_nrmse"]) and out["force_rmse_N"] == 1.0 and out["share_at_I_max"] == 1.0


def test_exact_sum_is_the_correctly_rounded_sum():
    values = [1e16, 1.0, -1e16, 1e-3, 3.3, -2.2] * 50 + [0.1] * 1000
    s = ExactSum()
    for v in values:
        s.add(v)
    assert s.value() == math.fsum(values)
    s.add(math.inf)
    assert s.value() == math.inf
