"""Running a sweep's points: in this process, on this machine's cores, or on Dask.

Local by default: a process pool with one worker per core (no server to
start); ``scheduler`` (``tcp://HOST:PORT`` or a ``distributed.Client``) runs
the same tasks on a Dask distributed cluster. Both ship the point's plain
data (:meth:`Point.task`), so a worker needs mrctl installed and nothing
else, and both call the one function :func:`mrctl.sweep.point.run_point`
(up to :data:`MAX_BATCH` points per task, :func:`run_points`): the table
does not depend on where a point ran. At most a few tasks per worker are in
flight, so a Ctrl-C stops within one batch's time and a 10⁴-point sweep
never sits in memory as futures.
"""

from __future__ import annotations

import itertools
import os
import signal
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from mrctl.errors import BadInput, DependencyMissing, ExitCode, MrctlError
from mrctl.sweep.point import prewarm, run_point, run_points
from mrctl.sweep.spec import Point, Sweep, expand
from mrctl.sweep.table import ResultsTable, columns
from mrctl.util.progress import make_bar

IN_FLIGHT_PER_WORKER = 4
#: most points sent to a worker at once: a compiled point is ~8 ms, and a
#: task's round trip through a process pool or Dask costs a good part of that
MAX_BATCH = 8


def batch_size(n_points: int, n_workers: int) -> int:
    """Points per task: up to :data:`MAX_BATCH`, fewer when the sweep is
    small, so every worker still gets several tasks."""
    return max(1, min(MAX_BATCH, n_points // (IN_FLIGHT_PER_WORKER * max(1, n_workers))))


def _batches(tasks: Iterable[dict[str, Any]], size: int) -> Iterator[list[dict[str, Any]]]:
    it = iter(tasks)
    while batch := list(itertools.islice(it, size)):
        yield batch


class SweepInterrupted(MrctlError):
    """Ctrl-C: the table holds the points done; re-running resumes."""

    exit_code = ExitCode.INTERRUPTED


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides; workers finish their point


def _bounded(submit: Callable[[dict[str, Any]], Any], tasks: Iterable[dict[str, Any]], limit: int,
             done_of: Callable[[list[Any]], tuple[list[Any], list[Any]]]) -> Iterator[dict[str, Any]]:
    pending: list[Any] = []
    it = iter(tasks)
    exhausted = False
    while True:
        while not exhausted and len(pending) < limit:
            try:
                pending.append(submit(next(it)))
            except StopIteration:
                exhausted = True
        if not pending:
            return
        done, pending = done_of(pending)
        for f in done:
            yield from f.result()  # a batch's rows


def run_local(tasks: Iterable[dict[str, Any]], workers: int, batch: int = 1) -> Iterator[dict[str, Any]]:
    """Rows of ``tasks`` on ``workers`` processes (1: in this process), ``batch`` points per task."""
    if workers <= 1:
        for t in tasks:
            yield run_point(t)
        return
    it = iter(tasks)
    first = next(it, None)
    if first is None:
        return
    prewarm(first)  # before the fork: workers inherit the imports and the law registry
    tasks = itertools.chain([first], it)
    pool = ProcessPoolExecutor(max_workers=workers, initializer=_ignore_sigint)
    try:
        def done_of(pending: list[Future]) -> tuple[list[Future], list[Future]]:
            d, p = wait(pending, return_when=FIRST_COMPLETED)
            return list(d), list(p)

        yield from _bounded(lambda b: pool.submit(run_points, b), _batches(tasks, batch),
                            IN_FLIGHT_PER_WORKER * workers, done_of)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def dask_client(scheduler: Any) -> tuple[Any, bool]:
    """(client, owned): a ``distributed.Client`` given, or one connected to ``tcp://HOST:PORT``."""
    if not isinstance(scheduler, str):
        return scheduler, False
    try:
        from distributed import Client
    except ImportError:
        raise DependencyMissing("--scheduler needs dask.distributed: pip install 'mrctl[sweep]'") from None
    if not scheduler.startswith(("tcp://", "tls://", "ucx://", "inproc://")):
        raise BadInput(f"--scheduler: {scheduler!r}: expected an address such as tcp://HOST:8786")
    try:
        return Client(scheduler, timeout="10s"), True
    except (OSError, TimeoutError) as exc:
        from mrctl.errors import LinkFailure

        raise LinkFailure(f"--scheduler {scheduler}: cannot connect: {exc}") from None


def run_dask(tasks: Iterable[dict[str, Any]], client: Any, batch: int = 1) -> Iterator[dict[str, Any]]:
    """Rows of ``tasks`` on a Dask cluster (the same :func:`run_points`), ``batch`` points per task."""
    from distributed import wait as dwait

    n = max(1, sum(client.nthreads().values()))

    def done_of(pending: list[Any]) -> tuple[list[Any], list[Any]]:
        r = dwait(pending, return_when="FIRST_COMPLETED")
        return list(r.done), list(r.not_done)

    futures: list[Any] = []

    def submit(b: list[dict[str, Any]]) -> Any:
        f = client.submit(run_points, b, key=f"mrctl-points-{b[0]['hash']}-{b[0]['index']}-{len(b)}", pure=False)
        futures.append(f)
        return f

    try:
        yield from _bounded(submit, _batches(tasks, batch), IN_FLIGHT_PER_WORKER * n, done_of)
    finally:
        client.cancel([f for f in futures if not f.done()])


def run_sweep(sweep: Sweep, out: str | os.PathLike[str], scheduler: Any = None, workers: int | None = None,
              progress: bool = True) -> dict[str, int]:
    """Run every point not yet in ``out``; counts by status (this run's points), plus ``skipped``.

    Raises :class:`SweepInterrupted` on Ctrl-C, after the table is closed valid."""
    table = ResultsTable(Path(out), columns(sweep.axes, sweep.metrics))
    client, owned = dask_client(scheduler) if scheduler is not None else (None, False)
    done = table.open()
    counts = {"ok": 0, "fault": 0, "invalid": 0, "error": 0, "skipped": 0}
    values: dict[int, dict[str, Any]] = {}
    todo: list[Point] = []
    total = 0
    for p in expand(sweep):
        total += 1
        if isinstance(p, tuple):  # values that cannot be applied: a failed row at once (if not yet there)
            index, vals, error = p
            h = f"unresolved-{index}"
            if h in done:
                counts["skipped"] += 1
                continue
            table.add({"point": index, "config_hash": h, **vals, "status": "invalid", "error": error,
                       "mrctl_version": "", "build": ""})
            counts["invalid"] += 1
            continue
        if p.hash in done:
            counts["skipped"] += 1
            continue
        done.add(p.hash)  # a point twice in a sweep (same config) runs once
        values[p.index] = {**p.values, "seed": p.seed}
        todo.append(p)
    bar = make_bar(total, "sweep", progress, initial=total - len(todo), unit="pt", every_s=5.0)
    n_workers = workers if workers is not None else (os.cpu_count() or 1)
    tasks = (p.task(sweep.metrics) for p in todo)
    if client is not None:
        n_workers = max(1, sum(client.nthreads().values()))
    size = batch_size(len(todo), n_workers)
    rows = run_dask(tasks, client, size) if client is not None else run_local(tasks, n_workers, size)
    complete = False
    try:
        for row in rows:
            table.add({**row, **values[row["point"]]})
            counts[row["status"]] += 1
            bar.update()
        complete = True
    except KeyboardInterrupt:
        raise SweepInterrupted(f"interrupted: {len(table.rows)} of {total} points in {out}; "
                               f"run the same command again to resume") from None
    finally:
        if hasattr(rows, "close"):
            rows.close()
        bar.close()
        table.close(complete)
        if owned:
            client.close()
    return counts
