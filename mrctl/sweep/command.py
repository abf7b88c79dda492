"""``mrctl sweep`` and ``mrctl report RESULTS``: what they do and print.

Their options are parsed in mrctl/cli.py with every other command's (one
vocabulary, docs/cli.md); errors raised here reach its one handler
unchanged.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mrctl.errors import BadInput


def run_sweep_command(args: argparse.Namespace) -> int:
    """``mrctl sweep`` (its options are mrctl.cli's): run or resume a sweep;
    0 when every point has its row, failed points included."""
    from mrctl.sweep.runner import check_scheduler_address, run_sweep
    from mrctl.sweep.spec import load_sweep
    from mrctl.sweep.table import check_table_path, parquet_wanted
    from mrctl.util.files import refuse_inputs

    if args.workers is not None and args.workers < 1:
        raise BadInput(f"--workers: must be >= 1, got {args.workers}")
    if args.scheduler is not None:
        check_scheduler_address(args.scheduler)
    check_table_path(args.out)  # a directory, /dev/null or a FIFO: refused before anything is read
    parquet_wanted(Path(args.out))  # before any point runs
    sweep = load_sweep(args.config, allow_outside=args.allow_outside_paths)
    refuse_inputs([args.out], [*sweep.bases.values(), *sweep.fence.admitted])  # the bases and the sets they name
    where = f"Dask at {args.scheduler}" if args.scheduler else f"{args.workers or 'all'} local cores"
    if not args.quiet:
        print(f"{sweep.name}: {sweep.size()} points on {where} → {args.out}", flush=True)
    counts = run_sweep(sweep, args.out, scheduler=args.scheduler, workers=args.workers,
                       progress=not (args.no_progress or args.quiet))
    print(f"{args.out}: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v or k == "ok"))
    return 0


def report_sweep(args: argparse.Namespace) -> int:
    """``mrctl report RESULTS``: the sweep's figure and its summary lines."""
    from mrctl.sweep.figure import make_sweep_report

    for line in make_sweep_report(args.runs[0], args.out, metric=args.metric, bound=args.bound, title=args.title):
        print(line)
    print(f"wrote {args.out}")
    return 0
