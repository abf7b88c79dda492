"""A device's latched status, read clean before anything is commanded.

Why its own place: ``mrctl run`` (after the start-up probe, and again just
before the first tick) and ``mrctl calibrate`` (before its current steps)
both ask the device to clear what an earlier run left latched (an E-stop
once its input closed, its watchdog's trip, a driver fault that came and
went) and then judge what is still there. A device clears when it acts on
the request (hil_sim at its next tick, the reference firmware before it
builds the reply), so the status is read until it is clean, asking again
each time, for up to :data:`CLEAR_WAIT_S`. Each read commands 0 A.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from mrctl.io.base import LinkError, Status

__all__ = ["CLEAR_WAIT_S", "Cleared", "cause_of", "read_until_clean", "start_refusal"]

#: how long the status is read, asking the device to clear it, until it is clean (s)
CLEAR_WAIT_S = 0.5


@dataclass(frozen=True)
class Cleared:
    """What :func:`read_until_clean` found."""

    status: int | None  #: the last status read; None: no read answered
    reads: int  #: reads tried
    last_error: str  #: the last read's error, if any
    asked: bool  #: a CLEAR_FAULTS went out (False: the link has no way to ask)


def read_until_clean(link: Any, clear_mask: int, keep_mask: int = 0, wait_s: float = CLEAR_WAIT_S) -> Cleared:
    """Read the status at 0 A until no bit of ``clear_mask`` is set, asking
    the device to clear them after each read that has one; a read with a bit
    of ``keep_mask`` ends it at once, with nothing asked (what must not be
    cleared: an E-stop pressed while a run was being built). A lost reply (a
    busy host) is tried again within ``wait_s``."""
    deadline, n, last, asked = time.monotonic() + wait_s, 0, "", False
    status: int | None = None
    while status is None or status & clear_mask:
        if n and time.monotonic() > deadline:
            break
        n += 1
        try:
            status = int((link.read() if link.split else link.exchange(0.0)).status)
        except LinkError as exc:
            last = str(exc)
            continue
        if status & keep_mask:
            break
        if status & clear_mask:
            asked = bool(link.request_clear_faults()) or asked
            time.sleep(0.005)
    return Cleared(status, n, last, asked)


def cause_of(status: int) -> str:
    """The latched cause a status names, as a sentence's subject: the E-stop
    first (it is the operator's), then the device's watchdog, then the driver."""
    if status & int(Status.ESTOP):
        return "the E-stop input is open"
    if status & int(Status.WATCHDOG_TRIPPED):
        return "the device's watchdog tripped"
    if status & int(Status.DRIVER_FAULT):
        return "the device reports a driver fault (DRIVER_FAULT: a T7 when DAC0 reads back as another writer left it)"
    return f"the device's status is {status:#x}"


def start_refusal(found: Cleared, clear_mask: int, before: str, where: str = "") -> str | None:
    """Why nothing may start on what :func:`read_until_clean` found (None: it
    may): no read answered (``before`` what: "the first tick"); the E-stop
    still open (``where`` names its input); a bit of ``clear_mask`` that did
    not clear, or that this link cannot ask the device to clear."""
    status, n = found.status, found.reads
    if status is None:
        return f"cannot read the device before {before} ({n} attempts): {found.last_error}"
    if status & int(Status.ESTOP):
        return f"refusing to start: the E-stop input is open{where}; close it (reset the E-stop) and start again"
    if status & clear_mask:
        how = (f"did not clear on request (CLEAR_FAULTS, {n} attempts in {CLEAR_WAIT_S:g} s)" if found.asked else
               f"this link cannot ask it to clear (no CLEAR_FAULTS; {n} reads in {CLEAR_WAIT_S:g} s)")
        return f"refusing to start: {cause_of(status)} and {how}"
    return None
