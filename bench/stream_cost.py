#!/usr/bin/env python3
"""What the live UDP stream costs the loop: compute p99 with and without it, same window.

Each round runs the real controller tick (fig5 on the in-process sim bench,
safety supervisor, recorder formatting the log in the loop's idle time:
``bench/controller_tick.py``) twice, back to back, in alternating order:
once as ``mrctl run --out`` runs it, once with the stream added as ``mrctl
run --stream`` adds it (the recorder's hand-over feeds a row bus; the UDP
sink formats and sends every row in the loop's idle time) to a receiver that
never reads (a bound UDP socket with a 4 KiB buffer, nobody calling recv).
Each run goes through ``bench/loop_timing.py``'s ``run_strategy``, with
cyclictest in the same window when it is installed (``apt-get install -y
rt-tests``). Reported: per run, compute p99 and lateness p99 (µs),
overruns, datagrams sent and dropped; then the medians per variant.

    python bench/stream_cost.py --rounds 4 --seconds 8
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import controller_tick  # noqa: E402
from loop_timing import cyclictest_path, run_strategy  # noqa: E402

from mrctl.daemon import rt  # noqa: E402
from mrctl.daemon.rowbus import RowBus  # noqa: E402
from mrctl.daemon.stream import UdpStream  # noqa: E402
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS  # noqa: E402

_streams: list[UdpStream] = []


def _deaf_receiver() -> tuple[socket.socket, str]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.bind(("127.0.0.1", 0))
    return s, f"udp://127.0.0.1:{s.getsockname()[1]}"


def make_tick_stream(period_s: float) -> tuple[Callable[[int, int], object], Callable[[int], object]]:
    """As ``controller_tick.make_tick``, plus the stream exactly as the service wires it."""
    tick, background = controller_tick.make_tick(period_s)
    rec = background.__self__  # Recorder.format_pending's recorder
    sock, url = _deaf_receiver()
    bus = RowBus(RUN_COLUMNS, rec.block_ticks, defer=True)
    st = UdpStream(url, RUN_COLUMNS, None, 1, epoch0=time.time, formats=RUN_FORMATS)
    st._deaf = sock  # keep the receiver open (and unread) for the run
    bus.add(st)
    rec.on_block = bus.publish
    _streams.append(st)

    def both(until_ns: int) -> None:
        background(until_ns)
        bus.work(until_ns)

    return tick, both


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=4, help="pairs of runs (order alternates)")
    ap.add_argument("--seconds", type=float, default=8.0, help="seconds per run")
    ap.add_argument("--strategy", default="hybrid", help="wait strategy (the daemon's default: hybrid)")
    ap.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    a = ap.parse_args(argv)
    settings = rt.RtSettings(gc_freeze=True, gc_disable=True)
    use_ct = cyclictest_path() is not None
    variants = {"log": controller_tick.make_tick, "log+stream": make_tick_stream}
    rows: list[dict[str, Any]] = []
    print(f"{a.rounds} rounds x {a.seconds:g} s per variant, {a.strategy}; times in µs"
          + ("" if use_ct else " (no cyclictest: apt-get install -y rt-tests)"))
    print(f"{'round':>5} {'variant':>11} {'comp p99':>9} {'late p99':>9} {'ct p99':>7} {'overruns':>8} "
          f"{'sent':>7} {'dropped':>7}")
    for r in range(a.rounds):
        order = list(variants) if r % 2 == 0 else list(reversed(variants))
        for name in order:
            n_before = len(_streams)
            row = run_strategy(a.strategy, a.seconds, 1000.0, variants[name], 3e-4, settings, use_ct)
            st = _streams[-1].stats() if len(_streams) > n_before else {}
            row.update(round=r, variant=name, stream=st)
            rows.append(row)
            ct = (row.get("cyclictest") or {}).get("p99_us")
            print(f"{r:>5} {name:>11} {row['compute_p99_us']:>9.1f} {row['lateness_p99_us']:>9.1f} "
                  f"{ct if ct is not None else '-':>7} {row['overruns']:>8} "
                  f"{st.get('datagrams', '-'):>7} {st.get('dropped', '-'):>7}", flush=True)
    for name in variants:
        comp = [x["compute_p99_us"] for x in rows if x["variant"] == name]
        late = [x["lateness_p99_us"] for x in rows if x["variant"] == name]
        print(f"median {name:>11}: compute p99 {statistics.median(comp):.1f} µs "
              f"({', '.join(f'{c:.0f}' for c in comp)}), lateness p99 {statistics.median(late):.1f} µs")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=2, default=str))
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
