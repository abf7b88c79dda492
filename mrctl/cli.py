"""``mrctl`` command line: run, status, ls, tap, exporter, simulate, sweep, report, identify, check, calibrate,
examples, docs.

The one place that turns errors into exit codes: every user-facing error is
a :class:`mrctl.errors.MrctlError` carrying its code (:data:`EXIT_CODES`,
shown at the end of every ``--help``), and :func:`main` prints it as one
line on stderr, never a traceback.

One vocabulary (docs/cli.md, checked by tests/test_cli_vocabulary.py, which
walks every subparser): the options a concept shares are added by one helper
each (:func:`add_daemon_options`, :func:`add_quiet_options`,
:func:`add_out_options`), and :func:`build_parser` ends every subcommand's
help with the exit codes, also for subcommands added later.
"""

from __future__ import annotations

from mrctl.util.blas import limit_blas_threads

limit_blas_threads()  # before anything imports numpy (mrctl/util/blas.py)

import argparse  # noqa: E402
import json
import sys
from pathlib import Path
from typing import Any, Sequence

from mrctl import __version__
from mrctl.build import build_notice, tick_build
from mrctl.errors import BadInput, ExitCode, LinkFailure, MrctlError
from mrctl.runlog.format import exit_codes_text

EXIT_OK = ExitCode.OK
EXIT_FAILURE = ExitCode.FAILURE
EXIT_BAD_INPUT = ExitCode.BAD_INPUT

#: the end of every --help (README's "Exit codes", docs/cli.md); the table is mrctl.runlog.format's
EXIT_CODES = exit_codes_text()

#: optional dependencies by import name -> the extra that brings them (pyproject.toml)
EXTRAS = {"scipy": "identify", "matplotlib": "plot", "tqdm": "identify", "prometheus_client": "metrics"}


# -- the shared vocabulary: one helper per concept (docs/cli.md) -------------------------------

def add_daemon_options(p: argparse.ArgumentParser, serving: bool = False) -> None:
    """``--socket PATH`` and ``--instance NAME``: where a daemon is addressed
    (``serving``: where ``run`` serves its status); ``--status-socket`` stays
    a hidden alias of ``--socket``."""
    where = "where to serve the status" if serving else "the status socket of the daemon to ask"
    p.add_argument("--socket", metavar="PATH", help=f"{where} (default: $RUNTIME_DIRECTORY/status.sock, "
                                                    f"else $TMPDIR/mrctl-UID/status.sock)")
    p.add_argument("--status-socket", dest="socket", help=argparse.SUPPRESS)
    p.add_argument("--instance", metavar="NAME",
                   help="the daemon's name: a mrctl@NAME service, or a run started with --instance NAME "
                        "(mrctl ls lists them)" + ("; its status socket is then $TMPDIR/mrctl-UID/NAME.sock"
                                                   if serving else ""))


def add_quiet_options(p: argparse.ArgumentParser, progress: bool = True) -> None:
    """``-q/--quiet`` (only the result, warnings and errors) and, where there
    is progress, ``--no-progress``."""
    p.add_argument("-q", "--quiet", action="store_true",
                   help="print only the result, warnings and errors (no progress, no 'wrote' lines)")
    if progress:
        p.add_argument("--no-progress", action="store_true", help="no progress line or bar (the rest prints)")


def add_out_options(p: argparse.ArgumentParser, what: str, default: str | None = None) -> None:
    """``-o/--out`` (strftime patterns expanded, :func:`out_path`) and ``--mkdir``."""
    where = f"; default {default}" if default else ""
    p.add_argument("-o", "--out", metavar="PATH",
                   help=f"{what}{where}; strftime patterns such as %%Y%%m%%d-%%H%%M%%S are expanded")
    p.add_argument("--mkdir", action="store_true",
                   help="create --out's directory if it is missing (default: refuse, naming it; runs/ is "
                        "always created)")


#: what a command writes beside ``--out`` (a run log's sidecar, identify's JSON summary)
OUT_COMPANIONS = {"run": (".json",), "simulate": (".json",), "identify": (".json",), "sweep": (".partial.csv",)}


def out_outputs(command: str, out: str) -> list[str]:
    """``out`` and what ``command`` writes beside it (:data:`OUT_COMPANIONS`;
    ``.json``: the sidecar's name, :func:`mrctl.runlog.files.sidecar_path`)."""
    from mrctl.runlog.files import sidecar_path

    return [out, *(str(sidecar_path(out)) if c == ".json" else out + c for c in OUT_COMPANIONS.get(command, ()))]


