"""One point of a sweep, run where it lands (this process, a local worker, a Dask worker).

It takes plain data (:meth:`mrctl.sweep.spec.Point.task`) and gives back a
row: the metrics, a status and the error, never an exception, so one bad
combination or one law fault is a row and the sweep goes on.

- ``ok``: ran to the end;
- ``fault``: the law raised or returned NaN (the run ended there at 0 A,
  as ``mrctl simulate`` does); the metrics are of the run up to it;
- ``invalid``: the point's config does not validate (the error names the key);
- ``error``: anything else (the exception's type and message).
"""

from __future__ import annotations

import inspect
import math
import time
from pathlib import Path
from typing import Any

from mrctl import __version__

STATUSES = ("ok", "fault", "invalid", "error")


def build_kind() -> str:
    """``compiled`` when the offline tick loop is not Python code (a compiled build), else ``pure``."""
    from mrctl.offline import simulate

    loop = getattr(simulate, "_loop", None)
    return "pure" if inspect.isfunction(loop) else "compiled"


def prewarm(task: dict[str, Any]) -> None:
    """Import what a point needs and fill the law registry's caches (entry points) in this process,
    so forked workers start with them instead of each paying for them on its first point."""
    from mrctl.config import validate_experiment
    from mrctl.experiment import build
    from mrctl.offline import simulate  # noqa: F401
    from mrctl.sweep import metrics  # noqa: F401

    try:
        build(validate_experiment(task["config"], Path(task["base_dir"]), fence=task_fence(task)))
    except Exception:  # noqa: BLE001 - the point itself will report it
        pass


def task_fence(task: dict[str, Any]) -> Any:
    """Where the files a point's config names must lie (its sweep's fence, as plain data)."""
    from mrctl.util.files import Fence

    return Fence.from_text(task.get("fence"))


def run_points(tasks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows of several points, one after another (one task of the pool or
    the cluster: a point is too short to pay a round trip of its own)."""
    return [run_point(t) for t in tasks]


def run_point(task: dict[str, Any]) -> dict[str, Any]:
    """Simulate one point and return its row (metrics, status, error, wall time)."""
    from mrctl.config import ConfigError, validate_experiment
    from mrctl.experiment import build
    from mrctl.offline.simulate import run_duration, simulate
    from mrctl.sweep.metrics import compute

    names = list(task["metrics"])
    row: dict[str, Any] = {"point": task["index"], "config_hash": task["hash"], **{m: math.nan for m in names},
                           "status": "ok", "error": "", "mrctl_version": __version__, "build": build_kind()}
    t0 = time.perf_counter()
    base_dir = Path(task["base_dir"])
    try:
        exp = build(validate_experiment(task["config"], base_dir, fence=task_fence(task)))
        duration = run_duration(exp)
        res = simulate(exp, duration)
        row.update(compute(names, res, exp, task["config"], base_dir, duration))
        if res.fault is not None:
            row["status"], row["error"] = "fault", str(res.fault)
    except ConfigError as exc:
        row["status"], row["error"] = "invalid", "; ".join(exc.errors)
    except Exception as exc:  # noqa: BLE001 - a point's failure is its row, not the sweep's end
        row["status"], row["error"] = "error", f"{type(exc).__name__}: {exc}"
    row["wall_s"] = time.perf_counter() - t0
    return row
