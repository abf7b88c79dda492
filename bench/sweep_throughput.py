#!/usr/bin/env python3
"""Sweep throughput: local processes and a loopback Dask cluster against one ``mrctl simulate``.

Per round, on the same points (fig5_robust, 4 s, the closed law, a Monte
Carlo over its damper's F0 so no two points are alike):

1. *one simulate*: the points one after another in this process (validate,
   build, simulate: what a point costs), points/s;
2. *local sweep*: ``mrctl sweep``'s runner on all cores (processes),
   points/s, against cores × (1);
3. *Dask loopback*: ``dask scheduler`` and 2 ``dask worker`` processes (1
   thread each) on 127.0.0.1, started and stopped here; the same sweep with
   ``--scheduler``; its table compared with the local one row for row (all
   but the wall time), points/s against (2).

Medians over the rounds. On a machine other jobs load, the wall-clock
ratios say as much about them as about the sweep; the CPU seconds per point
(this process and its pool's workers; the cluster's processes by
``Client.run``) are the sweep's own overhead: CPU efficiency = one
simulate's CPU per point / the sweep's. Needs ``pip install 'mrctl[sweep]'``.

    python bench/sweep_throughput.py [--points 60] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import yaml  # noqa: E402

from hil_sim.testing.peers import free_port  # noqa: E402
from mrctl.sweep.point import run_point  # noqa: E402
from mrctl.sweep.runner import run_sweep  # noqa: E402
from mrctl.sweep.spec import expand, load_sweep  # noqa: E402
from mrctl.sweep.table import read_results  # noqa: E402


def _sweep_file(d: Path, n: int) -> Path:
    p = d / "throughput.yaml"
    p.write_text(yaml.safe_dump({
        "name": "throughput", "base": str(ROOT / "config" / "experiments" / "fig5_robust.yaml"),
        "random": {"n": n, "seed": 1, "plant.parameters.F0": {"factor_uniform": [0.8, 1.2]}},
        "metrics": ["force_nrmse", "max_current_step_A", "peak_current_A"]}))
    return p


class LoopbackCluster:
    """``dask scheduler`` + 2 ``dask worker`` on 127.0.0.1, each stopped by its pid."""

    def __init__(self, workers: int = 2) -> None:
        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.workers = workers
        self.procs: list[subprocess.Popen] = []
        self.dir = tempfile.mkdtemp(prefix="mrctl-dask-")

    def __enter__(self) -> "LoopbackCluster":
        dask = shutil.which("dask") or str(Path(sys.executable).parent / "dask")
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "cwd": self.dir}
        self.procs.append(subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                                            "--no-dashboard"], **quiet))
        for _ in range(self.workers):
            self.procs.append(subprocess.Popen([dask, "worker", self.address, "--nthreads", "1", "--nworkers", "1",
                                                "--no-dashboard", "--local-directory", self.dir], **quiet))
        from distributed import Client

        with Client(self.address, timeout="30s") as c:
            c.wait_for_workers(self.workers, timeout=60)
        return self

    def __exit__(self, *exc: object) -> None:
        for p in reversed(self.procs):
            p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        shutil.rmtree(self.dir, ignore_errors=True)


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _cluster_cpu(address: str) -> float:
    """CPU seconds used so far by the cluster's scheduler and workers."""
    from distributed import Client

    with Client(address) as c:
        return sum(c.run(time.process_time).values()) + c.run_on_scheduler(time.process_time)


def _rows(path: Path) -> list[dict[str, str]]:
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in read_results(path)[1]]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=60, help="points per run (default 60)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    a = ap.parse_args()
    cores = os.cpu_count() or 1
    serial, local, dask = [], [], []
    cpu: dict[str, list[float]] = {"serial": [], "local": [], "dask": []}  # CPU seconds per point
    same = True
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        sweep = load_sweep(_sweep_file(d, a.points), allow_outside=True)  # its base is this tree's
        t0 = time.perf_counter()
        tasks = [p.task(sweep.metrics) for p in expand(sweep)]
        build_ms = 1e3 * (time.perf_counter() - t0) / a.points
        with LoopbackCluster(2) as cluster:
            for r in range(a.rounds):
                n1 = max(cores, a.points // cores)
                t0, c0 = time.perf_counter(), time.process_time()
                for t in tasks[:n1]:
                    run_point(t)
                serial.append(n1 / (time.perf_counter() - t0))
                cpu["serial"].append((time.process_time() - c0) / n1)
                for name, kw, acc in (("local", {}, local), ("dask", {"scheduler": cluster.address}, dask)):
                    out = d / f"{name}{r}.csv"
                    c0 = time.process_time() + (_children_cpu() if name == "local" else _cluster_cpu(cluster.address))
                    t0 = time.perf_counter()
                    run_sweep(sweep, out, progress=False, **kw)
                    acc.append(a.points / (time.perf_counter() - t0))
                    c1 = time.process_time() + (_children_cpu() if name == "local" else _cluster_cpu(cluster.address))
                    cpu[name].append((c1 - c0) / a.points)
                same = same and _rows(d / f"local{r}.csv") == _rows(d / f"dask{r}.csv")
                print(f"round {r + 1}: one simulate {serial[-1]:.2f} pt/s, local {local[-1]:.2f} pt/s, "
                      f"dask {dask[-1]:.2f} pt/s", flush=True)
    s, lo, dk = statistics.median(serial), statistics.median(local), statistics.median(dask)
    cs, cl, cd = (1e3 * statistics.median(cpu[k]) for k in ("serial", "local", "dask"))
    print(f"\n{a.points} points of fig5_robust (4 s, closed), {cores} cores, medians of {a.rounds} rounds; "
          f"load average before: {os.getloadavg()[0]:.1f}")
    print("| run | points/s (wall) | ratio | CPU ms per point | CPU efficiency |\n|---|---|---|---|---|")
    print(f"| one simulate after another, 1 process | {s:.2f} | 1 | {cs:.0f} | 1 |")
    print(f"| local sweep, {cores} processes | {lo:.2f} | {lo / (cores * s):.2f} × cores × one (target ≥ 0.8) "
          f"| {cl:.0f} | {cs / cl:.2f} |")
    print(f"| Dask loopback, scheduler + 2 workers | {dk:.2f} | {dk / lo:.2f} × local (target ≥ 0.7) "
          f"| {cd:.0f} | {cs / cd:.2f} |")
    print(f"Dask's table {'is' if same else 'is NOT'} the local one row for row (all columns but wall_s)")
    print(f"a point's config built (values applied, hashed) in {build_ms:.3f} ms, as it is handed out")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
