"""``mrctl`` command line: run, status, tap, exporter, simulate, sweep, report, identify, check, examples.

The one place that turns errors into exit codes: every user-facing error is
a :class:`mrctl.errors.MrctlError` carrying its code (README: 0 success,
1 internal error, 2 bad input, 3 link failure, 4 run log incomplete), and
:func:`main` prints it as one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path
from typing import Sequence

from mrctl import __version__
from mrctl.errors import BadInput, ExitCode, LogIncomplete, MrctlError
from mrctl.util.jsonutil import jsonable

EXIT_OK = ExitCode.OK
EXIT_FAILURE = ExitCode.FAILURE
EXIT_BAD_INPUT = ExitCode.BAD_INPUT


def _err(msg: str) -> None:
    from mrctl.util.journal import ERR, Journal

    Journal(sys.stderr).log(ERR, msg)  # <3> first when stderr is the journal (a unit's ExecStartPre=)


def _load(config_path: str):
    from mrctl.config import load_experiment
    from mrctl.experiment import build

    return build(load_experiment(config_path))


def cmd_simulate(args: argparse.Namespace) -> int:
    from mrctl.offline.simulate import run_duration, simulate, write_csv
    from mrctl.runlog import files
    from mrctl.runlog.format import sidecar_header
    from mrctl.runlog.metrics import format_summary
    from mrctl.util.options import check_duration

    override = check_duration(args.duration)
    if args.out:
        files.check_log_path(args.out, args.force)  # before a long simulation, not after
    exp = _load(args.config)
    duration = run_duration(exp, override)
    res = simulate(exp, duration)
    s = res.summary
    if args.out:
        side = {**sidecar_header("simulate", Path(args.out).name, {
                    "mrctl_version": __version__, "python": platform.python_version(), "host": platform.node(),
                    "config_file": str(Path(args.config).resolve()), "config": jsonable(exp.config),
                    "parameters": exp.params.as_dict(), "backend": "simulate: offline closed loop",
                    "law": exp.config.inverse.law, "I_max_A": exp.I_max, "rate_hz": exp.config.rate_hz,
                    "settle_s": exp.excitation.settle_s, "load_cell_delay_ticks": 1}),
                "complete": True, "rows_written": res.ticks, "ticks": res.ticks, "dropped_rows": 0,
                "exit_code": 1 if res.fault is not None else 0, "summary": s,
                "law_fault": str(res.fault) if res.fault is not None else None,
                "notices": res.notices}
        try:
            write_csv(res, args.out, force=args.force)
            files.write_json(files.sidecar_path(args.out), side)
        except OSError as exc:
            raise LogIncomplete(f"{exc.filename or args.out}: cannot write the run log: "
                                f"{exc.strerror or exc}") from None
    law = exp.config.inverse.law
    print(f"{exp.name}: law {law}, {int(s['ticks'])} ticks ({s['simulated_s']:.3f} s simulated) "
          f"in {s['wall_s']:.3f} s = {s['realtime_factor']:.0f}x real time")
    print(format_summary(s, exp.I_max))
    if "rms_a_sprung_mps2" in s:
        from mrctl.runlog.ride import format_ride

        print(format_ride(s))
    for note in res.notices:
        print(f"mrctl: {note}", file=sys.stderr)
    if args.out:
        print(f"wrote {args.out} and {Path(args.out).with_suffix('.json')}")
    if res.fault is not None:  # the run ended at the fault, at 0 A (docs/laws.md)
        _err(str(res.fault))
        return EXIT_FAILURE
    return EXIT_OK


def cmd_report(args: argparse.Namespace) -> int:
    from mrctl.offline.report import make_report
    from mrctl.sweep.table import is_results_table

    if len(args.runs) == 1 and is_results_table(args.runs[0]):
        from mrctl.sweep.command import report_sweep

        return report_sweep(args)
    make_report(args.runs, args.out, title=args.title)
    print(f"wrote {args.out}")
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    import time

    from mrctl.daemon.service import RunOptions, run

    out = time.strftime(args.out) if args.out and "%" in args.out else args.out
    columns = _columns(args.stream_columns, "--stream-columns") if args.stream_columns else None
    return run(RunOptions(args.config, out=out, duration_s=args.duration, force=args.force,
                          status_socket=args.status_socket, live=not args.quiet, stream_url=args.stream,
                          stream_every=args.stream_every, stream_columns=columns,
                          log_priorities=True if args.log_priorities else None))


def _columns(text: str, option: str) -> tuple[str, ...]:
    from mrctl.config.observe import parse_columns

    try:
        return parse_columns(text)
    except ValueError as exc:
        raise BadInput(f"{option}: {exc}") from None


def _status_path(args: argparse.Namespace) -> str:
    from mrctl.daemon.status import default_status_socket

    if args.instance:
        return f"/run/mrctl/{args.instance}/status.sock"
    return args.socket or default_status_socket(check=True)


def cmd_status(args: argparse.Namespace) -> int:
    from mrctl.daemon.status import StatusError, format_status, query_status

    fmt = "json" if args.json else args.format
    path = _status_path(args)
    try:
        st = query_status(path)  # StatusError (exit 1) with a clear message
    except StatusError:
        if fmt == "prometheus":  # the textfile collector still learns that nothing answered
            from mrctl.daemon.prometheus import prometheus_text

            print(prometheus_text(None, args.instance), end="")
        raise
    if fmt == "json":
        print(json.dumps(st, indent=2))
    elif fmt == "prometheus":
        from mrctl.daemon.prometheus import prometheus_text

        print(prometheus_text(st, args.instance), end="")
    else:
        print(format_status(st))
    return EXIT_OK


def cmd_tap(args: argparse.Namespace) -> int:
    """CSV rows of a running daemon on stdout; Ctrl-C ends it cleanly (exit 0)."""
    import os

    from mrctl.daemon.tap import parse_trigger, tap
    from mrctl.runlog.format import RUN_COLUMNS

    if args.n is not None and args.n < 1:
        raise BadInput(f"-n: must be >= 1, got {args.n}")
    columns = _columns(args.columns, "--columns") if args.columns else None
    if args.trigger is not None:
        try:
            parse_trigger(args.trigger, RUN_COLUMNS)
        except ValueError as exc:
            raise BadInput(f"--trigger: {exc}") from None
    if args.pre and args.trigger is None:
        raise BadInput("--pre: only with --trigger")
    try:
        res = tap(_status_path(args), sys.stdout.buffer, args.n, columns, args.trigger, args.pre)
    except KeyboardInterrupt:
        sys.stdout.flush()
        return EXIT_OK
    except BrokenPipeError:  # | head: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    short = args.n is not None and res.rows < args.n
    if res.end != "complete" and (short or res.end.startswith("dropped")):
        _err(f"tap: {res.rows} rows, then {res.end}")
        return EXIT_FAILURE
    return EXIT_OK


def cmd_exporter(args: argparse.Namespace) -> int:
    from mrctl.daemon.exporter import start

    path = _status_path(args)
    server, thread = start(args.listen, path, args.instance)
    host, port = server.server_address[:2]
    print(f"mrctl exporter: http://{host}:{port}/metrics, reading {path}", flush=True)
    try:
        while thread.is_alive():
            thread.join(1.0)
    except KeyboardInterrupt:
        pass
    server.shutdown()
    return EXIT_OK


def cmd_examples(args: argparse.Namespace) -> int:
    from mrctl.examples import copy_examples

    for rel in copy_examples(Path(args.dir), force=args.force):
        print(f"wrote {Path(args.dir) / rel}")
    return EXIT_OK


def cmd_identify(args: argparse.Namespace) -> int:
    """Run CSVs (mrctl's own logs of constant-current steps) or a dataset
    description (a lab's measured records, ``--dataset`` or a .yaml argument).
    Prints progress, the summary table, what was written. Errors are raised
    (IdentificationError/ConfigError exit 2, DependencyMissing without scipy
    exit 1, ReportError exit 2) for :func:`main`'s handler."""
    from mrctl.errors import BadInput

    runs = list(args.runs)
    dataset = args.dataset
    if dataset is None and len(runs) == 1 and runs[0].lower().endswith((".yaml", ".yml")):
        dataset, runs = runs[0], []
    if dataset is not None:
        if runs:
            raise BadInput("identify: give run CSVs or --dataset, not both")
        if args.period is not None or args.method != "trf":
            raise BadInput("identify: --period and --method are for run CSVs; a dataset's segments have their own "
                           "period")
        return _identify_dataset(args, dataset)
    if args.holdout is not None:
        raise BadInput("identify: --holdout is for --dataset (run CSVs are scored on their fit windows)")
    from mrctl.offline.identify import format_summary, identify_files

    def progress(i: int, n: int, I: float, elapsed: float, nrmse: float) -> None:
        print(f"[{i:2d}/{n}] I = {I:.3f} A  NRMSE {100 * nrmse:5.2f} %  ({elapsed:.1f} s)", flush=True)

    if args.period is not None and not args.period > 0:
        raise BadInput(f"identify: --period must be > 0 s, got {args.period:g}")
    result = identify_files(args.runs, args.out, method=args.method, progress=progress, period_s=args.period,
                            offset=not args.no_offset, stiffness="auto" if not args.no_offset else False)
    print(format_summary(result))
    print(f"wrote {args.out} ({len(result.fits)} currents, {result.time_s:.1f} s, optimiser {result.method})")
    if args.report:
        from mrctl.offline.report import make_identification_report

        make_identification_report(result, args.report)
        print(f"wrote {args.report}")
    return EXIT_OK


def _identify_dataset(args: argparse.Namespace, dataset: str) -> int:
    from mrctl.offline.identify import format_dataset_summary, identify_dataset_file, json_path

    model = {"offset": False, "stiffness": False} if args.no_offset else None
    res = identify_dataset_file(dataset, args.out, holdout=args.holdout, model=model,
                                progress=not args.no_progress and sys.stderr.isatty())
    print(format_dataset_summary(res))
    print(f"wrote {args.out} and {json_path(args.out)} ({res.time_s:.1f} s)")
    if args.report:
        from mrctl.offline.identify_figure import make_dataset_report

        make_dataset_report(res, args.report)
        print(f"wrote {args.report}")
    return EXIT_OK


def cmd_check(args: argparse.Namespace) -> int:
    from mrctl.config.laws import laws_markdown, laws_report
    from mrctl.daemon.feasibility import assess, wire_time_s

    if args.laws:
        print(laws_markdown())
    if not args.config:
        if not args.laws:
            _err("check: give an experiment YAML (or --laws)")
        return EXIT_OK if args.laws else EXIT_BAD_INPUT
    from mrctl.config import load_yaml
    from mrctl.sweep.spec import is_sweep_file

    if is_sweep_file(load_yaml(args.config)):
        from mrctl.sweep.check import check_sweep

        return check_sweep(args.config)
    exp = _load(args.config)
    cfg = exp.config
    wire = wire_time_s(cfg.backend)
    if wire is not None:
        f = assess(cfg.rate_hz, wire, what=f"{cfg.backend.type} at {cfg.backend.baudrate} Bd")
        if not f.ok:
            level = "warning" if cfg.link.on_infeasible == "reduce_rate" else "error"
            _err(f"{args.config}: {level}: {f.message}")
            if level == "error":
                return EXIT_BAD_INPUT
        else:
            print(f.message)
    print("\n".join(laws_report(cfg)))
    print(f"{args.config}: OK")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="mrctl", description="MR damper (Lord RD-1097-01) control daemon")
    ap.add_argument("--version", action="version", version=f"mrctl {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("simulate", help="offline closed loop (no real-time pacing)")
    sp.add_argument("config", help="experiment YAML")
    sp.add_argument("--out", help="run CSV to write (a .json sidecar goes beside it)")
    sp.add_argument("--duration", type=float, help="simulated seconds (overrides duration_s)")
    sp.add_argument("--force", action="store_true", help="replace an existing run log and sidecar")
    sp.set_defaults(func=cmd_simulate)

    from mrctl.sweep.command import add_sweep_parser

    add_sweep_parser(sub)

    rp = sub.add_parser("report", help="figure of runs: force and current over time, F-v and F-x loops; "
                                       "or of a sweep's results table")
    rp.add_argument("runs", nargs="+", metavar="RUN.csv", help="run CSVs from simulate or run (several: overlaid), "
                                                               "or one results table of mrctl sweep")
    rp.add_argument("--out", required=True, help="figure to write: .png, .pdf or .svg")
    rp.add_argument("--title", help="figure title (default: the run file names)")
    rp.add_argument("--metric", default="force_nrmse", help="sweep: the metric drawn (default force_nrmse)")
    rp.add_argument("--bound", type=float, default=0.01, help="sweep: the share at most this (default 0.01)")
    rp.set_defaults(func=cmd_report)

    rn = sub.add_parser("run", help="the real-time loop (simulated bench or real links)")
    rn.add_argument("config", help="experiment YAML")
    rn.add_argument("--out", help="run CSV to write (a .json sidecar goes beside it); "
                                  "strftime patterns such as %%Y%%m%%d-%%H%%M%%S are expanded")
    rn.add_argument("--duration", type=float, help="seconds to run (overrides duration_s)")
    rn.add_argument("--force", action="store_true", help="replace an existing run log and sidecar")
    rn.add_argument("--status-socket", help="Unix socket for mrctl status (default: $RUNTIME_DIRECTORY/status.sock)")
    rn.add_argument("--quiet", action="store_true", help="no live progress line")
    rn.add_argument("--stream", metavar="udp://HOST:PORT",
                    help="send every run-log row as a JSON datagram (PlotJuggler's UDP server; docs/observe.md)")
    rn.add_argument("--stream-every", type=int, metavar="N", help="stream every Nth row (default 1)")
    rn.add_argument("--stream-columns", metavar="COLS", help="comma-separated run-log columns to stream (default all)")
    rn.add_argument("--log-priorities", action="store_true",
                    help="prefix warnings and errors with <4>/<3> (default: when stderr is the journal)")
    rn.set_defaults(func=cmd_run)

    st = sub.add_parser("status", help="live state of a running mrctl")
    st.add_argument("--socket", help="status socket path (default as for run)")
    st.add_argument("--instance", help="the damper NAME of a mrctl@NAME service")
    st.add_argument("--format", choices=("text", "json", "prometheus"), default="text",
                    help="text (default), json, or prometheus (node_exporter textfile collector)")
    st.add_argument("--json", action="store_true", help="print the raw JSON (= --format json)")
    st.set_defaults(func=cmd_status)

    tp = sub.add_parser("tap", help="the next N rows of a running mrctl as CSV on stdout (like halsampler)")
    tp.add_argument("-n", type=int, help="rows to capture (default: until Ctrl-C)")
    tp.add_argument("--columns", "-c", metavar="COLS", help="comma-separated run-log columns (default all; in the run log's order)")
    tp.add_argument("--trigger", metavar="COND",
                    help="start at the next rising edge of fault, COLUMN>VALUE or COLUMN<VALUE (e.g. F>500)")
    tp.add_argument("--pre", type=int, default=0, metavar="N", help="with --trigger: rows before the trigger")
    tp.add_argument("--socket", help="status socket path (default as for run)")
    tp.add_argument("--instance", help="the damper NAME of a mrctl@NAME service")
    tp.set_defaults(func=cmd_tap)

    xp = sub.add_parser("exporter", help="Prometheus HTTP exporter reading the status socket (mrctl[metrics])")
    xp.add_argument("--listen", default=":9877", metavar="[HOST]:PORT", help="where to serve /metrics (default :9877)")
    xp.add_argument("--socket", help="status socket path (default as for run)")
    xp.add_argument("--instance", help="the damper NAME of a mrctl@NAME service (also a damper label)")
    xp.set_defaults(func=cmd_exporter)

    ip = sub.add_parser("identify", help="fit the LuGre parameter set: from run CSVs of constant-current steps, "
                                         "or from measured data described by a dataset YAML")
    ip.add_argument("runs", nargs="*", help="run CSVs (simulate or run) with a constant-current schedule; "
                                            "or one dataset .yaml")
    ip.add_argument("--dataset", help="dataset description (docs/identification.md): measured records, any columns")
    ip.add_argument("--out", required=True, help="parameters YAML to write (usable as parameters: FILE); "
                                                 "a dataset also writes the JSON summary beside it")
    ip.add_argument("--report", help="also draw a figure (.png/.pdf/.svg): run CSVs the paper's Figs 2 and 3, "
                                     "a dataset its held-out force and F-v loops")
    ip.add_argument("--holdout", help="dataset: held out of the fit: a fraction (0.3), none, or record names "
                                      "(a,b) held out whole; default the description's")
    ip.add_argument("--period", type=float, help="run CSVs: the excitation period (s), if it cannot be estimated")
    ip.add_argument("--no-offset", action="store_true", help="fit no force offset and stiffness (for comparison)")
    ip.add_argument("--no-progress", action="store_true", help="dataset: no progress bar")
    ip.add_argument("--method", default="trf", choices=("trf", "trf-bounds", "lm", "nelder-mead"),
                    help="run CSVs: optimiser (docs/identification.md); default trf")
    ip.set_defaults(func=cmd_identify)

    cp = sub.add_parser("check", help="validate an experiment or sweep file (every error at once); list the laws")
    cp.add_argument("config", nargs="?")
    cp.add_argument("--laws", action="store_true", help="print every installed law's keys (built-ins and plugins)")
    cp.set_defaults(func=cmd_check)

    ex = sub.add_parser("examples", help="copy the example experiments, bench configs and systemd units out")
    ex.add_argument("dir", nargs="?", default="mrctl-examples",
                    help="directory to write config/, systemd/ and README.md into (default: mrctl-examples)")
    ex.add_argument("--force", action="store_true", help="overwrite files that exist")
    ex.set_defaults(func=cmd_examples)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except MrctlError as exc:
        _err(str(exc))
        return int(exc.exit_code)
    except KeyboardInterrupt:
        _err("interrupted")
        return int(ExitCode.INTERRUPTED)
    except OSError as exc:
        _err(f"{exc.filename}: {exc.strerror or exc}" if exc.filename else str(exc.strerror or exc))
        return EXIT_FAILURE
    except Exception as exc:  # noqa: BLE001 - a lab user gets one line, not a traceback
        _err(f"internal error: {type(exc).__name__}: {exc}")
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
