"""Identification from end to end: runs in, an IdentificationResult out.

:func:`identify` works on run records (``{column: array}``);
:func:`identify_files` is what ``mrctl identify`` calls: run CSVs in, the
parameters YAML written, the result returned, every problem a typed error
(:mod:`mrctl.offline.identify.errors`) whose message is for the user.
"""

from __future__ import annotations

import math
import os
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from mrctl.offline.identify.errors import IdentificationError, merge_warnings, require_scipy
from mrctl.offline.identify.fit import DEFAULT_METHOD, METHODS, _fit_one_current, _identifiability, _noise_N
from mrctl.offline.identify.guards import Support, check_laws, theta_problems
from mrctl.model.params import LuGreParams
from mrctl.offline.identify.laws import bench_at, fit_laws, table_set, theta_from_params
from mrctl.offline.identify.model import THETA_NAMES, _model_batch
from mrctl.offline.identify.result import CurrentFit, IdentificationResult, write_params_yaml
from mrctl.offline.identify.runs import _check_run, common_period, decimate, fit_windows, load_identification_run

__all__ = ["ProgressFn", "identify", "identify_files"]

#: ``progress(index, total, current_A, elapsed_s, nrmse)``, index 1-based
ProgressFn = Callable[[int, int, float, float, float], None]