def command_inputs(args: argparse.Namespace) -> list[str]:
    """The files a command reads that its command line names (a run's sidecar with it)."""
    from mrctl.runlog.files import sidecar_path

    named = [v for v in (getattr(args, "config", None), getattr(args, "dataset", None)) if isinstance(v, str) and v]
    runs = [*(getattr(args, "runs", None) or []), *([args.replay] if getattr(args, "replay", None) else [])]
    return named + [str(q) for r in runs for q in (r, sidecar_path(r))]


def out_path(args: argparse.Namespace, default: str | None = None, inputs: list[str] | None = None) -> str | None:
    """``--out`` with its strftime patterns expanded, or ``default``; its
    directory checked (a missing one is exit 2 naming it, unless --mkdir or
    runs/: :func:`mrctl.util.files.check_out_parent`); neither it nor what
    the command writes beside it a device, FIFO or directory, nor one of
    the command's ``inputs`` (default :func:`command_inputs`), ``--force``
    or not."""
    import time

    from mrctl.util.files import check_out_parent, refuse_inputs, refuse_special

    if args.out is not None and not args.out.strip():  # not a silent "no file" or "the default"
        raise BadInput("--out '': an empty value names no file; give a file name, or leave --out out")
    out = args.out if args.out else default
    if out is None:
        return None
    if "%" in out:
        out = time.strftime(out)
    check_out_parent(out, getattr(args, "mkdir", False))
    outputs = out_outputs(getattr(args, "command", ""), out)
    refuse_special(outputs)  # /dev/null, a FIFO, a directory: never replaced, --force or not
    refuse_inputs(outputs, command_inputs(args) if inputs is None else inputs)
    return out


def _stop_on_sigterm() -> None:
    """SIGTERM ends a command that runs until stopped (sweep, exporter, tap)
    as Ctrl-C does: a KeyboardInterrupt it turns into exit 0 (docs/cli.md)."""
    from mrctl.util import interrupt

    interrupt.install(sigterm=True)


def _say(args: argparse.Namespace, msg: str) -> None:
    """An informational line (what was written): not with -q."""
    if not getattr(args, "quiet", False):
        print(msg, flush=True)


def _err(msg: str) -> None:
    from mrctl.util.journal import ERR, Journal

    Journal(sys.stderr).log(ERR, msg)  # <3> first when stderr is the journal (a unit's ExecStartPre=)


def _load(args: argparse.Namespace, outputs: tuple[str, ...] = ()):
    """The experiment of ``args.config``, built (the files it names under its
    folder unless ``--allow-outside-paths``); none of them is one of ``outputs``."""
    from mrctl.config import load_experiment
    from mrctl.experiment import build
    from mrctl.util.files import Fence, refuse_inputs

    fence = Fence.around(Path(args.config).parent, args.allow_outside_paths)
    node = load_experiment(args.config, fence=fence)
    refuse_inputs(outputs, fence.admitted)
    return build(node)


def _load_simulated(args: argparse.Namespace):
    """The experiment ``simulate`` runs: CONFIG, or a run log replayed
    (``--replay``: its sidecar's config, or CONFIG's, with the log's motion),
    with ``--law`` replacing the inverse law."""
    from mrctl.experiment import build

    if args.replay:
        from mrctl.offline.replay import replay_config

        return build(replay_config(args.replay, args.config, args.law, allow_outside=args.allow_outside_paths))
    if not args.config:
        raise BadInput("simulate: give an experiment YAML, or --replay RUN.csv")
    if args.law:
        from mrctl.offline.replay import load_with_law

        return build(load_with_law(args.config, args.law, allow_outside=args.allow_outside_paths))
    outputs = () if args.out is None else tuple(out_outputs("simulate", args.out))
    return _load(args, outputs)  # a series the config names is no place for the run log


def cmd_simulate(args: argparse.Namespace) -> int:
    """The offline closed loop, streamed in blocks; ``--out``: :func:`mrctl.offline.simulate_log.simulate_logged`."""
    from mrctl.offline.simulate import run_duration, run_ticks, simulate_blocks
    from mrctl.offline.simulate_log import simulate_logged, simulate_verdict
    from mrctl.runlog import files
    from mrctl.util.options import check_duration
    from mrctl.util.progress import make_bar

    override = check_duration(args.duration)
    if args.no_log and args.out is not None:
        raise BadInput("--no-log and --out: give one (--no-log keeps only the figures)")
    args.out = out_path(args)
    if args.out is not None:
        files.check_log_path(args.out, args.force, args.mkdir)  # before a long simulation, not after
    exp = _load_simulated(args)
    duration = run_duration(exp, override)
    total = run_ticks(exp, duration)
    bar = make_bar(total, "simulate", not (args.quiet or args.no_progress), unit="ticks", delay_s=2.0,
                   every_s=30.0)
    done = [0]

    def progress(ticks: int) -> None:
        bar.update(ticks - done[0])
        done[0] = ticks

    try:
        if args.out is None:  # the figures only, accumulated block by block
            res = simulate_blocks(exp, duration, progress=progress)
            verdict, code = simulate_verdict(exp, res)
        else:
            def say_size(e: Any) -> None:  # a long run says, before it goes on, what the disk must hold
                if e.total_bytes >= 2**28:
                    _say(args, f"run log {args.out}: {e.text()}")

            res, verdict, code = simulate_logged(
                exp, duration, args.out, args.config, force=args.force, mkdir=args.mkdir, replay_of=args.replay,
                on_estimate=say_size, progress=progress)
    finally:
        bar.close()
    return _simulated(args, exp, res, verdict, code)


