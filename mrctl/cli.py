"""``mrctl`` command line: run, status, simulate, report, identify, check.

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
from mrctl.errors import ExitCode, MrctlError
from mrctl.util.jsonutil import jsonable

EXIT_OK = ExitCode.OK
EXIT_FAILURE = ExitCode.FAILURE
EXIT_BAD_INPUT = ExitCode.BAD_INPUT


def _err(msg: str) -> None:
    print(f"mrctl: {msg}", file=sys.stderr)


def _load(config_path: str):
    from mrctl.config import load_experiment
    from mrctl.experiment import build

    return build(load_experiment(config_path))


def cmd_simulate(args: argparse.Namespace) -> int:
    from mrctl.runlog.metrics import format_summary
    from mrctl.offline.simulate import run_duration, simulate, write_csv

    exp = _load(args.config)
    duration = run_duration(exp, args.duration)
    res = simulate(exp, duration)
    s = res.summary
    meta = {
        "mrctl_version": __version__,
        "python": platform.python_version(),
        "host": platform.node(),
        "config_file": str(Path(args.config).resolve()),
        "config": jsonable(exp.config),
        "parameters": exp.params.as_dict(),
        "summary": s,
        "notices": res.notices,
    }
    if args.out:
        write_csv(res, args.out, comment=f"mrctl {__version__} simulate {args.config}")
        Path(args.out).with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    law = exp.config.inverse.law
    print(f"{exp.name}: law {law}, {int(s['ticks'])} ticks ({s['simulated_s']:.3f} s simulated) "
          f"in {s['wall_s']:.3f} s = {s['realtime_factor']:.0f}x real time")
    print(format_summary(s, exp.I_max))
    for note in res.notices:
        print(f"mrctl: {note}", file=sys.stderr)
    if args.out:
        print(f"wrote {args.out} and {Path(args.out).with_suffix('.json')}")
    return EXIT_OK


def cmd_report(args: argparse.Namespace) -> int:
    from mrctl.offline.report import make_report

    make_report(args.run, args.out, title=args.title)
    print(f"wrote {args.out}")
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    import time

    from mrctl.daemon.service import RunOptions, run

    out = time.strftime(args.out) if args.out and "%" in args.out else args.out
    return run(RunOptions(args.config, out=out, duration_s=args.duration,
                          status_socket=args.status_socket, live=not args.quiet))


def cmd_status(args: argparse.Namespace) -> int:
    from mrctl.daemon.status import default_status_socket, query_status

    if args.instance:
        path = f"/run/mrctl/{args.instance}/status.sock"
    else:
        path = args.socket or default_status_socket()
    try:
        st = query_status(path)
    except OSError as exc:
        _err(str(exc))
        return EXIT_FAILURE
    if args.json:
        print(json.dumps(st, indent=2))
        return EXIT_OK
    t = st.get("timing") or {}
    print(f"{st.get('experiment')} (pid {st.get('pid')}): up {st.get('uptime_s', 0):.1f} s, "
          f"{st.get('rate_hz')} Hz, {st.get('ticks')} ticks, law {st.get('law')}")
    print(f"current {st.get('current_A', 0.0):.4f} A, safety {st.get('safety_state')} "
          f"(fault {st.get('fault')}), link errors {st.get('link_errors')}")
    if t:
        print(f"lateness p50/p99/max {t.get('lateness_p50_us')}/{t.get('lateness_p99_us')}/"
              f"{t.get('lateness_max_us')} us, compute p99 {t.get('compute_p99_us')} us, "
              f"overruns {t.get('overruns')}")
    return EXIT_OK


def cmd_identify(args: argparse.Namespace) -> int:
    from mrctl.offline.identify import cli_identify

    return cli_identify(args.runs, args.out, method=args.method, report_png=args.report)


def cmd_check(args: argparse.Namespace) -> int:
    from mrctl.daemon.feasibility import assess, wire_time_s

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
    sp.set_defaults(func=cmd_simulate)

    rp = sub.add_parser("report", help="figure of a run: force and current over time, F-v and F-x loops")
    rp.add_argument("run", help="run CSV from simulate or run")
    rp.add_argument("--out", required=True, help="PNG to write")
    rp.add_argument("--title", help="figure title (default: the run file name)")
    rp.set_defaults(func=cmd_report)

    rn = sub.add_parser("run", help="the real-time loop (simulated bench or real links)")
    rn.add_argument("config", help="experiment YAML")
    rn.add_argument("--out", help="run CSV to write (a .json sidecar goes beside it); "
                                  "strftime patterns such as %%Y%%m%%d-%%H%%M%%S are expanded")
    rn.add_argument("--duration", type=float, help="seconds to run (overrides duration_s)")
    rn.add_argument("--status-socket", help="Unix socket for mrctl status (default: $RUNTIME_DIRECTORY/status.sock)")
    rn.add_argument("--quiet", action="store_true", help="no live progress line")
    rn.set_defaults(func=cmd_run)

    st = sub.add_parser("status", help="live state of a running mrctl")
    st.add_argument("--socket", help="status socket path (default as for run)")
    st.add_argument("--instance", help="the damper NAME of a mrctl@NAME service")
    st.add_argument("--json", action="store_true", help="print the raw JSON")
    st.set_defaults(func=cmd_status)

    ip = sub.add_parser("identify", help="fit the LuGre parameter set from constant-current sine runs")
    ip.add_argument("runs", nargs="+", help="run CSVs (simulate or run) with a constant-current schedule")
    ip.add_argument("--out", required=True, help="parameters YAML to write (usable as parameters: FILE)")
    ip.add_argument("--method", default="trf", choices=("trf", "trf-bounds", "lm", "nelder-mead"),
                    help="optimiser (docs/identification.md); default trf")
    ip.add_argument("--report", help="also draw Figs 2 and 3 of the paper to this PNG")
    ip.set_defaults(func=cmd_identify)

    cp = sub.add_parser("check", help="validate an experiment config; lists every error")
    cp.add_argument("config")
    cp.set_defaults(func=cmd_check)
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
        _err(f"{exc.filename or ''}: {exc.strerror or exc}")
        return EXIT_FAILURE
    except Exception as exc:  # noqa: BLE001 - a lab user gets one line, not a traceback
        _err(f"internal error: {type(exc).__name__}: {exc}")
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
