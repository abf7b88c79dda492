"""Running a sweep's points: in this process, on this machine's cores, or on Dask.

Local by default: a process pool with one worker per core (no server to
start); ``scheduler`` (``tcp://HOST:PORT`` or a ``distributed.Client``) runs
the same tasks on a Dask distributed cluster. Both ship the point's plain
data (:meth:`Point.task`), so a worker needs mrctl installed and nothing
else, and both call the one function :func:`mrctl.sweep.point.run_point`
(up to :data:`MAX_BATCH` points per task, :func:`run_points`): the table
does not depend on where a point ran. Points are built as they are handed
out and at most a few tasks per worker are in flight, so a Ctrl-C stops
within one batch's time and a sweep's size costs no memory.

A pool worker dies with its parent (a parent-death signal, and a check of
its parent at start): a killed sweep leaves no worker computing, nor holding
the table's lock. A scheduler is asked who it is before a client connects,
within :data:`SCHEDULER_TIMEOUT_S` of wall-clock time whatever the peer
does: a peer that is mute, or is not a Dask scheduler, is a link failure
(exit 3).
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import itertools
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from mrctl.errors import BadInput, DependencyMissing, ExitCode, LinkFailure, MrctlError
from mrctl.sweep.point import prewarm, run_point, run_points
from mrctl.sweep.points import Unresolved
from mrctl.sweep.spec import Sweep
from mrctl.sweep.table import ResultsTable, columns
from mrctl.util.progress import make_bar

#: wall-clock bound on reaching a scheduler and hearing who it is (s)
SCHEDULER_TIMEOUT_S = 10.0
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
    """Ctrl-C or SIGTERM: the table holds the points done; re-running resumes.
    Exit 0, as every command the user stops (docs/cli.md, "Exit codes"): the
    user asked for it and the table is valid."""

    exit_code = ExitCode.OK


_PR_SET_PDEATHSIG = 1


def _worker_init(parent: int) -> None:
    """A pool worker: SIGINT ignored (the parent decides; workers finish their
    point), killed when its parent dies (Linux: PR_SET_PDEATHSIG; elsewhere a
    thread watching the parent), and gone at once if it already has."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    armed = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            armed = libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent:  # died before the signal was armed
        os._exit(1)
    if not armed:
        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(1.0)
            os._exit(1)

        threading.Thread(target=watch, name="mrctl-parent-watch", daemon=True).start()


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
    # forked (whatever the interpreter's default): workers inherit the prewarmed imports, and this process
    # is their parent, whose death they watch
    ctx = multiprocessing.get_context("fork") if "fork" in multiprocessing.get_all_start_methods() else None
    pool = ProcessPoolExecutor(max_workers=workers, initializer=_worker_init, initargs=(os.getpid(),),
                               mp_context=ctx)
    try:
        def done_of(pending: list[Future]) -> tuple[list[Future], list[Future]]:
            d, p = wait(pending, return_when=FIRST_COMPLETED)
            return list(d), list(p)

        yield from _bounded(lambda b: pool.submit(run_points, b), _batches(tasks, batch),
                            IN_FLIGHT_PER_WORKER * workers, done_of)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def check_scheduler_address(scheduler: str) -> None:
    """``BadInput`` unless ``scheduler`` is a Dask address (before anything runs)."""
    if not scheduler.startswith(("tcp://", "tls://", "ucx://", "inproc://")):
        raise BadInput(f"--scheduler: {scheduler!r}: expected an address such as tcp://HOST:8786")


async def _identity(address: str, timeout: float) -> Any:
    from distributed.comm import connect

    comm = await connect(address, timeout=timeout)  # its handshake has no bound of its own: wait_for gives one
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


