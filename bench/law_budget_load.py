#!/usr/bin/env python3
"""fig5_robust runs next to CPU-bound neighbours: is the law faulted "too slow"?

Why: the law guard faults a law whose calls overrun its budget on three
ticks in a row. Judged on wall time, a machine busy with other work made
the ``closed`` law "too slow" though it did nothing wrong; judged on the
loop thread's CPU time (mrctl/core/controller.py) only the law's own work
counts. This script runs ``mrctl run config/experiments/fig5_robust.yaml``
``--runs`` times while ``--neighbours`` processes spin on the CPUs, and
counts the runs that ended in a law fault, their exit codes, and the
skipped deadlines (what preemption does show as).

    python bench/law_budget_load.py --runs 20
    python bench/law_budget_load.py --runs 20 --pure              # the interpreted build
    python bench/law_budget_load.py --runs 20 --tree /tmp/base    # another checkout's mrctl (a baseline)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SPIN = "import time\nend = time.monotonic() + {s}\nwhile time.monotonic() < end:\n    pass\n"


def one_run(env: dict[str, str], out: Path, duration: float) -> dict[str, object]:
    res = subprocess.run([sys.executable, "-m", "mrctl.cli", "run", str(ROOT / "config" / "experiments" /
                          "fig5_robust.yaml"), "--out", str(out), "--force", "--duration", str(duration)],
                         env=env, capture_output=True, text=True, timeout=duration * 10 + 60)
    side = json.loads(out.with_suffix(".json").read_text()) if out.with_suffix(".json").exists() else {}
    summary = side.get("summary", {})
    skipped = re.search(r"skipped deadlines (\d+)", res.stdout)
    return {"code": res.returncode, "law_fault": "law fault" in res.stderr,
            "too_slow": "was too slow" in res.stderr,
            "skipped": int(skipped.group(1)) if skipped else None,
            "nrmse_pct": None if summary.get("force_nrmse") is None else round(100 * summary["force_nrmse"], 3)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--neighbours", type=int, default=2, help="CPU-bound processes beside each run")
    ap.add_argument("--duration", type=float, default=4.0, help="seconds per run")
    ap.add_argument("--pure", action="store_true", help="MRCTL_PURE_PYTHON=1 (the interpreted build)")
    ap.add_argument("--tree", help="run the mrctl of this source tree instead (PYTHONPATH)")
    a = ap.parse_args()
    env = {k: v for k, v in os.environ.items() if k != "MRCTL_PURE_PYTHON"}
    if a.pure:
        env["MRCTL_PURE_PYTHON"] = "1"
    if a.tree:
        env["PYTHONPATH"] = str(Path(a.tree).resolve())
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for i in range(a.runs):
            spinners = [subprocess.Popen([sys.executable, "-c", SPIN.format(s=a.duration + 3)])
                        for _ in range(a.neighbours)]
            try:
                rows.append(one_run(env, Path(d) / "run.csv", a.duration))
            finally:
                for p in spinners:
                    p.kill()
                    p.wait()
            print(f"run {i + 1}: {rows[-1]}", flush=True)
    faults = sum(1 for r in rows if r["too_slow"])
    codes = sorted({int(r["code"]) for r in rows})  # type: ignore[call-overload]
    skipped = [r["skipped"] for r in rows if r["skipped"] is not None]
    what = a.tree or ("pure Python" if a.pure else "installed build")
    print(f"{what}: {a.runs} runs of fig5_robust beside {a.neighbours} spinning processes: "
          f"law 'too slow' faults in {faults}, exit codes {codes}, "
          f"skipped deadlines median {statistics.median(skipped) if skipped else 'n/a'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
