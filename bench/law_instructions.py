#!/usr/bin/env python3
"""Instructions per call of a config's inverse law, or per controller tick, counted by callgrind.

Why instructions: on a shared VM a timing moves by 2x from one minute to the
next, an instruction count does not depend on what else the machine does
(it still moves by a few per cent from one run to the next: allocation and
start-up differ). The law is called on the samples ``mrctl simulate``
recorded for the same file, ``--reps`` passes over it; the count of a run
with no calls is subtracted, so start-up does not count. The figure includes
the loop's own work per call (1 600 instructions with the ``constant`` law).

``--tick NAME`` counts a whole controller tick instead: NAME is a factory of
``bench/controller_tick.py`` (e.g. ``make_tick_robust_replay``), called
``--reps`` × 2000 times back to back, GC frozen and off, the law's time
budget lifted (under callgrind the law runs ~50x slower and would fault as
slow). The recorder's rows are not formatted (in the loop that happens in
idle time, outside the tick): the process exits without formatting them.

Run it once with ``MRCTL_PURE_PYTHON=1`` for the interpreted build of the
same tick (docs/performance.md gives both).

    python bench/law_instructions.py [--config config/experiments/fig5_robust.yaml] [--set KEY=VALUE]
    python bench/law_instructions.py --config config/experiments/fig5.yaml      # the smooth law
    python bench/law_instructions.py --tick make_tick_robust_replay             # closed + observer, whole tick

Needs valgrind (Debian package ``valgrind``).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _calls(config: str, reps: int, sets: list[str]) -> None:
    """The measured body: simulate once, then call a fresh law on the record ``reps`` times."""
    sys.path.insert(0, str(ROOT))
    from mrctl.config import load_yaml, validate_experiment
    from mrctl.experiment import build
    from mrctl.laws.base import Measurement
    from mrctl.offline.simulate import log_columns, run_duration, simulate

    sys.path.insert(0, str(ROOT / "bench"))
    from robust_scenarios import parse_sets

    path = Path(config)
    data = load_yaml(path)
    if sets and not isinstance(data.get("inverse"), dict):
        raise SystemExit(f"{path}: no inverse section to --set keys in")
    data.get("inverse", {}).update(parse_sets(sets))
    exp = build(validate_experiment(data, path.parent))
    c = log_columns(simulate(exp, run_duration(exp)))
    rows = list(zip(*(c[k].tolist() for k in ("k", "t", "x", "v", "F", "I_applied", "F_des"))))
    law, m = exp.law, Measurement()
    for _ in range(reps):
        law.reset(0.0)
        I = 0.0
        for k, t, x, v, F, Ia, Fd in rows:
            m.k, m.t, m.x, m.v, m.F, m.I_applied, m.I_cmd = int(k), t, x, v, F, Ia, I
            I = law.current(m, Fd)
    print(len(rows))


def _ticks(name: str, reps: int) -> None:
    """The measured body of ``--tick``: build the tick, then run it ``reps`` × 2000 times."""
    import gc

    sys.path.insert(0, str(ROOT / "bench"))
    import controller_tick

    tick, _background = getattr(controller_tick, name)(1e-3)
    tick.__self__.law_budget_ns = 1 << 62  # type: ignore[attr-defined]
    gc.freeze()
    gc.disable()
    n = reps * 2000
    for k in range(n):
        tick(k, 0)
    print(n, flush=True)
    # the rows wait in the recorder: formatting them (the loop's idle time, or the
    # writer thread at close) is not the tick's work, and exiting here skips it
    os._exit(0)


def _count(config: str, reps: int, sets: list[str], tick: str | None = None) -> tuple[int, int]:
    what = ["--tick", tick] if tick else ["--config", config, *sum((["--set", s] for s in sets), [])]
    with tempfile.TemporaryDirectory() as d:
        out = subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={d}/cg.out", sys.executable,
                              __file__, "--inner", str(reps), *what],
                             capture_output=True, text=True, env={**os.environ, "PYTHONHASHSEED": "0"})
    m = re.search(r"Collected : (\d+)", out.stderr)
    if out.returncode or m is None:
        raise SystemExit(f"callgrind failed: {out.stderr[-500:]}")
    return int(m.group(1)), int(out.stdout.split()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "experiments" / "fig5_robust.yaml"))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an inverse-law key")
    ap.add_argument("--reps", type=int, default=2, help="passes over the record")
    ap.add_argument("--tick", help="count a whole tick of this bench/controller_tick.py factory instead")
    ap.add_argument("--inner", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args()
    from robust_scenarios import parse_sets  # this script's directory is on the path

    try:
        parse_sets(a.set)  # a malformed one fails here, not under valgrind
    except ValueError as exc:
        ap.error(str(exc))
    if a.tick is not None:
        import controller_tick  # fail early on a wrong name, not under valgrind

        if not callable(getattr(controller_tick, a.tick, None)):
            ap.error(f"--tick {a.tick!r}: no such factory in bench/controller_tick.py")
    if a.inner is not None:
        if a.tick is not None:
            _ticks(a.tick, a.inner)
        else:
            _calls(a.config, a.inner, a.set)
        return 0
    if shutil.which("valgrind") is None:
        raise SystemExit("valgrind not found (apt-get install -y valgrind)")
    base, _ = _count(a.config, 0, a.set, a.tick)
    total, n = _count(a.config, a.reps, a.set, a.tick)
    if a.tick is not None:
        print(f"{a.tick}: {(total - base) / n:,.0f} instructions per controller tick ({n} ticks, callgrind)")
    else:
        print(f"{a.config}: {(total - base) / (a.reps * n):,.0f} instructions per call of the inverse law "
              f"({a.reps} x {n} calls, callgrind)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
