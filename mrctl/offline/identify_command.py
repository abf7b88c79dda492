"""``mrctl identify``: run CSVs or a dataset description to a parameters YAML.

Checks the command line, then every output before the fit, fits, and writes
the parameters, the dataset's JSON summary and the figures together after
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
    """Run CSVs (mrctl's own logs of constant-current steps, described by
    :func:`mrctl.offline.identify.runs.describe_runs`) or a dataset
    description (a lab's measured records, ``--dataset`` or a .yaml
    argument), through :func:`mrctl.offline.identify.identify_dataset`
    either way. Prints progress, the summary table,
    what was written. Errors are raised (IdentificationError/ConfigError
    exit 2, DependencyMissing exit 2, FigureError exit 2) for :func:`main`'s
    handler. Outputs: checked before the fit, written after it, all or
    nothing."""
    from mrctl.config.dataset import load_dataset
    from mrctl.offline.identify import format_summary, identify_dataset, load_runs
    from mrctl.offline.identify.result import result_bytes
    from mrctl.runlog.files import sidecar_path

    runs = list(args.runs)
    dataset = args.dataset  # a single .yaml among the runs is already taken as it (mrctl.cli)
    overrides = {"fit": {"laws": args.fit_laws}} if args.fit_laws else {}
    doc: dict | None = None  # the description mrctl writes for run CSVs (what --describe would write)
    notes: list[str] = []  # what it could not say
    if dataset is not None:
        if runs:
            raise BadInput("identify: give run CSVs or --dataset, not both")
        if args.describe is not None:
            raise BadInput("identify: --describe writes the description of run CSVs; a dataset has one")
        ds = load_dataset(dataset, data_dir=args.data_dir, allow_outside=args.allow_outside_paths)
        if overrides:
            ds = ds.replace(fit=ds.fit.replace(**overrides["fit"]))
        inputs = [dataset, *(f.path for f in ds.files or [])]
        if ds.manifest is not None:  # the manifest and every file it lists
            from mrctl.offline.identify.records import manifest_paths

            inputs += [ds.manifest.path, *manifest_paths(ds.manifest)]
        source = str(dataset)
    else:
        if args.data_dir is not None:
            raise BadInput("identify: --data-dir is for --dataset (where its records are)")
        if args.allow_outside_paths:
            raise BadInput("identify: --allow-outside-paths is for --dataset (run CSVs are named on the command "
                           "line)")
        ds, doc = load_runs(runs, overrides=overrides, notes=notes)
        if args.describe is not None:
            for note in notes:
                print(f"warning: {note}", file=sys.stderr)
            return _describe(args, doc)
        inputs = [q for r in runs for q in (r, sidecar_path(r))]
        source = ", ".join(runs)
    detail = getattr(args, "report_detail", None)
    check_outputs(args.out, args.report, inputs, force=args.force, detail=detail)
    model = {"offset": False, "stiffness": False} if args.no_offset else None
    res = identify_dataset(ds, holdout=args.holdout, model=model, source=source, method=args.method,
                           progress=not (args.no_progress or args.quiet), described=doc, notes=notes)
    items = result_bytes(res, args.out)
    figures = [(f, d) for f, d in ((args.report, False), (detail, True)) if f]
    for fig, as_detail in figures:
        from mrctl.offline.identify_figure import make_identification_figure

        items.append((Path(fig), make_identification_figure(res, fig, write=False, detail=as_detail)))
    print(format_summary(res))
    write_all(items, args.force)
    _say(args, f"wrote {args.out} and {items[1][0]} ({res.time_s:.1f} s)")
    for fig, _ in figures:
        _say(args, f"wrote {fig}")
    return 0


def _describe(args: argparse.Namespace, doc: dict) -> int:
    """``--describe D.yaml``: the description of the run CSVs, paths relative to it, for ``--dataset``."""
    import yaml

    out = Path(args.describe)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"--describe {args.describe}: name the description .yaml")
    check_output_path(out, args.force, inputs=[f["path"] for f in doc["files"]],
                      what="the description (--describe)")
    base = out.resolve().parent
    files = []
    for f in doc["files"]:
        rel = os.path.relpath(f["path"], base)
        files.append({**f, "path": rel if not rel.startswith("..") else f["path"]})
    text = ("# dataset description of mrctl run CSVs, written by mrctl identify --describe;\n"
            f"# mrctl identify --dataset {out.name} fits the same (paths outside this directory need "
            "--allow-outside-paths)\n" + yaml.safe_dump({**doc, "files": files}, sort_keys=False, allow_unicode=True,
                                                          width=120))
    write_all([(out, text.encode("utf-8"))], args.force)
    _say(args, f"wrote {out}: mrctl identify --dataset {out} fits the same records")
    return 0


PathLike = str | os.PathLike[str]


def _say(args: argparse.Namespace, msg: str) -> None:
    """What was written: not with ``-q``."""
    if not getattr(args, "quiet", False):
        print(msg, flush=True)


def check_outputs(out: str, report: str | None, inputs: Sequence[PathLike], *, force: bool = False,
                  detail: str | None = None) -> None:
    """``BadInput`` for any output that would destroy something (see the
    module doc): the parameters, the JSON summary beside them, the figure.
    Touches nothing."""
    if not out:
        raise BadInput("--out '': an empty name; give the parameters file to write (.yaml)")
    if Path(out).suffix.lower() == ".json":
        raise BadInput(f"--out {out}: the parameters file is YAML; a .json name is the summary's, written beside "
                       "it (name it .yaml)")
    outs = [(Path(out), "the parameters (--out)"), (json_path(out), f"the summary of {Path(out).name}")]
    for opt, fig, what in (("--report", report, "the figure"), ("--report-detail", detail, "the detail figure")):
        if fig is not None:
            if Path(fig).suffix.lower().lstrip(".") not in FORMATS:
                raise BadInput(f"{opt} {fig!r}: cannot write a figure of that name; name it .png, .pdf or .svg")
            outs.append((Path(fig), f"{what} ({opt})"))
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
