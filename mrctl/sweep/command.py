"""``mrctl sweep`` and ``mrctl report RESULTS``: their options and what they print.

Kept beside the sweep package so the command line (mrctl/cli.py) stays the
one error handler without growing a command's worth of options; errors
raised here reach that handler unchanged.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mrctl.errors import BadInput


def add_sweep_parser(sub: Any) -> None:
    """``mrctl sweep``'s options."""
    sw = sub.add_parser("sweep", help="run an experiment over a grid and Monte Carlo draws (docs/sweeps.md)")
    sw.add_argument("config", help="sweep YAML (config/sweeps/)")
    sw.add_argument("--out", required=True, help="results table: .csv, or .parquet (pyarrow); an existing one "
                                                 "of the same sweep is resumed")
    sw.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on a Dask distributed cluster "
                                                                   "(pip install 'mrctl[sweep]')")
    sw.add_argument("--workers", type=int, help="local processes (default: all cores)")
    sw.add_argument("--no-progress", action="store_true", help="no progress bar")
    sw.set_defaults(func=cmd_sweep)


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run (or resume) a sweep; 0 when every point has its row, failed points included."""
    from mrctl.sweep.runner import run_sweep
    from mrctl.sweep.spec import load_sweep
    from mrctl.sweep.table import parquet_wanted

    if args.workers is not None and args.workers < 1:
        raise BadInput(f"--workers: must be >= 1, got {args.workers}")
    parquet_wanted(Path(args.out))  # before any point runs
    sweep = load_sweep(args.config)
    where = f"Dask at {args.scheduler}" if args.scheduler else f"{args.workers or 'all'} local cores"
    print(f"{sweep.name}: {sweep.size()} points on {where} → {args.out}", flush=True)
    counts = run_sweep(sweep, args.out, scheduler=args.scheduler, workers=args.workers,
                       progress=not args.no_progress)
    print(f"{args.out}: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v or k == "ok"))
    return 0


def report_sweep(args: argparse.Namespace) -> int:
    """``mrctl report RESULTS``: the sweep's figure and its summary lines."""
    from mrctl.sweep.figure import make_sweep_report

    for line in make_sweep_report(args.runs[0], args.out, metric=args.metric, bound=args.bound, title=args.title):
        print(line)
    print(f"wrote {args.out}")
    return 0
