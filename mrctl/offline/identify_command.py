"""``mrctl identify``: run CSVs or a dataset description to a parameters YAML.

Checks the command line, then every output before the fit, fits, and writes
the parameters, the dataset's JSON summary and the figure together after
it, all or nothing. The outputs keep the run log's rules
(:mod:`mrctl.runlog.files`): an existing file only with ``--force``, never a
symlink's target, never an input (a run, its sidecar, the dataset
description, its data or manifest), never ``--out x.json`` (the summary's
name), never two outputs with one name. Beside :mod:`mrctl.offline.identify` (which
never imports the figures or the CLI), like :mod:`mrctl.offline.identify_figure`.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Sequence

from mrctl.errors import BadInput
from mrctl.offline.identify import IdentificationError, json_path
from mrctl.offline.identify_figure import FORMATS
from mrctl.runlog.files import check_output_path, write_outputs

__all__ = ["identify_command", "check_outputs", "write_all"]


def identify_command(args: argparse.Namespace) -> int:
    """Run CSVs (mrctl's own logs of constant-current steps) or a dataset
    description (a lab's measured records, ``--dataset`` or a .yaml argument).
    Prints progress, the summary table, what was written. Errors are raised
    (IdentificationError/ConfigError exit 2, DependencyMissing without scipy
    exit 1, ReportError exit 2) for :func:`main`'s handler. Outputs: checked
    before the fit, written after it (:mod:`mrctl.offline.identify.outputs`)."""
    runs = list(args.runs)
    dataset = args.dataset  # a single .yaml among the runs is already taken as it (mrctl.cli)
    if dataset is not None:
        if runs:
            raise BadInput("identify: give run CSVs or --dataset, not both")
        if args.period is not None or args.method != "trf":
            raise BadInput("identify: --period and --method are for run CSVs; a dataset's segments have their own "
                           "period")
        return _identify_dataset(args, dataset)
    if args.holdout is not None:
        raise BadInput("identify: --holdout is for --dataset (run CSVs are scored on their fit windows)")
    if args.data_dir is not None:
        raise BadInput("identify: --data-dir is for --dataset (where its records are)")
    if args.allow_outside_paths:
        raise BadInput("identify: --allow-outside-paths is for --dataset (run CSVs are named on the command line)")
    from mrctl.offline.identify import format_summary, identify_files
    from mrctl.offline.identify.result import params_yaml_bytes
    from mrctl.runlog.files import sidecar_path

    def progress(i: int, n: int, I: float, elapsed: float, nrmse: float) -> None:
        if not (args.quiet or args.no_progress):
            print(f"[{i:2d}/{n}] I = {I:.3f} A  NRMSE {100 * nrmse:5.2f} %  ({elapsed:.1f} s)", flush=True)

    if args.period is not None and not args.period > 0:
        raise BadInput(f"identify: --period must be > 0 s, got {args.period:g}")
    check_outputs(args.out, args.report, [q for r in runs for q in (r, sidecar_path(r))], force=args.force)
    result = identify_files(runs, None, method=args.method, progress=progress, period_s=args.period,
                            offset=not args.no_offset, stiffness="auto" if not args.no_offset else False)
    items = [(args.out, params_yaml_bytes(result))]
    if args.report:
        from mrctl.offline.report import make_identification_report

        items.append((args.report, make_identification_report(result, args.report, write=False)))
    print(format_summary(result))
    write_all(items, args.force)
    _say(args, f"wrote {args.out} ({len(result.fits)} currents, {result.time_s:.1f} s, optimiser {result.method})")
    if args.report:
        _say(args, f"wrote {args.report}")
    return 0


def _identify_dataset(args: argparse.Namespace, dataset: str) -> int:
    from mrctl.config.dataset import load_dataset
    from mrctl.offline.identify import format_dataset_summary, identify_dataset
    from mrctl.offline.identify.dataset_result import dataset_output_bytes

    ds = load_dataset(dataset, data_dir=args.data_dir, allow_outside=args.allow_outside_paths)
    inputs = [dataset, *(f.path for f in ds.files or [])] + ([ds.manifest.path] if ds.manifest is not None else [])
    check_outputs(args.out, args.report, inputs, force=args.force, summary=True)
    model = {"offset": False, "stiffness": False} if args.no_offset else None
    res = identify_dataset(ds, holdout=args.holdout, model=model, source=str(dataset),
                           progress=not (args.no_progress or args.quiet) and sys.stderr.isatty())
    items = dataset_output_bytes(res, args.out)
    if args.report:
        from mrctl.offline.identify_figure import make_dataset_report

        items.append((Path(args.report), make_dataset_report(res, args.report, write=False)))
    print(format_dataset_summary(res))
    write_all(items, args.force)
    _say(args, f"wrote {args.out} and {items[1][0]} ({res.time_s:.1f} s)")
    if args.report:
        _say(args, f"wrote {args.report}")
    return 0


PathLike = str | os.PathLike[str]


def _say(args: argparse.Namespace, msg: str) -> None:
    """What was written: not with ``-q``."""
    if not getattr(args, "quiet", False):
        print(msg, flush=True)


def check_outputs(out: str, report: str | None, inputs: Sequence[PathLike], *, force: bool = False,
                  summary: bool = False) -> None:
    """``BadInput`` for any output that would destroy something (see the
    module doc); ``summary``: the JSON beside ``out`` is written too (a
    dataset). Touches nothing."""
    if not out:
        raise BadInput("--out '': an empty name; give the parameters file to write (.yaml)")
    if Path(out).suffix.lower() == ".json":
        raise BadInput(f"--out {out}: the parameters file is YAML; a .json name is the summary's, written beside "
                       "it (name it .yaml)")
    outs = [(Path(out), "the parameters (--out)")]
    if summary:
        outs.append((json_path(out), f"the summary of {Path(out).name}"))
    if report is not None:
        if Path(report).suffix.lower().lstrip(".") not in FORMATS:
            raise BadInput(f"--report {report!r}: cannot write a figure of that name; name it .png, .pdf or .svg")
        outs.append((Path(report), "the figure (--report)"))
    seen: dict[Path, str] = {}
    for p, what in outs:
        key = p.resolve()
        if key in seen:
            raise BadInput(f"{p}: {what} and {seen[key]} would be the same file; give them different names")
        seen[key] = what
        check_output_path(p, force, inputs=inputs, what=what)


def write_all(items: Sequence[tuple[PathLike, bytes]], force: bool = False) -> None:
    """Write every ``(path, bytes)``, all or nothing (parent directories
    created); IdentificationError (exit 2) naming the file that failed."""
    try:
        write_outputs(items, force, mkdir=True)
    except OSError as exc:
        raise IdentificationError(f"{exc.filename or items[0][0]}: cannot write: {exc.strerror or exc}") from None
