"""Fail-safe rules. The safe state of an MR damper is 0 A.

Whatever a law computes, the driver only ever sees a finite current in
[0, I_max]; NaN and negative values become 0 A.

:class:`SafetySupervisor` adds the per-tick rules on top of the clamp:

* every DAQ sample is checked (missing, late, stale, non-finite, out of range,
  device status); a bad sample is *held over* — the law keeps using the last
  good sample — for at most ``hold_ticks`` consecutive bad ticks, because one
  dropped or corrupt frame at 1 kHz should not stop an experiment;
* the next bad tick after that enters FAULT: the output is 0 A immediately
  (not slew-limited — safety wins over smoothness) until the supervisor
  resumes by itself (``auto_resume``) or ``reset()`` is called;
* some faults **latch**: they wait for an explicit re-arm (:meth:`request_arm`,
  ``mrctl arm``) whatever ``auto_resume`` says: a sample whose device status
  has a latching bit (``latch_status_mask``: the E-stop input open, the
  device's watchdog tripped) latches at once, with no hold; a run of bad
  samples with missing ones (no reply: a link loss) longer than
  ``latch_after_ticks`` latches; without
  ``auto_resume`` every fault does. A re-arm takes only on a good sample
  without those bits, within ``arm_wait_ticks``, else it is refused naming
  the cause;
* commanded currents are clamped and slew-limited relative to the last
  current the supervisor let through, so the first tick, a resume and a
  re-arm ramp up from 0 A.

Pure logic: no I/O, logging or clock reads. The loop passes in everything
(the sample, its age) so the rules are deterministic and unit-testable, and
the per-tick methods touch only plain ints/floats (no containers, strings or
exceptions on the good path).

Per-tick protocol (once per tick, in this order)::

    ok = sup.check(k, seq, x, v, F, status, I_applied, age_s)   # or check_missing(k)
    I = law(sup.x, sup.v, ...) if ok else 0.0
    driver.command(sup.limit(I))                   # 0.0 whenever ok is False

It is part of the compiled core (mrctl/build.py): plain ints and floats,
no enum or object on the per-tick path.
"""

from __future__ import annotations

import math
from typing import Any, Final, Protocol

from mrctl.core.safety_config import Fault, SafetyConfig, SafetyCounters, SafetyState, _range
from mrctl.io.base import Status
from mrctl.laws.base import clamp_current

__all__ = [
    "clamp_current",
    "SafetyConfig",
    "SafetyState",
    "Fault",
    "SafetyCounters",
    "SafetySupervisor",
    "SampleLike",
]

_INF: Final = math.inf
_U32: Final = 1 << 32
_U32_HALF: Final = 1 << 31



class SampleLike(Protocol):
    """What the supervisor reads from a sample (``mrctl.io.base.Sample`` fits).

    Duck-typed so tests and the simulator can pass any object with these
    attributes. ``status`` is optional (read only when ``status_fault_mask``
    is set).
    """

    @property
    def seq(self) -> int: ...
    @property
    def x_m(self) -> float: ...
    @property
    def v_mps(self) -> float: ...
    @property
    def F_N(self) -> float: ...


_KIND_LABELS = (
    (Fault.MISSING, "missing"),
    (Fault.LATE, "late"),
    (Fault.STALE, "stale"),
    (Fault.NON_FINITE, "non-finite"),
    (Fault.OUT_OF_RANGE, "out of range"),
    (Fault.DEVICE_STATUS, "device status"),
    (Fault.ESTOP, "E-stop"),
    (Fault.DEVICE_WATCHDOG, "device watchdog"),
)

#: arm_state: what the last re-arm request came to (read by the status thread)
ARM_NONE: Final = 0
ARM_PENDING: Final = 1
ARM_DONE: Final = 2
ARM_REFUSED: Final = 3

