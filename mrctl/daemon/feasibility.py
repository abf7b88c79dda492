"""Start-up check: can this link sustain the configured control rate?

Two measures, both before the loop starts:

1. **Wire time** from the baud rate and the frame sizes (serial protocol,
   Modbus RTU). Physics, no link needed, so ``mrctl check`` reports it too.
   Example: Modbus RTU at 115200 Bd 8E1 needs ~5.6 ms per tick.
2. **Measured round trips**: ``probe_exchanges`` exchanges at 0 A (the safe
   setpoint), p50/p99 of their duration. This catches what the arithmetic
   cannot: USB-serial latency timers, device turnaround, a slow server.

The tick needs the exchange *and* the compute to fit in one period; we
allow the link 80 % of it. What the link *sustains* decides: the wire time
and the median round trip. If they do not fit, the run is refused, or, with
``link.on_infeasible: reduce_rate``, run at the highest standard rate that
fits, with a clear message either way. A tail (p99) beyond the budget with a
median inside it is a warning, not a refusal: on a shared or non-RT host a
few exchanges are late, and the safety supervisor bridges those with its
hold (and counts them); a short probe's p99 is also little more than its
single worst sample.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from mrctl.io.base import LinkError, LinkTimeout

LINK_SHARE = 0.8
STANDARD_RATES_HZ = (1000.0, 500.0, 250.0, 200.0, 100.0, 50.0, 20.0, 10.0)


@dataclass(frozen=True)
class Feasibility:
    rate_hz: float
    wire_s: float | None
    probe_p50_s: float | None
    probe_p99_s: float | None
    probe_errors: int
    ok: bool
    suggested_rate_hz: float | None
    message: str


def wire_time_s(backend_cfg: Any) -> float | None:
    """Seconds one tick occupies the wire, or None where it is not the limit
    (TCP, sim): asked of the link class that serves the backend (a device
    preset's link answers with its vendor's timing model)."""
    from mrctl.io import link_class_for

    return link_class_for(backend_cfg).wire_time_s(backend_cfg)


def wire_words(backend_cfg: Any) -> tuple[str, str | None]:
    """(what the wire-time estimate is of, the advice for a refused rate) for
    ``backend_cfg``: the link class's own words where it has them."""
    from mrctl.io import link_class_for

    cls = link_class_for(backend_cfg)
    what = getattr(cls, "wire_what", None)
    advice = getattr(cls, "infeasible_advice", None)
    return (what(backend_cfg) if what else f"{backend_cfg.type} at {backend_cfg.get('baudrate')} Bd",
            advice(backend_cfg) if advice else None)


def probe(link: Any, n: int, clock: Callable[[], float] = time.perf_counter,
          timeouts: list[int] | None = None) -> tuple[list[float], int]:
    """n exchanges at 0 A; returns (durations in s of the successful ones,
    error count). ``clock`` (s) is the run's clock (a test's virtual one);
    ``timeouts``, if given, gets the number of failures that were timeouts
    appended (a slow link, not a broken one)."""
    times: list[float] = []
    errors = n_timeouts = 0
    pc = clock
    for _ in range(n):
        t0 = pc()
        try:
            if link.split:
                link.read()
                link.write(0.0)
            else:
                link.exchange(0.0)
        except LinkTimeout:
            errors += 1
            n_timeouts += 1
            continue
        except LinkError:
            errors += 1
            continue
        times.append(pc() - t0)
    if timeouts is not None:
        timeouts.append(n_timeouts)
    return times, errors


#: what to try when a link is refused: said with every refusal
ADVICE = ("try a lower rate_hz, or link.on_infeasible: reduce_rate to let mrctl run at the rate that fits; "
          "check the cable, the port and the baud rate; a longer backend.timeout_s; "
          "a busy host delays replies (stop other jobs)")


