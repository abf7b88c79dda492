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
from mrctl.offline.identify.bbmodel import SpanData
from mrctl.offline.identify.broadband import fit_broadband, predict, warmup_samples
from mrctl.offline.identify.result import IdentificationResult, Score, Trace, nrmse as _nrmse
from mrctl.offline.identify.errors import IdentificationError, merge_warnings, require_scipy
from mrctl.offline.identify.fit import METHODS
from mrctl.offline.identify.guards import Support, check_laws
from mrctl.offline.identify.levels import constant_input
from mrctl.offline.identify.prep import Span, prepare
from mrctl.util.progress import make_bar
from mrctl.offline.identify.records import read_records
from mrctl.offline.identify.runs import load_runs
from mrctl.util.schema import Node

__all__ = ["identify_dataset", "identify_runs", "parse_holdout"]

_DEFAULT_FRACTION = {"broadband": 0.3, "constant_input": 0.5}
#: the description's model terms (``model:``), each a flag
MODEL_TERMS = ("offset", "stiffness", "lag", "inertia", "lag_fall", "sigma1_v", "hysteresis")


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
    use = {k: bool(ds.model.get(k)) for k in MODEL_TERMS}
    use.update(model or {})
    if ds.protocol == "constant_input":
        if use["inertia"]:  # the schema refuses it in a description; an override is refused the same
            raise IdentificationError("model.inertia: not identifiable from constant_input records (a steady "
                                      "sine's m·a is in phase with the stiffness k_x·x); fit broadband records")
        for k in ("lag_fall", "sigma1_v"):
            if use[k]:
                raise IdentificationError(f"model.{k}: broadband only (fitted from broadband or switched-input "
                                          "records)")
        use["lag"] = False
    elif use["lag_fall"] and not use["lag"]:
        use["lag_fall"] = False  # no lag, no falling lag (the schema refuses the pair in a description)
    warnings = list(notes)
    spans, info = prepare(records, band_hz=ds.motion_band_hz, resample_hz=ds.resample_hz,
                          need_accel=use["inertia"], warnings=warnings,
                          constant_input=ds.protocol == "constant_input")
    if use["stiffness"] and any(s.x is None for s in spans):  # pragma: no cover - the schema checks it
        use["stiffness"] = False
    if ds.protocol == "broadband":
        out = _broadband(ds, spans, frac, use, progress, warnings)
    else:
        out = constant_input(ds, spans, frac, use, method, progress, warnings)
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
