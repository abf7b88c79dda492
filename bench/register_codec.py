"""Register codec cost per tick: the table-driven codec against the code-generated one.

mrctl.io.registers.codec decodes and encodes register blocks with tables over
precompiled structs. Before it, mrctl/io/registers.py generated one small
function per map with exec(); this benchmark loads that module from git
history (the parent of the commit that removed it, or --old-rev) and times
both, alternating, in the same process:

* host, per tick: ``encode_write_into`` (setpoint → write block) +
  ``decode_read`` (sample block → values), the link's part;
* device, per tick: ``decode_write`` + ``encode_sample``, hil_sim's part.

Each round times ``-n`` ticks of one codec; rounds alternate old/new so load
drifts hit both; the figure is the median over rounds, µs per tick.

    python bench/register_codec.py            # default map, 31 rounds of 20000 ticks
    python bench/register_codec.py --rounds 11 -n 5000 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.io.base import Sample  # noqa: E402
from mrctl.io.registers import DEFAULT_REGISTER_MAP, RegisterMap  # noqa: E402

SAMPLE = Sample(70000, 12.5, 0.0125, -0.25, 321.5, 8, 0.75)


def load_old(rev: str | None) -> tuple[Any, str]:
    """The code-generating registers module at ``rev`` (default: the parent of
    the commit that deleted mrctl/io/registers.py), as a module object."""
    if rev is None:
        out = subprocess.run(["git", "-C", str(ROOT), "log", "--diff-filter=D", "--format=%H", "-1", "--",
                              "mrctl/io/registers.py"], capture_output=True, text=True, check=True).stdout.strip()
        if not out:
            raise SystemExit("cannot find the commit that removed mrctl/io/registers.py; pass --old-rev")
        rev = out + "^"
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:mrctl/io/registers.py"],
                         capture_output=True, text=True, check=True).stdout
    mod = types.ModuleType("old_registers")
    sys.modules["old_registers"] = mod  # dataclasses look their module up
    exec(compile(src, f"{rev}:mrctl/io/registers.py", "exec"), mod.__dict__)  # noqa: S102 - our own history
    rev_short = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", rev],
                               capture_output=True, text=True, check=True).stdout.strip()
    return mod, rev_short


def host_tick(m: Any) -> Callable[[int], float]:
    """n host ticks (encode the setpoint, decode the sample), seconds."""
    buf = bytearray(64)
    (blk,) = m.encode_read(SAMPLE)
    enc, dec = m.encode_write_into, m.decode_read

    def run(n: int) -> float:
        t0 = time.perf_counter()
        for _ in range(n):
            enc(buf, 20, 0.5, 1, 50)
            dec(blk)
        return time.perf_counter() - t0

    return run


def device_tick(m: Any) -> Callable[[int], float]:
    """n device ticks (decode the setpoint, encode the sample), seconds."""
    wblk = m.encode_write(0.5, True, 50)
    dec, enc = m.decode_write, m.encode_sample

    def run(n: int) -> float:
        t0 = time.perf_counter()
        for _ in range(n):
            dec(wblk)
            enc(SAMPLE)
        return time.perf_counter() - t0

    return run


def empty_loop(n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        pass
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("-n", type=int, default=20000, help="ticks per round (default 20000)")
    ap.add_argument("--rounds", type=int, default=31, help="rounds per codec, alternating (default 31)")
    ap.add_argument("--old-rev", help="git revision holding the old mrctl/io/registers.py")
    ap.add_argument("--json", help="write the figures here")
    a = ap.parse_args(argv)
    old_mod, rev = load_old(a.old_rev)
    maps = {"old": old_mod.RegisterMap.from_mapping(DEFAULT_REGISTER_MAP),
            "new": RegisterMap.from_mapping(DEFAULT_REGISTER_MAP)}
    # both codecs must agree before their speed means anything
    assert maps["old"].decode_read(*maps["old"].encode_read(SAMPLE)) == maps["new"].decode_read(
        *maps["new"].encode_read(SAMPLE))
    assert maps["old"].encode_write(0.5, True, 50) == maps["new"].encode_write(0.5, True, 50)
    cases = {(side, name): (host_tick if side == "host" else device_tick)(m)
             for side in ("host", "device") for name, m in maps.items()}
    per_tick: dict[tuple[str, str], list[float]] = {k: [] for k in cases}
    loop: list[float] = []
    for fn in cases.values():  # warm up
        fn(a.n // 10)
    for _ in range(a.rounds):
        loop.append(empty_loop(a.n) / a.n * 1e6)
        for k, fn in cases.items():
            per_tick[k].append(fn(a.n) / a.n * 1e6)
    med = {k: statistics.median(v) for k, v in per_tick.items()}
    print(f"register codec, default map, µs per tick (median of {a.rounds} alternating rounds of {a.n} ticks; "
          f"old = code generated with exec at {rev}; empty loop {statistics.median(loop):.3f} µs/iteration, "
          f"included)")
    print(f"{'side':8s} {'old':>8s} {'new':>8s} {'new-old':>8s}")
    for side, what in (("host", "encode_write_into + decode_read"), ("device", "decode_write + encode_sample")):
        o, n = med[(side, "old")], med[(side, "new")]
        print(f"{side:8s} {o:8.3f} {n:8.3f} {n - o:+8.3f}   ({what})")
    print(f"Python {sys.version.split()[0]}, load average {os.getloadavg()[0]:.2f} at the end")
    if a.json:
        Path(a.json).write_text(json.dumps({"rev": rev, "n": a.n, "rounds": a.rounds,
                                            "median_us": {f"{s}_{c}": v for (s, c), v in med.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
