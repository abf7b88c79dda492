"""``mrctl simulate --replay RUN.csv``: a logged experiment's motion, again, with another law.

A run log is a valid excitation file (``excitation: {type: file}`` reads its
t, x, v and ignores the rest), so a replay is the experiment of the log's
sidecar (or a CONFIG given beside it) with its excitation replaced by the
log itself, its duration the log's, its settling window the logged run's
(where the sidecar says its figures start: both are judged over the same
window), and
optionally another inverse law: the same motion, a different controller,
offline.

Why the sidecar's config: it is the experiment as it was validated when the
log was written (defaults filled in, parameters inline), so the replay
needs no file but the log and its ``.json``. A sidecar is a file like any
other: the files its config names must lie under the log's folder (its
``config/`` tree) unless ``--allow-outside-paths``, whatever folder it
claims its config came from, and its errors never quote it. The sidecar
keeps the config in a form that validates back (:mod:`mrctl.config.saved`);
an older sidecar's live forms are mended and said.
"""

from __future__ import annotations

import copy
import math
import sys
from pathlib import Path
from typing import Any

from mrctl.config.experiment import validate_experiment
from mrctl.config.saved import readable_config
from mrctl.errors import BadInput
from mrctl.runlog.files import sidecar_path
from mrctl.runlog.read import try_sidecar
from mrctl.util.files import Fence
from mrctl.util.schema import Node, load_yaml, quoting

__all__ = ["replay_config", "with_law", "load_with_law"]


def with_law(data: dict[str, Any], law: str) -> dict[str, Any]:
    """``data`` (a raw experiment mapping) with ``inverse.law`` set to
    ``law``; the previous law's own keys go with it (they are another
    law's), its section's shared ones stay."""
    out = copy.deepcopy(data)
    inv = out.get("inverse")
    if not isinstance(inv, dict) or inv.get("law") != law:
        out["inverse"] = {"law": law}
    return out


def replay_config(log: str | Path, config: str | Path | None = None, law: str | None = None, *,
                  allow_outside: bool = False) -> Node:
    """The validated experiment that replays ``log``: the sidecar's config
    (or ``config``'s), its excitation the log, no duration of its own (the
    log's length), ``law`` if given. ``BadInput`` when the log is missing or
    has no sidecar config and no ``config`` is given; ``ConfigError`` (with
    key paths) when the result is not a valid experiment. The log itself may
    lie anywhere (it was named on the command line); the files the config
    names stay under CONFIG's folder, or the log's for the sidecar's config,
    unless ``allow_outside``."""
    p = Path(log)
    if not p.is_file():
        raise BadInput(f"--replay {p}: no such run log")
    quiet = False
    settle: Any = None
    if config is not None:
        cp = Path(config)
        data, base = load_yaml(cp), cp.parent
        fence = Fence.around(base, allow_outside, allowed=(p,))
        source = f"{cp} replaying {p.name}"
    else:
        side = try_sidecar(p)
        data = side.get("config")
        if not isinstance(data, dict):
            raise BadInput(f"--replay {p}: no experiment in {sidecar_path(p)} (missing or not mrctl's sidecar); "
                           f"give the experiment YAML as well: mrctl simulate CONFIG --replay {p}")
        cf = side.get("config_file")
        base = Path(cf).parent if isinstance(cf, str) and Path(cf).parent.is_dir() else p.parent
        fence = Fence.around(p.parent, allow_outside, allowed=(p,), what="the run log")  # not the folder it claims
        source = f"{sidecar_path(p)} (the config of {p.name})"
        quiet = True
        data, notes = readable_config(data)
        for note in notes:
            print(f"mrctl: --replay {p.name}: {note}", file=sys.stderr)
        settle = _window_start(side)
    if not isinstance(data, dict):
        raise BadInput(f"{config}: not an experiment mapping")
    data = copy.deepcopy(data)
    if law is not None:
        data = with_law(data, law)
    data["excitation"] = {"type": "file", "path": str(p.resolve())}
    if isinstance(settle, (int, float)) and not isinstance(settle, bool) and math.isfinite(settle) and settle >= 0:
        data["excitation"]["settle_s"] = float(settle)  # judged over the logged run's window
    data["duration_s"] = None
    data["name"] = f"{data.get('name') or p.stem} (replay of {p.name})"
    with quoting(values=not quiet):
        return validate_experiment(data, base, source, fence=fence)


def _window_start(side: dict[str, Any]) -> Any:
    """Where the logged run's figures start, on the replay's clock (which starts
    at 0 where the log may start a tick or a skipped deadline later): the
    sidecar's window if it recorded one (``mrctl run``: ``summary.tracking``,
    ``mrctl simulate``: ``summary``), else its ``settle_s``."""
    summary = side.get("summary") if isinstance(side.get("summary"), dict) else {}
    for where in (summary.get("tracking"), summary):
        start = where.get("window_start_s") if isinstance(where, dict) else None
        if isinstance(start, (int, float)) and not isinstance(start, bool) and math.isfinite(start) and start > 0:
            return float(start)
    return side.get("settle_s")


def load_with_law(config: str | Path, law: str, *, allow_outside: bool = False) -> Node:
    """``mrctl simulate CONFIG --law NAME``: the experiment with another inverse law."""
    cp = Path(config)
    data = load_yaml(cp)
    if not isinstance(data, dict):
        raise BadInput(f"{cp}: not an experiment mapping")
    return validate_experiment(with_law(data, law), cp.parent, str(cp), allow_outside=allow_outside)