def _simulated(args: argparse.Namespace, exp: Any, res: Any, verdict: dict[str, Any], code: int) -> int:
    """What ``mrctl simulate`` prints after the run (and its exit code)."""
    from mrctl.runlog.acceptance import format_verdict
    from mrctl.runlog.metrics import format_summary

    s, law = res.summary, exp.config.inverse.law
    print(f"{exp.name}: law {law}, {int(s['ticks'])} ticks ({s['simulated_s']:.3f} s simulated) "
          f"in {s['wall_s']:.3f} s = {s['realtime_factor']:.0f}x real time")
    print(format_summary(s, exp.I_max, exp.dt, exp.excitation.settle_s))
    if "rms_a_sprung_mps2" in s:
        from mrctl.runlog.ride import format_ride

        print(format_ride(s))
    for note in res.notices:
        print(f"mrctl: {note}", file=sys.stderr)
    if args.out is not None:
        from mrctl.runlog.files import sidecar_path

        _say(args, f"wrote {args.out} and {sidecar_path(args.out)}")
    if res.fault is not None:  # the run ended at the fault, at 0 A (docs/laws.md)
        _err(str(res.fault))
        return EXIT_FAILURE
    if verdict["verdict"] == "degraded":
        _err(format_verdict(verdict))
    else:
        print(format_verdict(verdict))
    return int(code)


def cmd_report(args: argparse.Namespace) -> int:
    from mrctl.offline.report import check_panels, make_report, parse_pair
    from mrctl.sweep.table import is_results_table
    from mrctl.util.files import ensure_out_parent

    size = parse_pair(args.size, "--size", positive=True) if args.size else None  # options first, then files
    window = parse_pair(args.time, "--time") if args.time else None
    panels = check_panels([p.strip() for p in args.panels.split(",") if p.strip()]) if args.panels is not None \
        else None
    out = out_path(args, str(Path(args.runs[0]).with_suffix(".png")))  # beside the (first) run
    ensure_out_parent(out, args.mkdir)
    if len(args.runs) == 1 and is_results_table(args.runs[0]):
        from mrctl.sweep.command import report_sweep

        args.out = out
        return report_sweep(args)
    make_report(args.runs, out, title=args.title, size=size, time=window, panels=panels, force=args.force)
    _say(args, f"wrote {out}")
    return EXIT_OK


def default_log_path(config_path: str) -> str:
    """``runs/<name>-<date>-<time>.csv`` for an experiment file (its ``name``,
    else the file's stem; a bad config is reported by the run itself)."""
    from mrctl.runlog.files import default_log_path as path_for

    name = Path(config_path).stem
    try:  # the name only: validating here would import the laws' plugins twice
        from mrctl.config import load_yaml

        data = load_yaml(config_path)
        if isinstance(data, dict) and isinstance(data.get("name"), str) and data["name"].strip():
            name = data["name"]
    except Exception:  # noqa: BLE001 - the run reports a bad config with its key paths
        pass
    return path_for(str(name))


def cmd_run(args: argparse.Namespace) -> int:
    from mrctl.daemon.instances import check_instance
    from mrctl.daemon.service import RunOptions, run

    if args.stream is not None and not args.stream.strip():  # not a silent "off": leaving the option out is
        raise BadInput("--stream '': an empty value would silently turn it off; leave --stream out for none")
    if args.no_log and args.out is not None:
        raise BadInput("run: --out and --no-log contradict each other")
    if args.no_log:
        out = None
        print("no run log (--no-log): nothing of this run is recorded", flush=True)
    else:
        out = out_path(args, default_log_path(args.config))
        print(f"run log: {out}", flush=True)  # first, so a forgotten --out loses nothing
    columns = _columns(args.stream_columns, "--stream-columns") if args.stream_columns else None
    instance = check_instance(args.instance) if args.instance is not None else None
    return run(RunOptions(args.config, out=out, duration_s=args.duration, force=args.force, mkdir=args.mkdir,
                          status_socket=args.socket, instance=instance,
                          live=not (args.quiet or args.no_progress), stream_url=args.stream,
                          stream_every=args.stream_every, stream_columns=columns,
                          log_priorities=True if args.log_priorities else None,
                          allow_outside_paths=args.allow_outside_paths))