def identify(runs: Sequence[Mapping[str, Any]], *, method: str = DEFAULT_METHOD,
             settle_periods: float = 1.0, warmup_periods: float = 1.0, fit_periods: float | None = None,
             max_rate_hz: float | None = 2000.0, period_s: float | None = None, F0: str = "fit",
             progress: ProgressFn | None = None, sources: Sequence[str] | None = None,
             offset: bool = False, stiffness: bool = False, laws_kind: str = "auto") -> IdentificationResult:
    """Identify the 13 LuGre constants from constant-current sine runs.

    Args:
        runs: run records ``{column: array}`` with t, I (commanded current),
            F_meas (or F), v_meas (or v); I_applied is used when present.
        method: "trf" (default), "trf-bounds", "lm" or "nelder-mead" (the
            paper's fminsearch); see :data:`METHODS` and docs/identification.md.
        settle_periods: periods dropped after every change of current.
        warmup_periods: periods the candidate model runs before Q is
            accumulated (taken from the settling part when it is long enough).
        fit_periods: whole periods per segment in Q (None: all available).
        max_rate_hz: records sampled faster are decimated (anti-aliased).
        period_s: excitation period; estimated from the velocity if None.
        F0: "fit" or "measured" (see :func:`fit_laws`).
        progress: called after each current as
            ``progress(index, total, current_A, elapsed_s, nrmse)``, index 1-based,
            elapsed since the start of identify.
        sources: a name per run for messages and the YAML (default "run 1"…).
        offset: fit a constant force offset at every current (a real
            bench's load-cell zero, accumulator preload), solved exactly for
            every Θ; the set's F_offset is their mean weighted by samples.
        stiffness: fit a stiffness k_x on the displacement too (needs x_meas or x).
        laws_kind: the written laws: "paper" (6)–(11), "table" (every current's
            Θ, offset and stiffness interpolated piecewise linearly), or "auto":
            whichever predicts better each interior current left out of the laws.
    Raises:
        IdentificationError: bad or insufficient input, with a message for the
            user; also a fit that leaves what the data support (a per-current
            Θ or a law over the identified range): no absurd set is returned.
        DependencyMissing: scipy is not installed.
    """
    if laws_kind not in ("auto", "paper", "table"):
        raise IdentificationError(f"laws: {laws_kind!r} not allowed (auto, paper or table)")
    if method not in METHODS:
        raise IdentificationError(f"unknown method {method!r} (one of {', '.join(METHODS)})")
    if isinstance(runs, Mapping):
        runs = [runs]
    runs = list(runs)
    if not runs:
        raise IdentificationError("no runs given")
    labels = list(sources) if sources is not None else [f"run {k + 1}" for k in range(len(runs))]
    if len(labels) != len(runs):
        raise IdentificationError("sources: need one name per run")
    if settle_periods < 0 or warmup_periods < 0 or (fit_periods is not None and fit_periods < 1):
        raise IdentificationError("settle/warm-up periods must be ≥ 0 and fit_periods ≥ 1")
    require_scipy()
    t_start = time.perf_counter()
    warnings: list[str] = []
    checked = [_check_run(r, lab) for r, lab in zip(runs, labels)]
    if stiffness and not all("x" in c for c in checked):
        raise IdentificationError("stiffness: needs a displacement column (x_meas or x) in every run")
    use_x = stiffness
    dts = decimate(checked, labels, max_rate_hz, warnings)
    T = common_period(checked, labels, period_s)
    groups = fit_windows(checked, labels, dts, T, settle_periods, warmup_periods, fit_periods, warnings)

    fits: list[CurrentFit] = []
    total = len(groups)
    for gi, I_cmd in enumerate(sorted(groups)):
        t0 = time.perf_counter()
        windows = []
        Iapp = []
        segs_info = []
        Xs, xs = [], []
        for r, w0, f0, f1 in groups[I_cmd]:
            c = checked[r]
            h = np.empty(f1 - w0)
            h[1:] = np.diff(c["t"][w0:f1])
            h[0] = dts[r]
            windows.append((c["v"][w0:f1], c["F"][w0:f1], h, f0 - w0))
            Iapp.append(c.get("I_applied", c["I"])[f0:f1])
            segs_info.append((r, float(c["t"][f0]), float(c["t"][f1 - 1])))
            cols = ([np.ones(f1 - f0)] if offset else []) + ([c["x"][f0:f1]] if use_x else [])
            Xs.append(np.column_stack(cols) if cols else None)
            if "x" in c:
                xs.append(c["x"][f0:f1])
        X = np.vstack(Xs) if Xs[0] is not None else None
        theta, prob, p, notes, nfev, theta0, starts = _fit_one_current(windows, method, X=X)
        rec = prob.rec
        F_fit = _model_batch(theta[None, :], rec)[0]
        beta = rec.linear_terms(F_fit)
        off_k = (float(beta[0]) if offset else 0.0, float(beta[-1]) if use_x else 0.0)
        F_fit = rec.with_terms(F_fit)
        res = F_fit - rec.F
        rms = float(np.sqrt(np.mean(res * res)))
        ptp = float(np.ptp(rec.F))
        noise = float(np.median([_noise_N(w[1][w[3]:]) for w in windows]))
        se, rel_se, sens, corr, det = _identifiability(prob, p, theta, ptp)
        cf = CurrentFit(
            current=float(np.mean(np.concatenate(Iapp))), current_cmd=float(I_cmd),
            theta={k: float(theta[j]) for j, k in enumerate(THETA_NAMES)},
            theta0={k: float(theta0[j]) for j, k in enumerate(THETA_NAMES)}, start_notes=notes,
            nrmse=rms / ptp if ptp > 0 else math.nan, noise_nrmse=noise / ptp if ptp > 0 else math.nan,
            rms_N=rms, ptp_N=ptp, noise_N=noise, se=se, rel_se=rel_se, sensitivity=sens, corr=corr,
            determined=det,
            nfev=nfev, starts=starts, time_s=time.perf_counter() - t0, samples=int(rec.F.size),
            periods=float(sum((f1 - f0) for _, _, f0, f1 in groups[I_cmd]) * dts[groups[I_cmd][0][0]] / T),
            segments=segs_info, v=rec.v[rec.fit].copy(), F_meas=rec.F.copy(), F_fit=F_fit,
        )
        cf._rec = rec  # type: ignore[attr-defined]  # for the law-based NRMSE below
        cf._x = np.concatenate(xs) if use_x else None  # type: ignore[attr-defined]
        cf.offset_N, cf.k_x = off_k
        cf._support = Support.of(rec.F - (rec.X @ beta if rec.X is not None else 0.0), rec.v[rec.fit],  # type: ignore[attr-defined]
                                 np.concatenate(xs) if xs else None)
        problems = theta_problems(cf.theta, cf._support, f"{cf.current:.4g} A")  # type: ignore[attr-defined]
        if problems:
            raise IdentificationError("the fit at a current is not physical, so no parameters file was written:\n  "
                                      + "\n  ".join(problems))
        fits.append(cf)
        if progress is not None:
            progress(gi + 1, total, cf.current, time.perf_counter() - t_start, cf.nrmse)

    I_arr = np.array([f.current for f in fits])
    sup = max((f._support for f in fits), key=lambda q: q.F_amp)  # type: ignore[attr-defined]
    params, laws = fit_laws(I_arr, {k: np.array([f.theta[k] for f in fits]) for k in THETA_NAMES}, F0,
                            floors=sup.floors())
    if offset or use_x:
        w = np.array([f.samples for f in fits], float)
        params = params.with_overrides(F_offset=float(np.average([f.offset_N for f in fits], weights=w)),
                                       k_x=float(np.average([f.k_x for f in fits], weights=w)))
    check_laws(params, float(I_arr.min()), float(I_arr.max()), sup)
    bench = offset or use_x

    def candidates(part: list[CurrentFit]) -> dict[str, LuGreParams]:
        """The paper-law set and the table of these currents' fits."""
        I_p = np.array([f.current for f in part])
        th = {k: np.array([f.theta[k] for f in part]) for k in THETA_NAMES}
        if part is fits:
            paper = params
        else:
            paper, _ = fit_laws(I_p, th, F0, floors=sup.floors())
            if bench:
                wp = np.array([f.samples for f in part], float)
                paper = paper.with_overrides(F_offset=float(np.average([f.offset_N for f in part], weights=wp)),
                                             k_x=float(np.average([f.k_x for f in part], weights=wp)))
        out = {"paper": paper}
        if len(part) >= 2 and np.all(np.diff(I_p) > 0.0):
            out["table"] = table_set(paper, I_p, th, np.array([f.offset_N for f in part]) if bench else None,
                                     np.array([f.k_x for f in part]) if bench else None)
        return out

    def law_force(p: LuGreParams, f: CurrentFit) -> np.ndarray:
        off, kx = bench_at(p, f.current)
        with np.errstate(all="ignore"):
            F = _model_batch(theta_from_params(p, f.current)[None, :], f._rec)[0] + off  # type: ignore[attr-defined]
        return F + kx * f._x if f._x is not None else F  # type: ignore[attr-defined]

    # which laws to write: each interior current predicted by the sets of the others' fits
    loo: dict[str, dict[float, float]] = {"paper": {}, "table": {}}
    for k in range(1, len(fits) - 1):
        try:
            cands = candidates(fits[:k] + fits[k + 1:])
        except IdentificationError:  # pragma: no cover - the laws of fewer currents do not fit
            continue
        f = fits[k]
        for name, cand in cands.items():
            loo[name][f.current] = float(np.sqrt(np.mean((law_force(cand, f) - f._rec.F) ** 2))) / f.ptp_N  # type: ignore[attr-defined]
    mean = {name: (float(np.mean(list(v.values()))) if v else None) for name, v in loo.items()}
    cands = candidates(fits)
    pick = "table" if mean["table"] is not None and mean["paper"] is not None and mean["table"] < mean["paper"] \
        else "paper"
    if laws_kind in cands:
        pick = laws_kind
    elif laws_kind == "table":
        raise IdentificationError("laws: table needs at least 2 currents")
    for f in fits:
        for name, cand in cands.items():
            F_law = law_force(cand, f)
            nr = float(np.sqrt(np.mean((F_law - f._rec.F) ** 2))) / f.ptp_N  # type: ignore[attr-defined]
            setattr(f, "nrmse_" + name, nr)
            if name == pick:
                f.F_laws, f.nrmse_laws = F_law, nr
        del f._rec, f._x, f._support  # type: ignore[attr-defined]
    params = cands[pick]
    law_choice = {"laws": pick, "asked": laws_kind,
                  "rule": "auto: the lower mean NRMSE predicting each interior current from the other currents' "
                          "fits (leave one current out)",
                  "leave_level_out_nrmse": {name: {f"{k:g}": v for k, v in d.items()} for name, d in loo.items()},
                  "leave_level_out_mean": mean}
    return IdentificationResult(params=params, fits=fits, laws=laws, method=method, period_s=T,
                                dt_s=float(np.median(dts)), settle_periods=settle_periods,
                                warmup_periods=warmup_periods, fit_periods=fit_periods,
                                sources=labels, time_s=time.perf_counter() - t_start,
                                warnings=merge_warnings(warnings, labels), laws_choice=law_choice)