def assess(rate_hz: float, wire_s: float | None, rtts: Sequence[float] = (), errors: int = 0,
           what: str = "link", timeouts: int = 0, advice: str | None = None) -> Feasibility:
    """Decide, and say why in one message a lab user can act on.

    ``timeouts``: how many of the ``errors`` were timeouts. Timeouts mean a
    slow link (or host), not a broken one: with too many of them the run is
    refused but a lower rate is suggested (``link.on_infeasible:
    reduce_rate`` takes it); other errors (bad frames, exceptions) say the
    link is unreliable at any rate. ``advice``: the link's own way to a
    faster tick (default: a faster baud rate or Modbus TCP)."""
    budget = LINK_SHARE / rate_hz
    p50 = statistics.median(rtts) if rtts else None
    p99 = sorted(rtts)[min(len(rtts) - 1, int(0.99 * len(rtts)))] if rtts else None
    need = max(x for x in (wire_s, p50, 0.0) if x is not None)
    if rtts == [] and errors:
        return Feasibility(rate_hz, wire_s, None, None, errors, False, None,
                           f"{what}: no reply to any of {errors} probe exchanges; check the cable, address and baud "
                           "rate, and that the device is running and serving")
    parts = []
    if wire_s is not None:
        parts.append(f"{wire_s * 1e3:.2f} ms on the wire" if advice is None else f"{wire_s * 1e3:.2f} ms by the model")
    if p99 is not None:
        parts.append(f"measured round trip p50 {p50 * 1e3:.2f} ms, p99 {p99 * 1e3:.2f} ms")  # type: ignore[operator]
    how = " and ".join(parts) if parts else "no measurement"
    if need <= budget and (not rtts or errors <= len(rtts) // 10):
        tail = ""
        if p99 is not None and p99 > budget:
            tail = ("; warning: the p99 exceeds it, expect some late samples "
                    "(bridged by safety.hold_ticks, counted in the run log)")
        return Feasibility(rate_hz, wire_s, p50, p99, errors, True, None,
                           f"{what}: {how} per tick fits {rate_hz:g} Hz ({budget * 1e3:.2f} ms allowed){tail}")
    if need <= budget:
        lower = [r for r in STANDARD_RATES_HZ if r < rate_hz]
        if timeouts and timeouts >= errors - errors // 10 and lower:
            # a slow link at times: the next standard rate leaves the device and the host more slack per tick
            fits = [r for r in lower if p99 is not None and p99 <= LINK_SHARE / r]
            best = fits[0] if fits else lower[0]
            return Feasibility(rate_hz, wire_s, p50, p99, errors, False, best,
                               f"{what}: {errors} of {errors + len(rtts)} probe exchanges failed "
                               f"({timeouts} timeouts) at {rate_hz:g} Hz; {how}. Suggested rate {best:g} Hz; "
                               + ADVICE)
        return Feasibility(rate_hz, wire_s, p50, p99, errors, False, None,
                           f"{what}: {errors} of {errors + len(rtts)} probe exchanges failed "
                           f"({timeouts} timeouts); the link is unreliable; " + ADVICE)
    fits = [r for r in STANDARD_RATES_HZ if r < rate_hz and need <= LINK_SHARE / r]
    best = fits[0] if fits else None
    msg = (f"{what}: {how} per tick does not fit {rate_hz:g} Hz ({budget * 1e3:.2f} ms allowed for the link). "
           + (f"The highest standard rate that fits is {best:g} Hz (set link.on_infeasible: reduce_rate to run there)"
              if best else "No standard rate down to 10 Hz fits")
           + (advice if advice is not None else "; or use a faster baud rate / Modbus TCP") + ".")
    return Feasibility(rate_hz, wire_s, p50, p99, errors, False, best, msg)


def check_device_pacing(link: Any, period_s: float, n: int = 20) -> str | None:
    """With device pacing on, each of ``n`` back-to-back exchanges at 0 A
    (:func:`probe`) must wait for the device's next tick, about one period.
    A device that ignores the SYNC flag (firmware from before it) answers at
    once, and a loop paced by it would run as fast as the link allows:
    refuse then. Returns why not, or None when it is paced."""
    times, errors = probe(link, n)
    if len(times) < n // 2:
        return f"device pacing: only {n - errors} of {n} exchanges answered during the check"
    med = statistics.median(times)
    if med < 0.5 * period_s:
        return (f"device pacing: exchanges take {med * 1e6:.0f} µs, not one period "
                f"({period_s * 1e6:.0f} µs): the device ignores the SYNC flag; use loop.pacing: host")
    return None