_MISSING: Final = int(Fault.MISSING)
_LATE: Final = int(Fault.LATE)
_STALE: Final = int(Fault.STALE)
_NON_FINITE: Final = int(Fault.NON_FINITE)
_OUT_OF_RANGE: Final = int(Fault.OUT_OF_RANGE)
_DEVICE_STATUS: Final = int(Fault.DEVICE_STATUS)
_DRIVER: Final = int(Fault.DRIVER)
_LAW: Final = int(Fault.LAW)
_ESTOP: Final = int(Fault.ESTOP)
_DEV_WD: Final = int(Fault.DEVICE_WATCHDOG)
_LATCHED: Final = int(Fault.LATCHED)
_LATCH_KINDS: Final = _ESTOP | _DEV_WD
_ST_ESTOP: Final = int(Status.ESTOP)

# plain ints on the per-tick path (an IntEnum compares as an object); ``state`` gives the enum
_STARTING: Final = int(SafetyState.STARTING)
_OK: Final = int(SafetyState.OK)
_HOLDING: Final = int(SafetyState.HOLDING)
_FAULT: Final = int(SafetyState.FAULT)


class SafetySupervisor:
    """Per-tick safety rules: sample checks with hold-over, FAULT → 0 A, clamp + slew.

    Call :meth:`check` (or :meth:`check_missing`) then :meth:`limit` once per
    tick (see the module docstring). After a ``True`` from :meth:`check`, the
    sample the law runs on (this one, or the last good one held over) is in
    ``x``, ``v``, ``F``, ``I_applied`` and ``status``: plain fields, so a tick
    builds no object. Status (``state``, ``fault``, ``reason``,
    ``counters()``) may be read between ticks from the loop thread; it is not
    locked.
    """

    __slots__ = (
        "config",
        # precomputed config
        "_I_max", "_step", "_hold", "_max_age", "_xlo", "_xhi", "_vlo", "_vhi",
        "_Flo", "_Fhi", "_req_F", "_status_mask", "_auto", "_resume_n", "_latch_mask", "_latch_after",
        "_arm_wait",
        # state, and the sample the law runs on
        "_state", "_have_good", "_have_seq", "_last_seq", "_bad_run", "_bad_bits", "_good_run",
        "_fault", "_latched", "_reason", "_last_fault", "_last_reason", "_out_ok", "_last_out", "_law_reason",
        "_k", "_fault_tick", "_held", "x", "v", "F", "I_applied", "status",
        # re-arm (mrctl arm): the request's deadline tick, and what it came to
        "_arm_until", "arm_state", "arm_message",
        # counters
        "_n_good", "_n_missing", "_n_late", "_n_stale", "_n_non_finite",
        "_n_out_of_range", "_n_status", "_n_holds", "_longest_bad",
        "_n_faults", "_n_fault_ticks", "_n_resumes", "_n_resets", "_n_cmd_nonfinite",
        "_n_estop", "_n_dev_wd", "_n_latches", "_n_latched_ticks", "_n_arms", "_n_arms_refused",
    )

    def __init__(self, config: SafetyConfig) -> None:
        self.config = config
        self._I_max = float(config.I_max)
        slew = config.max_slew_A_per_s
        # inf step == no slew limit, so limit() has a single code path
        self._step = math.inf if slew is None else float(slew) * float(config.dt_s)
        self._hold: int = config.hold_ticks
        self._max_age = math.inf if config.max_age_s is None else float(config.max_age_s)
        self._xlo, self._xhi = _range(config.x_range_m, "x_range_m")
        self._vlo, self._vhi = _range(config.v_range_mps, "v_range_mps")
        self._Flo, self._Fhi = _range(config.F_range_N, "F_range_N")
        self._req_F = bool(config.require_force)
        self._status_mask = int(config.status_fault_mask)
        self._auto = bool(config.auto_resume)
        self._resume_n: int = config.resume_good_ticks
        self._latch_mask = int(config.latch_status_mask)
        self._latch_after: int = -1 if config.latch_after_ticks is None else config.latch_after_ticks
        self._arm_wait: int = config.arm_wait_ticks
        self._n_good = self._n_missing = self._n_late = self._n_stale = 0
        self._n_non_finite = self._n_out_of_range = self._n_status = 0
        self._n_holds = self._longest_bad = self._n_faults = self._n_fault_ticks = 0
        self._n_resumes = self._n_resets = self._n_cmd_nonfinite = 0
        self._n_estop = self._n_dev_wd = self._n_latches = self._n_latched_ticks = 0
        self._n_arms = self._n_arms_refused = 0
        self._arm_until = -1
        self.arm_state = ARM_NONE
        self.arm_message = ""
        self._last_fault = 0  # the last fault and its reason, kept after it clears (for reports)
        self._last_reason = ""
        self._k = -1  # the tick being checked (the fault's tick in every message)
        self._fault_tick = -1
        self._held: Any = None  # check_sample's object API: the last good sample object
        #: the sample the law runs on (valid after check() returned True)
        self.x = self.v = self.F = self.I_applied = math.nan
        self.status = 0
        self._arm()

    def _arm(self) -> None:
        """Back to STARTING: no fault, no reference sample, 0 A output."""
        self._state = _STARTING
        self._have_good = False
        # forget the sequence reference too: a reconnected DAQ may restart its
        # counter, which would otherwise look stale (backwards) forever
        self._have_seq = False
        self._last_seq = 0
        self._bad_run = 0
        self._bad_bits = 0
        self._good_run = 0
        self._fault = 0
        self._latched = False
        self._reason = ""
        self._law_reason = ""
        self._out_ok = False
        self._last_out = 0.0
        self._arm_until = -1

    # ------------------------------------------------------------------ per tick

    def _classify(self, seq: int, x: float, v: float, F: float, status: int, age_s: float) -> int:
        """0 if good, else the first bad kind found (one kind per sample);
        a latching status bit comes first: it says what the device did."""
        if status & self._latch_mask:
            return _ESTOP if status & _ST_ESTOP else _DEV_WD
        if not age_s <= self._max_age:  # NaN age counts as late
            return _LATE
        if self._have_seq:
            d = (seq - self._last_seq) % _U32
            if d == 0 or d >= _U32_HALF:
                return _STALE
        if not (-_INF < x < _INF and -_INF < v < _INF):
            return _NON_FINITE
        F_ok = -_INF < F < _INF
        if not F_ok and (self._req_F or F == F):  # inf always bad; NaN only if required
            return _NON_FINITE
        if not (self._xlo <= x <= self._xhi and self._vlo <= v <= self._vhi):
            return _OUT_OF_RANGE
        if F_ok and not self._Flo <= F <= self._Fhi:
            return _OUT_OF_RANGE
        if status & self._status_mask:
            return _DEVICE_STATUS
        return 0

    def check(self, k: int, seq: int, x: float, v: float, F: float, status: int, I_applied: float,
              age_s: float = 0.0) -> bool:
        """Check tick ``k``'s sample (its fields); True: the law runs on
        ``self.x`` … ``self.status`` (this sample, or the last good one
        during a hold); False: FAULT or no good sample yet, the loop skips
        the law and :meth:`limit` outputs 0 A. ``age_s`` is the sample's
        measured age (ignored unless ``max_age_s`` is set)."""
        self._k = k
        kind = self._classify(seq, x, v, F, status, age_s)
        if kind == 0:
            self._n_good += 1
            self._have_good = True
            self.x, self.v, self.F, self.I_applied, self.status = x, v, F, I_applied, status
            self._have_seq = True
            self._last_seq = seq
            self._bad_run = 0
            self._bad_bits = 0
            if self._state == _FAULT:
                self._good_run += 1
                if self._latched:
                    if not 0 <= k <= self._arm_until:  # no re-arm asked for (or too late): stay at 0 A
                        self._fault_ticked()
                        return False
                    self._rearm()
                elif self._good_run < self._resume_n:
                    self._fault_ticked()
                    return False
                else:
                    self._resume()
            self._state = _OK
            self._out_ok = True
            return True
        return self._bad(kind)

    def check_missing(self, k: int) -> bool:
        """No sample this tick (read timeout, link error): as :meth:`check`."""
        self._k = k
        return self._bad(_MISSING)

    def _bad(self, kind: int) -> bool:
        self._count_bad(kind)
        self._bad_run += 1
        self._bad_bits |= kind
        if self._bad_run > self._longest_bad:
            self._longest_bad = self._bad_run
        if kind != _STALE or self._state != _FAULT:
            # A repeated sequence number while recovering is no evidence either
            # way: an exchange link polls faster than the device publishes now
            # and then (~7 % of ticks on the HIL bench). It must not restart
            # the count of good samples (recovery took 655 ticks that way); a
            # frozen seq still never resumes, since no fresh sample arrives.
            self._good_run = 0
        self._out_ok = False

        if kind & _LATCH_KINDS:  # the E-stop, the device's watchdog: 0 A at once, latched, no hold
            if not (self._latched and self._fault & kind):
                self._enter_fault(kind, True)
            self._fault_ticked()
            return False
        lost = 0 < self._latch_after < self._bad_run and self._bad_bits & _MISSING != 0  # a link loss, that long
        if self._state == _FAULT:
            if lost and not self._latched:
                self._enter_fault(self._bad_bits, True)
            self._fault_ticked()
            return False
        if self._bad_run > self._hold:
            self._enter_fault(self._bad_bits, lost)
            self._fault_ticked()
            return False
        self._n_holds += 1
        if not self._have_good:  # nothing to hold yet (STARTING): 0 A, not yet a fault
            return False
        self._state = _HOLDING
        self._out_ok = True
        return True

    def check_sample(self, sample: Any, age_s: float = 0.0, k: int = -1) -> Any:
        """The object form of :meth:`check`: returns the sample the law should
        use (``sample`` itself, or the last good sample during a hold), or
        None. ``sample`` is None when the read failed; any object with
        ``seq``, ``x_m``, ``v_mps``, ``F_N`` (and optionally ``status``,
        ``current_A``) fits (tests, tools)."""
        if sample is None:
            return self._held if self.check_missing(k) else None
        ok = self.check(k, sample.seq, sample.x_m, sample.v_mps, sample.F_N, getattr(sample, "status", 0),
                        getattr(sample, "current_A", math.nan), age_s)
        if self._bad_run == 0:  # a good sample (also one that does not yet end a FAULT)
            self._held = sample
        return self._held if ok else None

    def _count_bad(self, kind: int) -> None:
        """Count a bad sample by its kind (the bad path only)."""
        if kind == _MISSING:
            self._n_missing += 1
        elif kind == _ESTOP:
            self._n_estop += 1
        elif kind == _DEV_WD:
            self._n_dev_wd += 1
        elif kind == _LATE:
            self._n_late += 1
        elif kind == _STALE:
            self._n_stale += 1
        elif kind == _NON_FINITE:
            self._n_non_finite += 1
        elif kind == _OUT_OF_RANGE:
            self._n_out_of_range += 1
        else:
            self._n_status += 1

    def limit(self, I_cmd: float) -> float:
        """The current to command: clamped to [0, I_max] and slew-limited.

        Returns 0.0 (immediately, not slewed) whenever the last
        :meth:`check_sample` returned None. The slew step is relative to the
        previous return value, i.e. the last current actually commanded.
        """
        if not self._out_ok:
            self._last_out = 0.0
            return 0.0
        if not -_INF < I_cmd < _INF:
            self._n_cmd_nonfinite += 1
        I = clamp_current(I_cmd, self._I_max)
        last = self._last_out
        step = self._step
        if I > last + step:
            I = last + step
        elif I < last - step:
            I = last - step
        # last ± step can round 1 ulp outside the range near the limits
        if I > self._I_max:
            I = self._I_max
        elif I < 0.0:
            I = 0.0
        self._last_out = I
        return I

    # ----------------------------------------------------------- state changes

    def _enter_fault(self, bits: int, latch: bool) -> None:
        if self._state != _FAULT:
            self._n_faults += 1
            self._fault_tick = self._k
        self._state = _FAULT
        self._fault |= bits
        was = self._latched
        self._latched = was or latch or not self._auto
        if self._latched and not was:
            self._n_latches += 1
        self._good_run = 0
        self._out_ok = False
        self._last_out = 0.0
        self._reason = self._describe()
        self._last_fault, self._last_reason = self._fault, self._reason

    def _fault_ticked(self) -> None:
        """One more tick at 0 A in FAULT (and latched); an unanswered re-arm
        request runs out here."""
        self._n_fault_ticks += 1
        if self._latched:
            self._n_latched_ticks += 1
            if 0 <= self._arm_until < self._k:
                self._refuse_arm()

    def _resume(self) -> None:
        self._n_resumes += 1
        self._fault = 0
        self._latched = False
        self._good_run = 0
        self._reason = ""

    def _rearm(self) -> None:
        """A re-arm asked for, on a good sample without a latching bit: the
        fault ends; the output ramps up from 0 A at the slew limit."""
        self._n_arms += 1
        self._arm_until = -1
        self.arm_state = ARM_DONE
        self.arm_message = f"re-armed at tick {self._k} (was: {self._reason})"
        self._resume()

    def _refuse_arm(self) -> None:
        self._n_arms_refused += 1
        self._arm_until = -1
        self.arm_state = ARM_REFUSED
        self.arm_message = f"refused: the cause is still there after {self._arm_wait} ticks ({self.cause_now()})"

    def request_arm(self) -> None:
        """``mrctl arm``, taken at a tick boundary: leave a latched fault on
        the next good sample without a latching bit within ``arm_wait_ticks``;
        else refuse (``arm_state``, ``arm_message``). Not latched: nothing to
        do (said in ``arm_message``)."""
        if self._state != _FAULT or not self._latched:
            self.arm_state = ARM_DONE
            self.arm_message = f"nothing to re-arm (state {self.state.name})"
            return
        self._arm_until = self._k + self._arm_wait
        self.arm_state = ARM_PENDING
        self.arm_message = "waiting for a good sample without the cause"

    def cause_now(self) -> str:
        """What keeps a latched fault now: the kinds of the current bad run,
        or "none" once samples are good again (then a re-arm takes)."""
        if self._bad_run == 0:
            return "samples good again"
        parts = [label for bit, label in _KIND_LABELS if self._bad_bits & bit]
        return f"{'/'.join(parts)} for {self._bad_run} tick(s)"

    def _describe(self) -> str:
        parts = [label for bit, label in _KIND_LABELS if self._fault & bit & ~_LATCH_KINDS]
        msgs = []
        if self._fault & _ESTOP:
            msgs.append("E-stop input open")
        if self._fault & _DEV_WD:
            msgs.append("the device's watchdog tripped (it applied its safe state)")
        if self._fault & _DRIVER:
            msgs.append("current driver failed")
        if self._fault & _LAW:
            msgs.append(f"control law failed ({self._law_reason})")
        if parts:
            msgs.append(
                f"{'/'.join(parts)} sample(s) for {self._bad_run} consecutive tick(s)"
                f" (hold_ticks={self._hold})"
            )
        how = "latched until mrctl arm" if self._latched else (
            f"auto-resume after {self._resume_n} good samples")
        return f"{'; '.join(msgs)}; 0 A, {how}"

    def driver_failed(self) -> None:
        """The loop could not command the current driver: FAULT, latched.

        Latched even with ``auto_resume``: good samples say nothing about the
        actuator, so only ``reset()`` (after the link is back) clears it.
        """
        self._enter_fault(_DRIVER, True)

    def law_failed(self, why: str, k: int = -1) -> None:
        """A law raised, returned NaN/inf or overran its budget at tick ``k``:
        FAULT, 0 A, latched (its state can no longer be trusted; docs/laws.md)."""
        if k >= 0:
            self._k = k
        self._law_reason = why
        self._enter_fault(_LAW, True)

    def reset(self) -> None:
        """Clear any fault and re-arm (back to STARTING; counters are kept).

        Output stays 0 A until the next good sample; the sequence-number
        reference is forgotten so a restarted DAQ counter is accepted.
        """
        self._n_resets += 1
        self._arm()

    # ------------------------------------------------------------------ status

    @property
    def state(self) -> SafetyState:
        return SafetyState(self._state)

    @property
    def shown_state(self) -> SafetyState:
        """:attr:`state` as status, the live line and Prometheus show it:
        LATCHED for a FAULT that waits for ``mrctl arm``."""
        if self.latched:
            return SafetyState.LATCHED
        return SafetyState(self._state)

    @property
    def latched(self) -> bool:
        """In a FAULT that waits for a re-arm (``mrctl arm``)."""
        return self._state == _FAULT and self._latched

    @property
    def latch_cause(self) -> str:
        """Why the supervisor is latched, in a word or two ("estop", "device
        watchdog", "link loss", "law", ...); "" when not latched."""
        if not self.latched:
            return ""
        f = self._fault
        if f & _ESTOP:
            return "estop"
        if f & _DEV_WD:
            return "device watchdog"
        if f & _LAW:
            return "law"
        if f & _DRIVER:
            return "driver"
        if f & _MISSING:
            return "link loss"
        return "bad samples"

    @property
    def in_fault(self) -> bool:
        return self._state == _FAULT

    @property
    def last_fault_tick(self) -> int:
        """The tick at which the most recent fault was entered (-1: none yet):
        the one tick number every report of that fault names."""
        return self._fault_tick

    @property
    def fault(self) -> Fault:
        """Fault bits of the current FAULT (NONE when not in FAULT)."""
        return Fault(self._fault)

    @property
    def fault_bits(self) -> int:
        """The same bits as a plain int, with ``LATCHED`` while latched: for
        the per-tick log (building the IntFlag costs ~1 us)."""
        return self._fault | _LATCHED if self._latched else self._fault

    @property
    def last_fault(self) -> Fault:
        """The most recent fault's kinds, also after it cleared (auto-resume)."""
        return Fault(self._last_fault)

    @property
    def last_reason(self) -> str:
        """The most recent fault's reason, also after it cleared."""
        return self._last_reason

    @property
    def reason(self) -> str:
        """Human-readable cause of the current FAULT ("" when not in FAULT)."""
        return self._reason

    @property
    def last_output_A(self) -> float:
        return self._last_out

    def counters(self) -> SafetyCounters:
        return SafetyCounters(
            good=self._n_good,
            missing=self._n_missing,
            late=self._n_late,
            stale=self._n_stale,
            non_finite=self._n_non_finite,
            out_of_range=self._n_out_of_range,
            device_status=self._n_status,
            holds_used=self._n_holds,
            longest_bad_run=self._longest_bad,
            faults_entered=self._n_faults,
            ticks_in_fault=self._n_fault_ticks,
            resumes=self._n_resumes,
            resets=self._n_resets,
            cmd_non_finite=self._n_cmd_nonfinite,
            estop=self._n_estop,
            device_watchdog=self._n_dev_wd,
            latches=self._n_latches,
            ticks_latched=self._n_latched_ticks,
            arms=self._n_arms,
            arms_refused=self._n_arms_refused,
        )