def identify_files(paths: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str] | None, *,
                   method: str = DEFAULT_METHOD, progress: ProgressFn | None = None, force: bool = False,
                   **kwargs: Any) -> IdentificationResult:
    """``mrctl identify``'s work: read the run CSVs, identify, write the parameters YAML.

    ``progress`` as for :func:`identify` (called once per current); other
    keyword arguments go to :func:`identify`. Nothing is written unless
    identification succeeds; ``out`` None writes nothing (the caller writes
    :func:`~mrctl.offline.identify.result.params_yaml_bytes` with its other
    outputs); an existing ``out`` is refused unless ``force``.

    Raises:
        IdentificationError: no path given, a file that cannot be read or
            identified from, or ``out`` cannot be written (exit code 2).
        DependencyMissing: scipy is not installed (exit code 2); checked
            before any file is read.
    """
    if not paths:
        raise IdentificationError("no run CSV given")
    require_scipy()
    runs = [load_identification_run(p) for p in paths]
    if kwargs.get("stiffness") == "auto":  # fit it where every run has a displacement column
        kwargs["stiffness"] = all(("x" in r or "x_meas" in r) for r in runs)
    result = identify(runs, method=method, progress=progress, sources=[str(p) for p in paths], **kwargs)
    if out is not None:
        write_params_yaml(result, out, force=force)
    return result