def _columns(text: str, option: str) -> tuple[str, ...]:
    from mrctl.config.observe import parse_columns

    try:
        return parse_columns(text)
    except ValueError as exc:
        raise BadInput(f"{option}: {exc}") from None


def _status_path(args: argparse.Namespace) -> str:
    from mrctl.daemon.instances import client_socket

    return client_socket(args.socket, args.instance)


def cmd_ls(args: argparse.Namespace) -> int:
    """The running daemons of this user (and the system's that it may ask)."""
    from mrctl.daemon.instances import format_daemons, list_daemons

    found = list_daemons()
    if args.json:
        print(json.dumps(found, indent=2))
    else:
        print(format_daemons(found))
    return EXIT_OK


def cmd_docs(args: argparse.Namespace) -> int:
    """One reference doc, the list of them, or where they are installed."""
    from mrctl import docs

    if args.generate:
        if not args.topic:
            raise BadInput(f"docs --generate: give a topic ({', '.join(docs.GENERATED)})")
        print(docs.generated(args.topic))
    elif args.path:
        print(docs.topic_path(args.topic) if args.topic else docs.docs_dir())
    elif args.topic:
        sys.stdout.write(docs.read_topic(args.topic))
    else:
        listed = docs.topics()
        width = max((len(t) for t, _ in listed), default=0)
        for t, title in listed:
            print(f"{t:<{width}}  {title}")
        print(f"\n{len(listed)} topics in {docs.docs_dir()} (mrctl docs TOPIC prints one; --path: where it is)")
    return EXIT_OK


def cmd_status(args: argparse.Namespace) -> int:
    from mrctl.daemon.status import StatusError, format_status, query_status

    fmt = "json" if args.json else args.format
    path = _status_path(args)
    try:
        st = query_status(path)  # StatusError (exit 3) with a clear message
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


def cmd_arm(args: argparse.Namespace) -> int:
    """Re-arm a daemon after a latched fault (docs/cli.md); exit 3 if it refuses."""
    from mrctl.daemon.arm import ArmRefused, arm

    try:
        print(f"mrctl arm: {arm(_status_path(args))}")
    except ArmRefused as exc:
        raise LinkFailure(f"mrctl arm: {exc}") from None
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
    _stop_on_sigterm()
    try:
        res = tap(_status_path(args), sys.stdout.buffer, args.n, columns, args.trigger, args.pre)
    except KeyboardInterrupt:
        sys.stdout.flush()
        return EXIT_OK
    except BrokenPipeError:  # | head: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    short = args.n is not None and res.rows < args.n
    if res.end != "complete" and (short or res.end.startswith("dropped")):  # the daemon ended or dropped us
        _err(f"tap: {res.rows} rows, then {res.end}")
        return int(ExitCode.LINK)
    return EXIT_OK


def cmd_exporter(args: argparse.Namespace) -> int:
    from mrctl.daemon.exporter import start

    path = _status_path(args)
    _stop_on_sigterm()
    server, thread = start(args.listen, path, args.instance)
    host, port = server.server_address[:2]
    shown = f"[{host}]" if ":" in str(host) else host  # an IPv6 address is bracketed in a URL
    print(f"mrctl exporter: http://{shown}:{port}/metrics, reading {path}", flush=True)
    try:
        while thread.is_alive():
            thread.join(1.0)
    except KeyboardInterrupt:
        pass
    server.shutdown()
    return EXIT_OK


def cmd_examples(args: argparse.Namespace) -> int:
    from mrctl.examples import copy_examples

    written = copy_examples(Path(args.dir), force=args.force)
    tops = sorted({rel.split("/", 1)[0] + ("/" if "/" in rel else "") for rel in written})
    _say(args, f"wrote {len(written)} files into {args.dir}: {', '.join(tops)} (--force replaces them)")
    return EXIT_OK


