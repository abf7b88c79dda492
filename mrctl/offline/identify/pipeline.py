"""Identification, end to end: from a dataset description, or from mrctl's run CSVs described as one.

:func:`identify_dataset` reads the records a description names
(:mod:`.records`), prepares spans at the fit rate (:mod:`.prep`), splits off
the held-out data, runs the protocol (constant-input sine tests,
:mod:`.sine`; broadband or switched input, :mod:`.broadband`), checks the
result (:mod:`.guards`: an absurd set is an error, never a file) and scores
it on the held-out data. :func:`identify_runs` does the same for mrctl's
own run CSVs, through the description :mod:`.runs` writes for them.
:func:`mrctl.offline.identify.result.write_result` writes either's
parameters YAML and the JSON summary beside it.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mrctl.config.dataset import load_dataset
from mrctl.config.params import INPUT_KINDS
from mrctl.model.params import LuGreParams
from mrctl.offline.identify.bbmodel import SpanData
from mrctl.offline.identify.broadband import fit_broadband, predict, warmup_samples
from mrctl.offline.identify.result import IdentificationResult, Score, Trace
from mrctl.offline.identify.errors import IdentificationError, merge_warnings, require_scipy
from mrctl.offline.identify.fit import _WELL_REL_SE, _WELL_SENS, METHODS
from mrctl.offline.identify.guards import Support, check_laws, theta_problems
from mrctl.offline.identify.laws import bench_at, fit_laws, table_set, theta_from_params
from mrctl.offline.identify.model import THETA_NAMES
from mrctl.offline.identify.prep import Span, prepare
from mrctl.offline.identify.progress import make_bar
from mrctl.offline.identify.records import read_records
from mrctl.offline.identify.runs import load_runs
from mrctl.offline.identify.sine import find_segments, fit_levels, predict_segment
from mrctl.util.schema import Node

__all__ = ["identify_dataset", "identify_runs", "parse_holdout"]

_DEFAULT_FRACTION = {"broadband": 0.3, "constant_input": 0.5}


def parse_holdout(text: str | None) -> tuple[float | None, list[str] | None]:
    """``--holdout``: a fraction (0.3), ``none`` (0), or record names (a,b) held out whole."""
    if text is None:
        return None, None
    s = text.strip()
    if s.lower() == "none":
        return 0.0, None
    try:
        f = float(s)
    except ValueError:
        names = [n.strip() for n in s.split(",") if n.strip()]
        if not names:
            raise IdentificationError(f"--holdout: {text!r}: give a fraction, none, or record names") from None
        return None, names
    if not 0.0 <= f <= 0.9:
        raise IdentificationError(f"--holdout: {f:g} out of range (a fraction in [0, 0.9], none, or record names)")
    return f, None


def _nrmse(meas: np.ndarray, pred: np.ndarray) -> float:
    ptp = float(np.ptp(meas)) if meas.size else 0.0
    return float(np.sqrt(np.mean((pred - meas) ** 2)) / ptp) if ptp > 0 else float("nan")


def _spandata(sp: Span, a: int, b: int) -> SpanData:
    z = np.zeros(b - a)
    return SpanData(sp.u[a:b], sp.v[a:b], sp.x[a:b] if sp.x is not None else z,
                    sp.a[a:b] if sp.a is not None else z, sp.dt)


def _broadband(ds: Node, spans: list[Span], frac: float, use: dict[str, bool], progress: bool,
               warnings: list[str]) -> dict[str, Any]:
    # the held-out part: the last `frac` of each fit record's used samples
    cuts: dict[int, int] = {}
    for rec in {s.record for s in spans if s.role == "fit"}:
        idx = [i for i, s in enumerate(spans) if s.record == rec]
        total = sum(spans[i].n for i in idx)
        keep = int(round((1.0 - frac) * total))
        for i in idx:
            cuts[i] = int(np.clip(keep, 0, spans[i].n))
            keep -= spans[i].n
    fit_parts = [(i, cuts[i]) for i in cuts if cuts[i] > warmup_samples(spans[i].dt) + 10]
    if not fit_parts:
        raise IdentificationError("nothing left to fit: every record is held out or too short")
    if len({round(spans[i].dt, 12) for i, _ in fit_parts}) > 1:
        raise IdentificationError("the fit records have different sample rates after resampling; set resample_hz")
    u_fit = np.concatenate([spans[i].u[:c] for i, c in fit_parts])
    u_lo, u_hi = float(u_fit.min()), float(u_fit.max())
    F_fit = np.concatenate([spans[i].F[:c] for i, c in fit_parts])
    sup = Support.of(F_fit, np.concatenate([spans[i].v[:c] for i, c in fit_parts]),
                     np.concatenate([spans[i].x[:c] for i, c in fit_parts]) if spans[0].x is not None else None)
    fit = fit_broadband([_spandata(spans[i], 0, c) for i, c in fit_parts], [spans[i].F[:c] for i, c in fit_parts],
                        u_lo, u_hi, sup, use=use, starts=ds.fit.starts, max_nfev=ds.fit.max_nfev,
                        progress=progress)
    unit = INPUT_KINDS[ds.input]
    check_laws(fit.params, u_lo, u_hi, sup, unit)
    hold, train, traces = [], [], []
    for rec in dict.fromkeys(s.record for s in spans):
        idx = [i for i, s in enumerate(spans) if s.record == rec]
        mh, ph, mt, pt, th, vh = [], [], [], [], [], []
        for i in idx:
            sp = spans[i]
            w = warmup_samples(sp.dt)
            Fp = predict(fit, _spandata(sp, 0, sp.n))
            c = cuts.get(i, 0)
            a = max(c, w)
            mh.append(sp.F[a:])
            ph.append(Fp[a:])
            th.append(sp.t[a:])
            vh.append(sp.v[a:])
            mt.append(sp.F[w:c])
            pt.append(Fp[w:c])
            if sp.role == "holdout" and (sp.u.max() > u_hi * 1.0001 + 1e-12 or sp.u.min() < u_lo - 1e-12):
                warnings.append(f"{rec}: its input ({sp.u.min():.4g}–{sp.u.max():.4g} {unit}) leaves the fitted "
                                f"range [{u_lo:.4g}, {u_hi:.4g}] {unit}: the laws are extrapolated there")
        Mh, Ph = np.concatenate(mh), np.concatenate(ph)
        if Mh.size:
            hold.append(Score(rec, None, _nrmse(Mh, Ph), int(Mh.size)))
            traces.append(Trace(rec, None, np.concatenate(th), np.concatenate(vh), Mh, Ph))
        Mt = np.concatenate(mt)
        if Mt.size:
            train.append(Score(rec, None, _nrmse(Mt, np.concatenate(pt)), int(Mt.size), part="fit"))
    details = {"optimiser": "scipy least_squares (trust-region reflective, bounded), forward-difference "
                            "Jacobian batched across columns, exact columns for the linear terms",
               "starts": fit.starts, "model_evaluations": fit.nfev, "fit_time_s": round(fit.time_s, 3),
               "at_bound": fit.at_bound, "warmup_s": warmup_samples(spans[0].dt) * spans[0].dt,
               "support": sup.__dict__}
    return {"params": fit.params, "range": (u_lo, u_hi), "holdout": hold, "train": train, "traces": traces,
            "details": details, "inertia": fit.inertia_kg}


def _constant_input(ds: Node, spans: list[Span], frac: float, use: dict[str, bool], method: str, progress: bool,
                    warnings: list[str]) -> dict[str, Any]:
    segs = find_segments(spans, fraction=frac, steady_tol=ds.fit.steady_tolerance, min_cycles=ds.fit.min_cycles,
                         warnings=warnings)
    n_levels = len({round(s.level, 9) for s in segs if s.cycles_fit > 0})
    bar = make_bar(max(n_levels, 1), "identify (levels)", enabled=progress)
    fits = fit_levels(spans, segs, use=use, method=method, bar=bar)
    bar.close()
    unit = INPUT_KINDS[ds.input]
    problems = []
    for lf in fits:
        problems += theta_problems(lf.theta, lf.support, f"level {lf.level:g} {unit}")
    if problems:
        raise IdentificationError("the fit at a level is not physical, so no parameters file was written:\n  "
                                  + "\n  ".join(problems))
    levels = np.array([lf.level for lf in fits])
    sup = max((lf.support for lf in fits), key=lambda s: s.F_amp)
    candidates, laws = _candidates(fits, use, sup)
    params = candidates["paper"]
    u_lo, u_hi = float(levels.min()), float(levels.max())
    check_laws(params, u_lo, u_hi, sup, unit)
    if len(fits) == 2:
        warnings.append("2 levels: Fc's law (6) passes through both, its shape between them is not determined")
    by_level = {round(lf.level, 9): lf for lf in fits}
    hold, train, traces = [], [], []

    for rec in dict.fromkeys(s.record for s in segs):
        for lv in sorted({s.level for s in segs if s.record == rec}):
            lf = min(fits, key=lambda f: abs(f.level - lv))
            if abs(lf.level - lv) > 1e-3 * max(abs(lv), 1.0) and round(lv, 9) not in by_level:
                warnings.append(f"{rec}: level {lv:g} {unit} is held out but no record was fitted at it; "
                                "not scored")
                continue
            th_laws = {name: (theta_from_params(cand, lf.level), *bench_at(cand, lf.level))
                       for name, cand in candidates.items()}
            for part, sel in (("holdout", lambda s: s.h1 > s.f1), ("fit", lambda s: s.cycles_fit > 0)):
                mm, pp, tt, vv = [], [], [], []
                pl: dict[str, list[np.ndarray]] = {name: [] for name in candidates}
                mine = [s for s in segs if s.record == rec and s.level == lv and sel(s)]
                for s in mine:
                    sp = spans[s.span]
                    start = s.f1 if part == "holdout" else s.f0
                    m, p = predict_segment(sp, s, lf.theta, lf.offset_N, lf.k_x, start)
                    end = s.h1 if part == "holdout" else s.f1
                    m, p = m[:end - start], p[:end - start]
                    for name, (th, off_l, kx_l) in th_laws.items():
                        pl[name].append(predict_segment(sp, s, th, off_l, kx_l, start)[1][:end - start])
                    mm.append(m)
                    pp.append(p)
                    tt.append(sp.t[start:end])
                    vv.append(sp.v[start:end])
                if not mm:
                    continue
                M, P = np.concatenate(mm), np.concatenate(pp)
                by_laws = {name: _nrmse(M, np.concatenate(q)) for name, q in pl.items()}
                sc = Score(rec, float(lf.level), _nrmse(M, P), int(M.size), by_laws["paper"], part=part,
                           nrmse_paper=by_laws["paper"], nrmse_table=by_laws.get("table"),
                           stroke_m=float(np.median([s.stroke_m for s in mine])),
                           frequency_hz=1.0 / float(np.median([s.period_s for s in mine])))
                (hold if part == "holdout" else train).append(sc)
                traces.append(Trace(rec, float(lf.level), np.concatenate(tt), np.concatenate(vv), M, P, part=part))
    loo = _leave_level_out(spans, segs, fits, use, sup, "holdout" if hold else "fit")
    params, law_choice = _choose_laws(candidates, loo, ds.fit.get("laws", "auto"), warnings)
    for sc in hold + train:
        sc.nrmse_laws = sc.nrmse_table if law_choice["laws"] == "table" else sc.nrmse_paper
    details = {"laws_choice": law_choice,
               "identifiability": _determined_summary(fits),
               "levels": [{"level": lf.level, "theta": lf.theta, "offset_N": lf.offset_N, "k_x": lf.k_x,
                           "nrmse_fit": lf.nrmse_fit, "nrmse_noise_floor": lf.noise_nrmse,
                           "std_error": lf.se, "rel_std_error": lf.rel_se, "sensitivity_1pct": lf.sensitivity,
                           "determined": lf.determined, "correlation": lf.corr, "start": lf.theta0,
                           "nfev": lf.nfev, "samples": lf.samples, "cycles": lf.cycles,
                           "segments": [{"record": s.record, "t_fit_s": [float(spans[s.span].t[s.f0]),
                                                                         float(spans[s.span].t[s.f1 - 1])],
                                         "period_s": s.period_s, "stroke_m": s.stroke_m, "cycles_fit": s.cycles_fit,
                                         "cycles_holdout": s.cycles_hold} for s in lf.segments],
                           "time_s": round(lf.time_s, 3)} for lf in fits],
               "laws": {k: {"equation": lf_.equation, "coefficients": lf_.coefficients, "rms": lf_.rms,
                            "rel_rms": lf_.rel_rms} for k, lf_ in laws.items()},
               "tau_input": "not identifiable from constant-input tests: 0"}
    return {"params": params, "range": (u_lo, u_hi), "holdout": hold, "train": train, "traces": traces,
            "details": details, "inertia": 0.0}


def _determined_summary(fits: list[Any]) -> dict[str, Any]:
    """Per parameter: 'well' determined at ≥ 75 % of the levels, 'poor' at ≤ 25 %, else 'mixed'."""
    out = {}
    for k in THETA_NAMES:
        share = float(np.mean([lf.determined.get(k) == "well" for lf in fits]))
        out[k] = "well" if share >= 0.75 else ("poor" if share <= 0.25 else "mixed")
    return {"summary": out,
            "criterion": f"'well' at a level if rel_std_error < {_WELL_REL_SE:.0%} (std_error from the Jacobian at "
                         f"the optimum, white sensor noise assumed) and sensitivity_1pct < {_WELL_SENS:.0%} (the "
                         "relative change that, the other five re-fitted, moves the force by 1 % of its "
                         "peak-to-peak)"}


def _candidates(fits: list[Any], use: dict[str, bool], sup: Support) -> tuple[dict[str, LuGreParams], dict[str, Any]]:
    """The sets the per-level fits give: ``paper`` (laws 6–11 fitted to the
    levels, the bench terms their sample-weighted means) and, from 2 levels,
    ``table`` (every level's Θ, and its F_offset and k_x when fitted)."""
    levels = np.array([lf.level for lf in fits])
    params, laws = fit_laws(levels, {k: np.array([lf.theta[k] for lf in fits]) for k in THETA_NAMES},
                            floors=sup.floors())
    w = np.array([lf.samples for lf in fits], float)
    off = float(np.average([lf.offset_N for lf in fits], weights=w))
    kx = float(np.average([lf.k_x for lf in fits], weights=w))
    params = params.with_overrides(F_offset=off, k_x=kx, tau_input=0.0)
    out = {"paper": params}
    if len(fits) >= 2:  # fits are sorted by level; the per-level bench terms too: they differ between levels
        bench = use["offset"] or use["stiffness"]
        out["table"] = table_set(params, levels, {k: np.array([lf.theta[k] for lf in fits]) for k in THETA_NAMES},
                                 np.array([lf.offset_N for lf in fits]) if bench else None,
                                 np.array([lf.k_x for lf in fits]) if bench else None)
    return out, laws


def _leave_level_out(spans: list[Span], segs: list[Any], fits: list[Any], use: dict[str, bool], sup: Support,
                     part: str) -> dict[str, dict[float, float]]:
    """How each kind of law predicts a level it was not fitted to: per interior
    level, the sets from the other levels' fits predict that level's
    ``part`` (held-out cycles, or fitted ones without a hold-out); mean NRMSE
    over its records. At a fitted level the table is that level's fit, so
    only this tells whether its interpolation beats the paper's shape."""
    out: dict[str, dict[float, float]] = {"paper": {}, "table": {}}
    for k in range(1, len(fits) - 1):
        rest = fits[:k] + fits[k + 1:]
        try:
            cands, _ = _candidates(rest, use, sup)
        except IdentificationError:  # pragma: no cover - the laws of fewer levels do not fit
            continue
        lv = fits[k].level
        per: dict[str, list[float]] = {name: [] for name in cands}
        for rec in dict.fromkeys(s.record for s in segs):
            mine = [s for s in segs if s.record == rec and abs(s.level - lv) <= 1e-3 * max(abs(lv), 1.0)
                    and (s.h1 > s.f1 if part == "holdout" else s.cycles_fit > 0)]
            if not mine:
                continue
            for name, cand in cands.items():
                th, (off, kx) = theta_from_params(cand, lv), bench_at(cand, lv)
                mm, pp = [], []
                for s in mine:
                    start, end = (s.f1, s.h1) if part == "holdout" else (s.f0, s.f1)
                    m, q = predict_segment(spans[s.span], s, th, off, kx, start)
                    mm.append(m[:end - start])
                    pp.append(q[:end - start])
                per[name].append(_nrmse(np.concatenate(mm), np.concatenate(pp)))
        for name, vals in per.items():
            if vals:
                out[name][float(lv)] = float(np.mean(vals))
    return out


def _choose_laws(candidates: dict[str, LuGreParams], loo: dict[str, dict[float, float]], want: str,
                 warnings: list[str]) -> tuple[LuGreParams, dict[str, Any]]:
    """The written set: the paper's laws (6)–(11) or the table of per-level Θ.
    ``fit.laws: auto`` takes whichever predicts the interior levels better
    when left out of the fit (:func:`_leave_level_out`, mean over those
    levels); with no interior level (2 levels) the paper's. Both scores are
    reported (``details.laws_choice``)."""
    mean = {name: (float(np.mean(list(v.values()))) if v else None) for name, v in loo.items()}
    if want in candidates:
        pick = want
    else:
        if want == "table":
            warnings.append("fit.laws: table needs at least 2 levels; the paper's laws are written")
        both = mean.get("paper") is not None and mean.get("table") is not None and "table" in candidates
        pick = "table" if both and mean["table"] < mean["paper"] else "paper"  # type: ignore[operator]
    return candidates[pick], {"laws": pick, "asked": want,
                              "rule": "auto: the lower mean NRMSE predicting each interior level from the "
                                      "other levels' fits (leave one level out)",
                              "leave_level_out_nrmse": {name: {f"{k:g}": v for k, v in d.items()}
                                                        for name, d in loo.items()},
                              "leave_level_out_mean": mean}


def identify_dataset(dataset: str | os.PathLike[str] | Node, *, holdout: str | None = None, progress: bool = False,
                     method: str = "trf", model: dict[str, bool] | None = None, source: str | None = None,
                     data_dir: str | os.PathLike[str] | None = None, allow_outside: bool = False,
                     described: dict[str, Any] | None = None, notes: Sequence[str] = ()) -> IdentificationResult:
    """Identify a parameter set from the records a dataset description names.

    Args:
        dataset: path of the description (YAML), or a validated one.
        holdout: ``--holdout``'s text: a fraction, ``none`` or record names
            held out whole (overrides the description's).
        progress: show a progress bar (tqdm, or plain lines without it).
        model: overrides of the description's ``model`` section (offset,
            stiffness, lag, inertia), e.g. ``{"lag": False}`` for a comparison.
        data_dir, allow_outside: where data files may lie (default: under the
            description's directory; :func:`mrctl.config.dataset.load_dataset`).
        described, notes: the plain description mrctl wrote for run CSVs
            (kept as ``settings["dataset"]``) and what it could not say
            (:func:`~mrctl.offline.identify.runs.load_runs`), among the warnings.
    Raises:
        ConfigError: the description is invalid (every error with its key path).
        IdentificationError: the data cannot be identified from, or the fit is not physical.
        DependencyMissing: scipy is not installed.
    """
    t0 = time.perf_counter()
    if method not in METHODS:
        raise IdentificationError(f"unknown method {method!r} (one of {', '.join(METHODS)})")
    require_scipy()
    if isinstance(dataset, Node):
        ds, src = dataset, source or "(dataset)"
    else:
        src = str(dataset)
        ds = load_dataset(dataset, data_dir=data_dir, allow_outside=allow_outside)
    frac_cli, names = parse_holdout(holdout)
    records = read_records(ds)
    if names is not None:
        unknown = [n for n in names if n not in {r.name for r in records}]
        if unknown:
            raise IdentificationError(f"--holdout: no record named {', '.join(unknown)} (records: "
                                      f"{', '.join(r.name for r in records)})")
        for r in records:
            r.role = "holdout" if r.name in names else "fit"
        if all(r.role == "holdout" for r in records):
            raise IdentificationError("--holdout: every record would be held out; at least one must be fitted")
    frac = frac_cli if frac_cli is not None else (0.0 if names is not None else ds.holdout.fraction)
    if frac is None:
        frac = _DEFAULT_FRACTION[ds.protocol]
    use = {k: bool(ds.model.get(k)) for k in ("offset", "stiffness", "lag", "inertia")}
    use.update(model or {})
    if ds.protocol == "constant_input":
        if use["inertia"]:  # the schema refuses it in a description; an override is refused the same
            raise IdentificationError("model.inertia: not identifiable from constant_input records (a steady "
                                      "sine's m·a is in phase with the stiffness k_x·x); fit broadband records")
        use["lag"] = False
    warnings = list(notes)
    spans, info = prepare(records, band_hz=ds.motion_band_hz, resample_hz=ds.resample_hz,
                          need_accel=use["inertia"], warnings=warnings,
                          constant_input=ds.protocol == "constant_input")
    if use["stiffness"] and any(s.x is None for s in spans):  # pragma: no cover - the schema checks it
        use["stiffness"] = False
    if ds.protocol == "broadband":
        out = _broadband(ds, spans, frac, use, progress, warnings)
    else:
        out = _constant_input(ds, spans, frac, use, method, progress, warnings)
    if not out["holdout"]:
        warnings.append("no held-out data (holdout fraction 0 and no record with role: holdout): every score "
                        "is on data the fit has seen")
    warnings = merge_warnings(warnings, [r.name for r in records])
    settings = {"holdout_fraction": frac, "holdout_records": sorted({r.name for r in records if r.role == "holdout"}),
                "model": use, "records": info["records"], "method": method}
    if described is not None:
        settings["dataset"] = described
    return IdentificationResult(ds.name or Path(src).stem, src, ds.protocol, ds.input, INPUT_KINDS[ds.input],
                                out["params"], out["range"], out["holdout"], out["train"], settings, out["details"],
                                out["traces"], warnings, time.perf_counter() - t0, out["inertia"])


def identify_runs(paths: Sequence[str | os.PathLike[str]], *, laws: str | None = None, name: str | None = None,
                  **kwargs: Any) -> IdentificationResult:
    """Identify from mrctl's own run CSVs: the description
    :func:`~mrctl.offline.identify.runs.describe_runs` writes, through
    :func:`identify_dataset` (``kwargs``: holdout, progress, method, model).
    ``laws``: "auto", "paper" or "table" (``fit.laws``). The description is
    in the result's ``settings["dataset"]``."""
    notes: list[str] = []
    ds, doc = load_runs(paths, name=name, overrides={"fit": {"laws": laws}} if laws else None, notes=notes)
    return identify_dataset(ds, source=", ".join(str(p) for p in paths), described=doc, notes=notes, **kwargs)
