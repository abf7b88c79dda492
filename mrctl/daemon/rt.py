"""Best-effort real-time setup for the control-loop thread.

Why best-effort: the daemon must run on a tuned target (root or
CAP_SYS_NICE/CAP_IPC_LOCK, isolated CPUs) as well as in a container or on a
laptop that refuses some of it. Each requested item is applied on its own and
reported as an :class:`RtResult` — applied, or refused with the reason — and
:func:`apply_rt` never raises for a refusal (a container refusing SCHED_FIFO
is normal, not an error).

Call :func:`apply_rt` **from the loop thread, after start-up** (imports,
config, buffer allocation done): the scheduler policy, CPU affinity and timer
slack are per-thread on Linux, and threads inherit them from their creator,
so start helper threads (status socket, logging) *before* it unless they too
should be SCHED_FIFO. Note the GIL: a SCHED_OTHER helper thread that holds
the GIL still delays the loop thread by up to ``sys.getswitchinterval()``.

Items (each skipped — no result — when left at its "off" default):

* ``fifo_priority``  — ``sched_setscheduler(SCHED_FIFO, prio)``.
* ``lock_memory``    — ``mlockall(MCL_CURRENT | MCL_FUTURE)`` via libc, so the
  loop never takes a page fault on swapped-out memory.
* ``cpus``           — ``sched_setaffinity`` to pin the thread (ideally to an
  isolated CPU).
* ``timer_slack_ns`` — ``prctl(PR_SET_TIMERSLACK)``; the 50 µs default slack
  of SCHED_OTHER threads is added to every sleep (SCHED_FIFO ignores it).
* ``gc_freeze``      — ``gc.freeze()``: moves start-up objects out of the
  collector's reach so a later collection has less to scan.
* ``gc_disable``     — ``gc.disable()`` for the loop's duration: no
  multi-millisecond collection pause inside a tick. Undone by
  :func:`restore`. The loop must not create reference cycles meanwhile.

:func:`restore` (or the :func:`rt_applied` context manager) re-enables the
collector and puts the scheduler policy and affinity back, so end-of-run
reporting does not run at real-time priority. Memory stays locked.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno as _errno
import gc
import os
import resource
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

_MCL_CURRENT = 1
_MCL_FUTURE = 2
_PR_SET_TIMERSLACK = 29
_PR_GET_TIMERSLACK = 30


@dataclass(frozen=True)
class RtSettings:
    """What to request; ``None``/``False`` means "don't touch"."""

    fifo_priority: int | None = None
    lock_memory: bool = False
    cpus: frozenset[int] | None = None
    timer_slack_ns: int | None = None
    gc_freeze: bool = False
    gc_disable: bool = False

    @classmethod
    def from_config(cls, r: Any) -> "RtSettings":
        """From the validated ``rt`` section."""
        return cls(fifo_priority=r.fifo_priority, lock_memory=r.lock_memory, cpus=r.cpus,
                   timer_slack_ns=r.timer_slack_ns, gc_freeze=r.gc_freeze, gc_disable=r.gc_disable)


@dataclass(frozen=True)
class RtResult:
    """Outcome of one requested item: applied, or refused with the reason."""

    name: str
    requested: object
    applied: bool
    detail: str

    def __str__(self) -> str:
        state = "applied" if self.applied else "REFUSED"
        return f"rt {self.name}={self.requested!r}: {state} ({self.detail})"


@dataclass
class _Saved:
    """State to put back in restore(); only what apply_rt changed."""

    thread_id: int | None = None
    sched: tuple[int, int] | None = None  # (policy, priority)
    affinity: set[int] | None = None
    timer_slack_ns: int | None = None
    gc_was_enabled: bool | None = None


_saved = _Saved()


def _os_error(e: OSError) -> str:
    name = _errno.errorcode.get(e.errno or 0, "?")
    return f"{name}: {e.strerror or e}"


def _libc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    except OSError:
        return None


def _apply_fifo(prio: int) -> RtResult:
    name = "sched_fifo"
    if not hasattr(os, "sched_setscheduler"):
        return RtResult(name, prio, False, "os.sched_setscheduler not available here")
    lo = os.sched_get_priority_min(os.SCHED_FIFO)
    hi = os.sched_get_priority_max(os.SCHED_FIFO)
    if not lo <= prio <= hi:
        return RtResult(name, prio, False, f"priority out of range [{lo}, {hi}]")
    try:
        before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except OSError as e:
        why = _os_error(e)
        if e.errno == _errno.EPERM:
            soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
            why += f" (needs CAP_SYS_NICE or RLIMIT_RTPRIO >= {prio}; RLIMIT_RTPRIO={soft})"
        return RtResult(name, prio, False, why)
    if _saved.sched is None:
        _saved.sched = before
    return RtResult(name, prio, True, f"SCHED_FIFO priority {prio} (range {lo}-{hi})")


def _apply_mlock() -> RtResult:
    name = "mlockall"
    libc = _libc()
    if libc is None or not hasattr(libc, "mlockall"):
        return RtResult(name, True, False, "libc mlockall not found")
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        why = f"{_errno.errorcode.get(err, '?')}: {os.strerror(err)}"
        soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
        lim = "unlimited" if soft == resource.RLIM_INFINITY else f"{soft} B"
        why += f" (needs CAP_IPC_LOCK or RLIMIT_MEMLOCK >= process size; RLIMIT_MEMLOCK={lim})"
        return RtResult(name, True, False, why)
    return RtResult(name, True, True, "MCL_CURRENT|MCL_FUTURE")


def _apply_affinity(cpus: frozenset[int]) -> RtResult:
    name = "cpu_affinity"
    req = sorted(cpus)
    if not hasattr(os, "sched_setaffinity"):
        return RtResult(name, req, False, "os.sched_setaffinity not available here")
    if not cpus:
        return RtResult(name, req, False, "empty CPU set")
    try:
        before = os.sched_getaffinity(0)
        os.sched_setaffinity(0, cpus)
    except (OSError, ValueError, OverflowError) as e:
        why = _os_error(e) if isinstance(e, OSError) else str(e)
        try:
            why += f" (allowed CPUs {sorted(os.sched_getaffinity(0))})"
        except OSError:
            pass
        return RtResult(name, req, False, why)
    if _saved.affinity is None:
        _saved.affinity = before
    return RtResult(name, req, True, f"pinned to CPUs {sorted(os.sched_getaffinity(0))}")


def _apply_timer_slack(ns: int) -> RtResult:
    name = "timer_slack_ns"
    libc = _libc()
    if libc is None or not hasattr(libc, "prctl"):
        return RtResult(name, ns, False, "libc prctl not found (Linux only)")
    if ns < 0:
        return RtResult(name, ns, False, "must be >= 0")
    before = libc.prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0)
    if libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(ns), 0, 0, 0) != 0:
        err = ctypes.get_errno()
        return RtResult(name, ns, False, f"{_errno.errorcode.get(err, '?')}: {os.strerror(err)}")
    if _saved.timer_slack_ns is None and before >= 0:
        _saved.timer_slack_ns = before
    # 0 means "reset to the thread's default", so report what is in force.
    now = libc.prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0)
    return RtResult(name, ns, True, f"timer slack now {now} ns (was {before} ns)")


def apply_rt(settings: RtSettings) -> list[RtResult]:
    """Apply each requested item to the calling thread; one result per item.

    Never raises for a refusal or an unexpected error: both become a result
    with ``applied=False`` and the reason in ``detail``.
    """
    s = settings
    steps: list[tuple[str, object, Callable[[], RtResult]]] = []
    if s.cpus is not None:
        cpus = frozenset(s.cpus)
        steps.append(("cpu_affinity", sorted(cpus), lambda: _apply_affinity(cpus)))
    if s.lock_memory:
        steps.append(("mlockall", True, _apply_mlock))
    if s.timer_slack_ns is not None:
        slack = int(s.timer_slack_ns)
        steps.append(("timer_slack_ns", slack, lambda: _apply_timer_slack(slack)))
    if s.gc_freeze:
        steps.append(("gc_freeze", True, _apply_gc_freeze))
    if s.gc_disable:
        steps.append(("gc_disable", True, _apply_gc_disable))
    # Last: once SCHED_FIFO, any slow step above would run at RT priority.
    if s.fifo_priority is not None:
        prio = int(s.fifo_priority)
        steps.append(("sched_fifo", prio, lambda: _apply_fifo(prio)))

    _saved.thread_id = threading.get_ident()
    results: list[RtResult] = []
    for name, requested, fn in steps:
        try:
            results.append(fn())
        except Exception as e:  # noqa: BLE001 - a refusal must never abort start-up
            results.append(RtResult(name, requested, False, f"unexpected {type(e).__name__}: {e}"))
    return results


def _apply_gc_freeze() -> RtResult:
    gc.collect()  # collect start-up garbage first so it is not frozen forever
    gc.freeze()
    return RtResult("gc_freeze", True, True, f"{gc.get_freeze_count()} objects frozen")


def _apply_gc_disable() -> RtResult:
    if _saved.gc_was_enabled is None:
        _saved.gc_was_enabled = gc.isenabled()
    gc.disable()
    return RtResult("gc_disable", True, True, "cyclic GC off until restore()")


def restore() -> list[str]:
    """Undo what :func:`apply_rt` changed (GC, scheduler, affinity, timer slack).

    Call from the same thread that called :func:`apply_rt`. Memory stays
    locked and frozen objects stay frozen. Returns one line per action, for
    the log; never raises.
    """
    done: list[str] = []
    if _saved.thread_id is not None and _saved.thread_id != threading.get_ident():
        done.append("warning: restore() called from a different thread than apply_rt()")
    if _saved.gc_was_enabled is not None:
        if _saved.gc_was_enabled:
            gc.enable()
        done.append(f"gc {'enabled' if gc.isenabled() else 'left disabled'}")
        _saved.gc_was_enabled = None
    if _saved.sched is not None:
        policy, prio = _saved.sched
        try:
            os.sched_setscheduler(0, policy, os.sched_param(prio))
            done.append(f"scheduler policy {policy} priority {prio} restored")
        except OSError as e:
            done.append(f"scheduler not restored: {_os_error(e)}")
        _saved.sched = None
    if _saved.affinity is not None:
        try:
            os.sched_setaffinity(0, _saved.affinity)
            done.append(f"affinity {sorted(_saved.affinity)} restored")
        except OSError as e:
            done.append(f"affinity not restored: {_os_error(e)}")
        _saved.affinity = None
    if _saved.timer_slack_ns is not None:
        libc = _libc()
        if libc is not None:
            libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(_saved.timer_slack_ns), 0, 0, 0)
            done.append(f"timer slack {_saved.timer_slack_ns} ns restored")
        _saved.timer_slack_ns = None
    _saved.thread_id = None
    return done


@contextmanager
def rt_applied(settings: RtSettings) -> Iterator[list[RtResult]]:
    """``with rt_applied(s) as results: loop.run(...)`` — apply, then always restore."""
    results = apply_rt(settings)
    try:
        yield results
    finally:
        restore()