def cmd_identify(args: argparse.Namespace) -> int:
    """Run CSVs or a dataset description (:mod:`mrctl.offline.identify_command`).
    ``--out`` defaults to ``STEM.params.yaml`` beside the dataset (or the
    first run); strftime patterns are expanded and a missing directory is
    refused unless ``--mkdir`` (:func:`out_path`)."""
    from mrctl.offline.identify_command import identify_command

    runs = list(args.runs)
    dataset = args.dataset
    if dataset is None and len(runs) == 1 and runs[0].lower().endswith((".yaml", ".yml")):
        dataset, runs = runs[0], []  # one .yaml: the description (identify_command takes it from here)
    if dataset is None and not runs:
        raise BadInput("identify: give run CSVs or a dataset description (--dataset D.yaml)")
    yamls = [r for r in runs if r.lower().endswith((".yaml", ".yml"))]
    if yamls:
        raise BadInput(f"identify: {yamls[0]} is a description among run CSVs; give one dataset description "
                       "(--dataset D.yaml) or run CSVs, not both")
    args.dataset, args.runs = dataset, runs
    if args.describe is not None:  # the description of the run CSVs, nothing fitted
        given = [o for o, v in (("--out", args.out), ("--report", args.report),
                                ("--report-detail", args.report_detail), ("--holdout", args.holdout),
                                ("--no-offset", args.no_offset), ("--method", args.method != "trf")) if v]
        if given:
            raise BadInput(f"identify: --describe writes the description and fits nothing; {given[0]} is for the "
                           "fit (give it with --dataset D.yaml on the description)")
        args.describe = out_path(argparse.Namespace(out=args.describe, mkdir=args.mkdir), inputs=command_inputs(args))
        return identify_command(args)
    src = Path(dataset if dataset is not None else runs[0])
    args.out = out_path(args, str(src.with_name(src.stem + ".params.yaml")))
    for opt in ("report", "report_detail"):
        if getattr(args, opt):
            setattr(args, opt, out_path(argparse.Namespace(out=getattr(args, opt), mkdir=args.mkdir),
                                        inputs=command_inputs(args)))
    return identify_command(args)


def cmd_check(args: argparse.Namespace) -> int:
    from mrctl.config.laws import laws_markdown, laws_report
    from mrctl.daemon.feasibility import assess, wire_time_s, wire_words

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

        return check_sweep(args.config, allow_outside=args.allow_outside_paths)
    exp = _load(args)
    cfg = exp.config
    wire = wire_time_s(cfg.backend)
    if wire is not None:
        what, advice = wire_words(cfg.backend)
        f = assess(cfg.rate_hz, wire, what=what, advice=advice)
        if not f.ok:
            level = "warning" if cfg.link.on_infeasible == "reduce_rate" else "error"
            _err(f"{args.config}: {level}: {f.message}")
            if level == "error":
                return EXIT_BAD_INPUT
        else:
            _say(args, f.message)
    from mrctl.config.acceptance import bounds
    from mrctl.runlog.acceptance import format_bounds

    _say(args, format_bounds(bounds(cfg)))
    _say(args, "\n".join(laws_report(cfg)))
    _say(args, f"tick: {tick_build()} build")
    _say(args, f"{args.config}: OK")
    return EXIT_OK


