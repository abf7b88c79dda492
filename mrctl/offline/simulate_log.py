"""``mrctl simulate --out``: the simulation's run log, kept as ``mrctl run`` keeps its own.

The CSV's and the sidecar's names are taken before simulating
(:func:`mrctl.runlog.files.create_log`: exclusive, never through a symlink)
and the sidecar is reserved at its full size (``complete: false``). The
rows are written while the simulation runs (:class:`mrctl.offline.logstream.BlockLog`):
a log the disk cannot hold is refused after the first block (exit 2); a
disk that fails during the run ends it, and the final sidecar, which fits
over the reservation, says what was written (exit 4). A simulation that
fails otherwise leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import os
import platform
from pathlib import Path
from typing import Any, Callable

from mrctl import __version__
from mrctl.build import tick_build
from mrctl.config.acceptance import bounds
from mrctl.errors import ExitCode, LogIncomplete
from mrctl.experiment import Experiment
from mrctl.offline.logstream import BlockLog, LogEstimate
from mrctl.offline.simulate import BLOCK_TICKS, SimResult, run_ticks, simulate_blocks
from mrctl.runlog import files
from mrctl.runlog.acceptance import offline_judgement
from mrctl.runlog.format import sidecar_header
from mrctl.util.jsonutil import jsonable

__all__ = ["simulate_logged", "simulate_verdict"]


def simulate_verdict(exp: Experiment, res: SimResult) -> tuple[dict[str, Any], int]:
    """The run's verdict against the experiment's ``acceptance`` bounds
    (:func:`mrctl.runlog.acceptance.offline_judgement` of the run's row
    figures) and the exit code it means: 1 for a law fault, 5 for a degraded
    run, else 0."""
    verdict = offline_judgement(res.row_figures, res.summary, bounds(exp.config), 1.0 / exp.config.rate_hz,
                                exp.excitation.settle_s)
    code = ExitCode.FAILURE if res.fault is not None else (
        ExitCode.DEGRADED if verdict["verdict"] == "degraded" else ExitCode.OK)
    return verdict, int(code)


def simulate_logged(exp: Experiment, duration_s: float, out: str, config_path: str | None, *,
                    force: bool = False, mkdir: bool = False, replay_of: str | None = None,
                    on_estimate: Callable[[LogEstimate], None] | None = None,
                    progress: Callable[[int], None] | None = None, block_ticks: int = BLOCK_TICKS
                    ) -> tuple[SimResult, dict[str, Any], int]:
    """Simulate ``exp`` for ``duration_s``, writing its run log to ``out``
    and the sidecar beside it (see the module doc). ``BadInput`` if the
    names cannot be taken or the disk cannot hold the log (``on_estimate``
    is told the estimate first), ``LogIncomplete`` (exit 4) if the disk
    fails (the sidecar records it when it can). Returns the result, its
    verdict and exit code (:func:`simulate_verdict`)."""
    side_path = files.sidecar_path(out)
    head = sidecar_header("simulate", Path(out).name, {
        "mrctl_version": __version__, "build": tick_build(), "python": platform.python_version(), "host": platform.node(),
        "config_file": str(Path(config_path).resolve()) if config_path else None,
        "replay_of": str(Path(replay_of).resolve()) if replay_of else None, "config": jsonable(exp.config),
        "parameters": exp.params.as_dict(), "backend": "simulate: offline closed loop",
        "law": exp.config.inverse.law, "I_max_A": exp.I_max, "rate_hz": exp.config.rate_hz,
        "settle_s": exp.excitation.settle_s, "load_cell_delay_ticks": 1})
    fh = files.create_log(out, force, mkdir)  # both names are ours from here
    log = BlockLog(fh, out, run_ticks(exp, duration_s), exp.dt, on_estimate)
    try:
        files.write_json(side_path, {**head, "complete": False}, reserve=files.SIDECAR_RESERVE_BYTES)
        res = simulate_blocks(exp, duration_s, log.add, block_ticks=block_ticks, progress=progress)
        log.close()
    except BaseException as exc:
        log.abandon()
        if log.error is not None and log.error is exc:  # the disk failed during the run: say what was written
            err = f"{type(exc).__name__}: {exc.strerror or exc}"
            with contextlib.suppress(OSError):  # over the reservation: this fits on a full disk
                files.write_json(side_path, {**head, "complete": False, "rows_written": log.rows_written,
                                             "exit_code": 4, "error": f"the CSV could not be written whole: {err}"})
            raise LogIncomplete(f"{out}: cannot write the run log: {exc.strerror or exc} after "
                                f"{log.rows_written} rows; the sidecar {side_path} says so") from None
        for q in (Path(out), side_path):  # refused, or failed: nothing left behind
            with contextlib.suppress(OSError):
                os.unlink(q)
        if isinstance(exc, OSError):
            raise LogIncomplete(f"{exc.filename or side_path}: cannot write the run log: "
                                f"{exc.strerror or exc}") from None
        raise
    verdict, code = simulate_verdict(exp, res)
    side = {**head, "complete": True, "rows_written": log.rows_written, "ticks": res.ticks, "dropped_rows": 0,
            "exit_code": code, "verdict": verdict["verdict"], "verdict_reasons": verdict["reasons"],
            "summary": {**res.summary, "acceptance": verdict},
            "law_fault": str(res.fault) if res.fault is not None else None, "notices": res.notices}
    try:
        files.write_json(side_path, side)
    except OSError as exc:
        raise LogIncomplete(f"{exc.filename or side_path}: cannot write the sidecar: {exc.strerror or exc}") from None
    return res, verdict, code
