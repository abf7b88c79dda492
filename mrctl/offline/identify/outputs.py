"""What ``mrctl identify`` writes, and the rules it keeps while doing so.

The parameters YAML (``--out``), the dataset's JSON summary beside it and
the figure (``--report``) are checked before any fit, with the run log's
rules (:mod:`mrctl.runlog.files`): an existing file only with ``--force``,
never a symlink's target, never an input (a run, its sidecar, the dataset
description, its data or manifest), never ``--out x.json`` (the summary's
name), never two outputs with one name. After the fit they are written
together, all or nothing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from mrctl.errors import BadInput
from mrctl.offline.identify.dataset_result import json_path
from mrctl.offline.identify.errors import IdentificationError
from mrctl.runlog.files import check_output_path, write_outputs

__all__ = ["check_outputs", "write_all"]

PathLike = str | os.PathLike[str]


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
        from mrctl.offline.identify_figure import FORMATS

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
