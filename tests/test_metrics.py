"""Tracking figures: the one definition behind simulate, run and report."""

import math

import numpy as np

from mrctl.runlog.metrics import tracking_summary


def _run(n=3000):
    t = np.arange(n) * 1e-3
    F_des = 30 * np.sin(2 * np.pi * t)
    F = F_des + 0.3  # known constant error
    I = np.abs(np.sin(2 * np.pi * t)) * 0.6
    return t, F_des, F, I


def test_known_error_and_window():
    t, F_des, F, I = _run()
    s = tracking_summary(t, F_des, F, I, 0.6, 1.0)
    w = t >= 1.0
    assert s["window_start_s"] == 1.0 and s["window_ticks"] == w.sum()
    assert math.isclose(s["force_rmse_N"], 0.3, rel_tol=1e-12)
    assert math.isclose(s["force_nrmse"], 0.3 / np.ptp(F_des[w]), rel_tol=1e-12)


def test_nan_rows_carry_no_value():
    """A daemon log with sample faults (NaN F_des) or no load cell (NaN F)."""
    t, F_des, F, I = _run()
    ref = tracking_summary(t, F_des, F, I, 0.6, 1.0)
    F_des2, F2 = F_des.copy(), F.copy()
    F_des2[1500:1600] = np.nan  # held at 0 A: no demand logged
    F2[2000:2010] = np.nan
    s = tracking_summary(t, F_des2, F2, I, 0.6, 1.0)
    assert math.isclose(s["force_rmse_N"], 0.3, rel_tol=1e-12)
    assert math.isclose(s["force_nrmse"], ref["force_nrmse"], rel_tol=1e-3)
    s = tracking_summary(t, F_des, np.full_like(F, np.nan), I, 0.6, 1.0)
    assert math.isnan(s["force_nrmse"]) and math.isnan(s["force_rmse_N"])


def test_i_max_none_uses_the_runs_own_maximum():
    t, F_des, F, I = _run()
    assert tracking_summary(t, F_des, F, I, None, 1.0)["share_at_I_max"] > 0
    assert tracking_summary(t, F_des, F, I * 0.5, 0.6, 1.0)["share_at_I_max"] == 0.0


def test_summary_of_a_run_without_a_force_to_track_says_so():
    """A current schedule (identify.yaml) demands no force: no 'nan %'."""
    import math

    from mrctl.runlog.metrics import format_summary

    s = {"window_start_s": 0.5, "force_nrmse": math.nan, "force_rmse_N": 4.0, "max_current_step_A": 0.05,
         "share_at_zero": 0.6, "share_at_I_max": 0.0}
    text = format_summary(s, 0.6)
    assert "nan" not in text and "no varying force demanded" in text
    assert "0.250 %" in format_summary({**s, "force_nrmse": 0.0025}, 0.6)


def test_a_run_without_a_settled_window_gives_its_rmse_and_says_the_nrmse_is_not_judged():
    """Normalised by the few newtons a start-up demands, a 2-tick run's NRMSE read 6225967 %;
    the summary gives the RMSE and says why the NRMSE is not judged, as the verdict does."""
    from mrctl.runlog.acceptance import tracking_judged
    from mrctl.runlog.metrics import format_summary

    t, F_des, F, I = _run()  # 4 s at 1 kHz
    dt = float(t[1] - t[0])
    for n, settle, why in ((2, 1.0, "ends before excitation.settle_s (1 s)"),
                           (1500, 1.0, "0.500 s past excitation.settle_s (1 s), under the 1 s"),
                           (1500, 0.0, "")):
        s = tracking_summary(t[:n], F_des[:n], F[:n], I[:n], 0.6, settle)
        text = format_summary(s, 0.6, dt, settle).splitlines()[0]
        judged = tracking_judged(s, settle, dt)["force_nrmse"]
        if why:
            assert text.startswith("force RMSE") and "%" not in text and why in text, text
            assert judged is None
        else:
            assert text.startswith("force NRMSE (t >= 0.000 s): ") and judged == s["force_nrmse"], text
    assert format_summary(s, 0.6).startswith("force NRMSE")  # no period given: the figure as it is