def _outside_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--allow-outside-paths", action="store_true", help="read files the config names (parameter "
                   "sets, a calibration, series, a sweep's bases, a dataset's records) outside its folder (its "
                   "config/ tree)")


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run (or resume) a sweep (:mod:`mrctl.sweep.command`); ``--out``
    defaults to ``STEM.results.csv`` beside the sweep file."""
    from mrctl.sweep.command import run_sweep_command

    src = Path(args.config)
    args.out = out_path(args, str(src.with_name(src.stem + ".results.csv")))
    _stop_on_sigterm()
    return run_sweep_command(args)


def cmd_calibrate(args: argparse.Namespace) -> int:
    from mrctl.daemon.calibrate import run_from_args

    src = Path(args.config)
    args.out = out_path(args, str(src.with_name(src.stem + ".cal.yaml")))
    return run_from_args(args, lambda _path: _load(args))


def cmd_device(args: argparse.Namespace) -> int:
    from mrctl.daemon.device import disarm

    return disarm(_load(args), args.config, lambda m: _say(args, m), _err)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="mrctl", description="MR damper (Lord RD-1097-01) control daemon",
                                 epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--version", action="version", version=f"mrctl {__version__} ({tick_build()})")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sp = sub.add_parser("simulate", help="offline closed loop (no real-time pacing); or replay a run log's motion")
    sp.add_argument("config", nargs="?", help="experiment YAML (with --replay: used instead of the log's sidecar)")
    sp.add_argument("--replay", metavar="RUN.csv",
                    help="re-run a logged experiment's motion (t, x, v of the run log) with its sidecar's config")
    sp.add_argument("--law", metavar="NAME", help="use this inverse law instead of the config's (inverse.law)")
    add_out_options(sp, "run CSV to write (a .json sidecar goes beside it), streamed while the loop runs; a "
                        "disk that cannot hold it is refused after the first block (exit 2)")
    sp.add_argument("--no-log", action="store_true", help="keep only the figures (as without --out), in memory "
                                                          "that does not grow with --duration")
    sp.add_argument("--duration", type=float, metavar="S", help="simulated seconds (overrides duration_s)")
    sp.add_argument("--force", action="store_true", help="replace an existing run log and sidecar")
    add_quiet_options(sp)
    _outside_option(sp)
    sp.set_defaults(func=cmd_simulate)

    sw = sub.add_parser("sweep", help="run an experiment over a grid and Monte Carlo draws (docs/sweeps.md)")
    sw.add_argument("config", help="sweep YAML (config/sweeps/)")
    add_out_options(sw, "results table: .csv, or .parquet (pyarrow); an existing one of the same sweep is resumed",
                    default="the sweep's name with .results.csv, beside it")
    sw.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on a Dask distributed cluster "
                                                                   "(pip install 'mrctl[sweep]')")
    sw.add_argument("--workers", type=int, metavar="N", help="local processes (default: all cores)")
    add_quiet_options(sw)
    _outside_option(sw)
    sw.set_defaults(func=cmd_sweep)

    rp = sub.add_parser("report", help="figure of runs: force, error and current over time, F-v and F-x loops; "
                                       "faults and skipped deadlines shaded, the verdict in the caption; or of a "
                                       "sweep's results table")
    rp.add_argument("runs", nargs="+", metavar="RUN.csv", help="run CSVs from simulate or run (several: overlaid), "
                                                               "or one results table of mrctl sweep")
    add_out_options(rp, "figure to write: .png, .pdf or .svg", default="the first run's name with .png")
    rp.add_argument("--title", help="figure title (default: the runs' file names and laws)")
    rp.add_argument("--size", metavar="W,H", help="figure size in inches (default: 12 wide, by the panels)")
    rp.add_argument("--time", metavar="T0,T1", help="draw only T0 <= t <= T1 (s); the figures stay the whole run's")
    rp.add_argument("--panels", metavar="P,P,...",
                    help="panels in this order, from force, error, current, fv, fx, body_acc, stroke, tyre "
                         "(default force,error,current,fv,fx; quarter-car runs body_acc,stroke,tyre,current)")
    rp.add_argument("--force", action="store_true", help="replace an existing figure (never a run or its sidecar)")
    add_quiet_options(rp, progress=False)
    rp.add_argument("--metric", default="force_nrmse", help="sweep: the metric drawn (default force_nrmse)")
    rp.add_argument("--bound", type=float, default=0.01, help="sweep: the share at most this (default 0.01)")
    rp.set_defaults(func=cmd_report)

    rn = sub.add_parser("run", help="the real-time loop (simulated bench or real links)")
    rn.add_argument("config", help="experiment YAML")
    add_out_options(rn, "run CSV to write (a .json sidecar goes beside it)",
                    default="runs/<name>-%%Y%%m%%d-%%H%%M%%S.csv under the working directory")
    rn.add_argument("--no-log", action="store_true", help="record nothing (no run log, no sidecar)")
    rn.add_argument("--duration", type=float, metavar="S", help="seconds to run (overrides duration_s)")
    rn.add_argument("--force", action="store_true", help="replace an existing run log and sidecar")
    add_daemon_options(rn, serving=True)
    add_quiet_options(rn)
    rn.add_argument("--stream", metavar="udp://HOST:PORT",
                    help="send every run-log row as a JSON datagram (PlotJuggler's UDP server; docs/observe.md)")
    rn.add_argument("--stream-every", type=int, metavar="N", help="stream every Nth row (default 1)")
    rn.add_argument("--stream-columns", metavar="COLS", help="comma-separated run-log columns to stream (default all)")
    rn.add_argument("--log-priorities", action="store_true",
                    help="prefix warnings and errors with <4>/<3> (default: when stderr is the journal)")
    _outside_option(rn)
    rn.set_defaults(func=cmd_run)

    st = sub.add_parser("status", help="live state of a running mrctl")
    add_daemon_options(st)
    st.add_argument("--format", choices=("text", "json", "prometheus"), default="text",
                    help="text (default), json, or prometheus (node_exporter textfile collector)")
    st.add_argument("--json", action="store_true", help="print the raw JSON (= --format json)")
    st.set_defaults(func=cmd_status)

    ls = sub.add_parser("ls", help="the running daemons of this user: instance, config, pid, socket, uptime, state")
    ls.add_argument("--json", action="store_true", help="a JSON list, one object per daemon")
    ls.set_defaults(func=cmd_ls)

    am = sub.add_parser("arm", help="re-arm a running mrctl after a latched fault (E-stop, device watchdog, link "
                                    "loss): refused while the cause is still there")
    add_daemon_options(am)
    am.set_defaults(func=cmd_arm)

    tp = sub.add_parser("tap", help="the next N rows of a running mrctl as CSV on stdout (like halsampler)")
    tp.add_argument("-n", "--rows", dest="n", type=int, metavar="N", help="rows to capture (default: until Ctrl-C)")
    tp.add_argument("-c", "--columns", metavar="COLS",
                    help="comma-separated run-log columns (default all; in the run log's order)")
    tp.add_argument("--trigger", metavar="COND",
                    help="start at the next rising edge of fault, COLUMN>VALUE or COLUMN<VALUE (e.g. F>500)")
    tp.add_argument("--pre", type=int, default=0, metavar="N", help="with --trigger: rows before the trigger")
    add_daemon_options(tp)
    tp.set_defaults(func=cmd_tap)

    xp = sub.add_parser("exporter", help="Prometheus HTTP exporter reading the status socket (mrctl[metrics])")
    xp.add_argument("--listen", default="127.0.0.1:9877", metavar="[HOST]:PORT",
                    help="where to serve /metrics (default 127.0.0.1:9877, loopback only; :9877 for every address)")
    add_daemon_options(xp)
    xp.set_defaults(func=cmd_exporter)

    ip = sub.add_parser("identify", help="fit the LuGre parameter set: from run CSVs of constant-current steps, "
                                         "or from measured data described by a dataset YAML")
    ip.add_argument("runs", nargs="*", metavar="RUN.csv", help="run CSVs (simulate or run) with a constant-current "
                                                               "schedule, described as a dataset by mrctl itself; "
                                                               "or one dataset .yaml")
    ip.add_argument("--dataset", metavar="D.yaml",
                    help="dataset description (docs/identification.md): measured records, any columns")
    add_out_options(ip, "parameters YAML to write (usable as parameters: FILE); the JSON summary is written "
                        "beside it", default="STEM.params.yaml beside the dataset or the first run")
    ip.add_argument("--report", metavar="FIG", help="also draw the summary figure (.png/.pdf/.svg): held-out NRMSE "
                                                    "per record, the worst record's force and F-v loop, the "
                                                    "parameters per level and their laws, NRMSE against stroke "
                                                    "and frequency")
    ip.add_argument("--report-detail", metavar="FIG", help="also draw every level's (broadband: held-out record's) "
                                                           "force and F-v loop, with every held-out score")
    ip.add_argument("--describe", metavar="D.yaml",
                    help="run CSVs: write the dataset description mrctl makes of them (edit it, then "
                         "--dataset D.yaml) and fit nothing")
    ip.add_argument("--data-dir", metavar="DIR",
                    help="dataset: where its records are (over its data_dir: key; default its own directory); "
                         "they must lie under it")
    ip.add_argument("--holdout", help="held out of the fit: a fraction (0.3), none, or record names (a,b) held "
                                      "out whole; default the description's (run CSVs: half of each level's steady "
                                      "cycles)")
    ip.add_argument("--fit-laws", choices=("auto", "paper", "table"),
                    help="constant input: the written laws (the description's fit.laws), paper (6)-(11) or a table of the "
                         "per-level values; "
                         "default auto (whichever predicts a left-out level better)")
    ip.add_argument("--no-offset", action="store_true", help="fit no force offset and stiffness (for comparison)")
    add_quiet_options(ip)
    ip.add_argument("--force", action="store_true", help="replace existing output files (never an input)")
    _outside_option(ip)
    ip.add_argument("--method", default="trf", choices=("trf", "trf-bounds", "lm", "nelder-mead"),
                    help="constant input: the per-level optimiser (docs/identification.md); default trf")
    ip.set_defaults(func=cmd_identify)

    cp = sub.add_parser("check", help="validate an experiment or sweep file (every error at once); list the laws")
    cp.add_argument("config", nargs="?", help="experiment or sweep YAML to check (every error, with its key path)")
    cp.add_argument("--laws", action="store_true", help="print every installed law's keys (built-ins and plugins)")
    add_quiet_options(cp, progress=False)
    _outside_option(cp)
    cp.set_defaults(func=cmd_check)

    ca = sub.add_parser("calibrate", help="day one on a bench (device presets): offsets and noise at rest and 0 A, "
                                          "the driver+coil lag from current steps; writes CAL.yaml for "
                                          "'calibration: CAL.yaml' (docs/hardware.md)")
    ca.add_argument("config", help="experiment YAML with a device backend (backend.device, backend.channels)")
    add_out_options(ca, "calibration YAML to write", default="CONFIG's name with .cal.yaml, beside it")
    ca.add_argument("--force", action="store_true", help="replace --out if it exists")
    ca.add_argument("--rest-s", type=float, default=2.0, metavar="S", help="seconds read at rest, 0 A (default 2)")
    ca.add_argument("--step-amps", dest="step_A", type=float, default=None, metavar="A",
                    help="current step (A; default half of safety.I_max)")
    ca.add_argument("--steps", type=int, default=8, metavar="N", help="steps up and down (0 = no lag fit; default 8)")
    ca.add_argument("--step-s", type=float, default=0.08, metavar="S", help="seconds per step (default 0.08)")
    ca.add_argument("--rate-hz", type=float, default=200.0, metavar="HZ", help="exchanges per second (default 200)")
    ca.add_argument("--accept-dead-channels", action="store_true",
                    help="write the calibration although an input read one constant value at rest (a disconnected "
                         "or stuck input, or a sensor whose noise is below the converter's step)")
    _outside_option(ca)
    ca.set_defaults(func=cmd_calibrate)

    dv = sub.add_parser("device", help="a device preset's own settings: device disarm CONFIG turns its watchdog "
                                       "off in flash (docs/hardware.md)")
    dv.add_argument("action", choices=("disarm",), help="disarm: WATCHDOG_ENABLE_DEFAULT = 0, read back")
    dv.add_argument("config", help="experiment YAML with the device backend (backend.device, host, port)")
    add_quiet_options(dv, progress=False)
    _outside_option(dv)
    dv.set_defaults(func=cmd_device)

    ex = sub.add_parser("examples", help="copy the example experiments, bench configs, systemd units and docs out")
    ex.add_argument("dir", nargs="?", default="mrctl-examples",
                    help="directory to write config/, systemd/, docs/ and README.md into (default: mrctl-examples)")
    ex.add_argument("--force", action="store_true", help="overwrite files that exist")
    add_quiet_options(ex, progress=False)
    ex.set_defaults(func=cmd_examples)

    dp = sub.add_parser("docs", help="the reference docs installed with mrctl: list them, print one, or where they are")
    dp.add_argument("topic", nargs="?", metavar="TOPIC",
                    help="config, laws, runlog, protocol, registers, install, reliability, ... (a prefix will do); "
                         "none: list them")
    dp.add_argument("--path", action="store_true", help="print where the docs (or TOPIC's file) are installed")
    dp.add_argument("--generate", action="store_true",
                    help="print TOPIC's reference generated from the installed code (config, runlog, laws, "
                         "identification), plugins included")
    dp.set_defaults(func=cmd_docs)
    finish_parser(ap)
    return ap


def finish_parser(ap: argparse.ArgumentParser) -> None:
    """Every subcommand's --help ends with the exit codes (also a
    subcommand added without its own epilog)."""
    for action in ap._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sp in action.choices.items():
                if not sp.epilog or "exit codes:" not in sp.epilog:
                    codes = exit_codes_text(name)
                    sp.epilog = f"{sp.epilog}\n\n{codes}" if sp.epilog else codes
                if sp.formatter_class is argparse.HelpFormatter:
                    sp.formatter_class = argparse.RawDescriptionHelpFormatter


def _command(argv: Sequence[str] | None) -> str | None:
    """The subcommand named on the command line (before argparse runs)."""
    words = list(sys.argv[1:] if argv is None else argv)
    return next((w for w in words if not w.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    if _command(argv) == "run":  # a SIGTERM or SIGHUP from here on is handled (mrctl.daemon.signals)
        from mrctl.daemon.signals import install_startup

        install_startup()
    else:  # a Ctrl-C is the user's, wherever it lands (a law's call too: mrctl/util/interrupt.py)
        from mrctl.util import interrupt

        interrupt.install()
    command = None
    try:
        args = build_parser().parse_args(argv)
        command = args.command
        if command in ("run", "simulate"):
            notice = build_notice()  # the compiled tick was wanted but not built at install
            if notice is not None:
                print(notice, file=sys.stderr)
        code = int(args.func(args))
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return code
    except MrctlError as exc:
        _err(str(exc))
        return int(exc.exit_code)
    except KeyboardInterrupt as exc:
        if getattr(exc, "signum", None) is not None:  # a stop before the service began: nothing was touched
            _err(f"stopped by {exc.name} during start-up: nothing ran")  # type: ignore[attr-defined]
            return EXIT_OK
        if command in ("sweep", "tap", "exporter"):  # runs until stopped: the user stopped it (docs/cli.md)
            _err("stopped before it began: nothing written")
            return EXIT_OK
        _err("interrupted: nothing written")
        return int(ExitCode.INTERRUPTED)
    except ModuleNotFoundError as exc:  # an optional dependency not caught where it is imported
        root = (exc.name or "").split(".")[0]
        if root not in EXTRAS:
            _err(f"internal error: {exc}")
            return EXIT_FAILURE
        _err(f"{root} is needed for mrctl {command}: pip install 'mrctl[{EXTRAS[root]}]'")
        return EXIT_BAD_INPUT
    except BrokenPipeError:  # mrctl ... | head: the reader has what it wanted
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except OSError as exc:
        _err(f"{exc.filename}: {exc.strerror or exc}" if exc.filename else str(exc.strerror or exc))
        return EXIT_FAILURE
    except Exception as exc:  # noqa: BLE001 - a lab user gets one line, not a traceback
        _err(f"internal error: {type(exc).__name__}: {exc}")
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