def probe_scheduler(address: str, timeout: float = SCHEDULER_TIMEOUT_S) -> None:
    """``LinkFailure`` unless a Dask scheduler answers at ``address`` who it
    is within ``timeout`` seconds of wall-clock time: a mute peer, a closed
    port and a server of another protocol (whatever its bytes make the
    decoder do) are told apart from a scheduler before a client connects."""
    def run() -> Any:
        return asyncio.run(asyncio.wait_for(_identity(address, timeout), timeout))

    try:
        reply = run()
    except (asyncio.TimeoutError, TimeoutError):
        raise LinkFailure(f"--scheduler {address}: no answer within {timeout:g} s (a Dask scheduler answers at "
                          "once): is it the scheduler's address?") from None
    except OSError as exc:
        raise LinkFailure(f"--scheduler {address}: cannot connect: {exc.strerror or exc}") from None
    except Exception as exc:  # noqa: BLE001 - whatever a foreign server's bytes make the decoder raise
        raise LinkFailure(f"--scheduler {address}: not a Dask scheduler (its reply cannot be read: "
                          f"{type(exc).__name__})") from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise LinkFailure(f"--scheduler {address}: not a Dask scheduler (it says it is "
                          f"{reply.get('type') if isinstance(reply, dict) else 'nothing Dask knows'})")


def dask_client(scheduler: Any) -> tuple[Any, bool]:
    """(client, owned): a ``distributed.Client`` given, or one connected to
    ``tcp://HOST:PORT`` once :func:`probe_scheduler` has heard it is one."""
    if not isinstance(scheduler, str):
        return scheduler, False
    try:
        from distributed import Client
    except ImportError:
        raise DependencyMissing("--scheduler needs dask.distributed: pip install 'mrctl[sweep]'") from None
    check_scheduler_address(scheduler)
    if not scheduler.startswith("inproc://"):  # a scheduler in this process: nothing foreign to ask
        probe_scheduler(scheduler)
    try:
        return Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT_S:g}s"), True
    except Exception as exc:  # noqa: BLE001 - it answered a moment ago: whatever fails now is the link
        raise LinkFailure(f"--scheduler {scheduler}: cannot connect: {type(exc).__name__}: {exc}") from None


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

    The scheduler is asked first, then the table locked and checked; points
    are built as they are handed out. Raises :class:`SweepInterrupted` on
    Ctrl-C, after the table is closed valid."""
    table = ResultsTable(Path(out), columns(sweep.axes, sweep.metrics))
    client, owned = dask_client(scheduler) if scheduler is not None else (None, False)
    try:
        done = table.open()
    except BaseException:
        if owned:
            client.close()
        raise
    counts = {"ok": 0, "fault": 0, "invalid": 0, "error": 0, "skipped": 0}
    total = sweep.size()
    rows = None
    complete = False
    bar = make_bar(total, "sweep", progress, unit="pt", every_s=5.0)
    values: dict[int, dict[str, Any]] = {}  # the values of the points in flight

    def tasks() -> Iterator[dict[str, Any]]:
        for p in sweep.points():
            if p.hash in done:  # in the table already, or a point with the same config earlier in this run
                counts["skipped"] += 1
                bar.update()
                continue
            done.add(p.hash)
            if isinstance(p, Unresolved):  # values that cannot be applied: a failed row at once
                table.add({"point": p.index, "config_hash": p.hash, **p.values, "status": "invalid",
                           "error": p.error, "mrctl_version": "", "build": ""})
                counts["invalid"] += 1
                bar.update()
                continue
            values[p.index] = {**p.values, "seed": p.seed}
            yield p.task(sweep.metrics)

    try:
        n_workers = workers if workers is not None else (os.cpu_count() or 1)
        if client is not None:
            n_workers = max(1, sum(client.nthreads().values()))
        size = batch_size(max(0, total - table.count), n_workers)
        rows = run_dask(tasks(), client, size) if client is not None else run_local(tasks(), n_workers, size)
        for row in rows:
            table.add({**row, **values.pop(row["point"])})
            counts[row["status"]] += 1
            bar.update()
        complete = True
    except KeyboardInterrupt:
        raise SweepInterrupted(f"interrupted: {table.count} of {total} points in {out}; "
                               f"run the same command again to resume") from None
    finally:
        if rows is not None and hasattr(rows, "close"):
            rows.close()
        bar.close()
        table.close(complete)
        if owned:
            client.close()
    return counts
