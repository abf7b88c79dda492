"""The emulated T7's I/O and watchdog, as LabJack documents them (docs/hil_sim.md, docs/hardware.md).

* **Power-up** (and every emulated restart): inputs at their defaults (range 0 = +/-10 V,
  resolution index 0, single-ended: NEGATIVE_CH 199, settling 0 = auto), both DACs at 0 V, every
  DIO an input (``labjack/ljm_constants``: ``DIO#`` "also configures the direction"; a T-series
  input has a pull-up to 3.3 V, so an unwired input reads 1 and a line wired to a pull-down 0).
* **DIO**: reading ``DIO#`` makes the line an input and returns its level, writing it makes it an
  output at that level; ``DIO_STATE`` reads every level without touching direction, and its writes
  (and ``DIO_DIRECTION``'s) skip the bits set in ``DIO_INHIBIT``.
* **Watchdog** (datasheet 23.0; the ``WATCHDOG_*_DEFAULT`` registers live in "flash", kept across
  restarts, every accepted write counted in ``flash_writes``): the timer is cleared by any request,
  or in strict mode only by the key written to ``WATCHDOG_STRICT_CLEAR``. When it expires the
  enabled actions happen: DACs to their values, the DIO lines not inhibited to their direction and
  state, the advanced IO-config reset, and with reset enabled a device restart (power-up state,
  every TCP connection dropped, ``CORE_TIMER`` from 0). Without reset the timer starts again and
  the actions repeat at every further expiry. The first period after a boot is
  ``WATCHDOG_STARTUP_DELAY_S_DEFAULT`` when it is not 0 (what 0 means is not documented: the
  emulator then uses the timeout). LabJack publishes no resolution for the timer: the emulator
  trips exactly at the timeout, which a real T7 need not (measure it: docs/hardware.md, First run).
"""

from __future__ import annotations

from typing import Any, Callable

__all__ = ["T7Io", "SINGLE_ENDED"]

SINGLE_ENDED = 199


class T7Io:
    """Volatile I/O state, flash-kept watchdog settings, and the watchdog's timer."""

    def __init__(self, n_ain: int, n_dac: int, n_dio: int, wd_regs: dict[str, Any], clock_ns: Callable[[], int],
                 pulled_down: set[int]) -> None:
        self.n_ain, self.n_dac, self.n_dio = n_ain, n_dac, n_dio
        self.clock_ns = clock_ns
        self.pulled_down = pulled_down  #: inputs wired to a pull-down (read 0 when nothing drives them)
        self.flash: dict[str, Any] = {k: (0.0 if v["type"] == "float32" else 0) for k, v in wd_regs.items()}
        self.flash_writes = 0
        self.restarts = 0
        self.watchdog_trips: list[int] = []
        self.on_dio_change: Callable[[int, int, int], None] = lambda n, old, new: None
        self.external: Callable[[int], int | None] = lambda n: None  #: a level driven from outside, or None
        self.power_up()

    def power_up(self) -> None:
        """The power-up state (a restart keeps the flash)."""
        old = [self.level(n) for n in range(self.n_dio)] if hasattr(self, "dio_dir") else None
        self.ain_range = [0.0] * self.n_ain
        self.ain_res = [0] * self.n_ain
        self.ain_neg = [SINGLE_ENDED] * self.n_ain
        self.ain_settle = [0.0] * self.n_ain
        self.dac_V = [0.0] * self.n_dac
        self.dio_dir = [0] * self.n_dio
        self.dio_out = [0] * self.n_dio
        self.dio_inhibit = 0
        now = self.clock_ns()
        self.boot_ns = now
        self.last_clear_ns = now
        self.cleared_since_boot = False
        if old is not None:
            for n in range(self.n_dio):
                self._changed(n, old[n])

    # -- digital I/O --------------------------------------------------------------------------
    def level(self, n: int) -> int:
        if self.dio_dir[n]:
            return self.dio_out[n]
        ext = self.external(n)
        if ext is not None:
            return ext
        return 0 if n in self.pulled_down else 1  # the input's pull-up, unless wired to a pull-down

    def _changed(self, n: int, old: int) -> None:
        new = self.level(n)
        if new != old:
            self.on_dio_change(n, old, new)

    def read_dio(self, n: int) -> int:
        """``DIO#`` read: the line becomes an input."""
        old = self.level(n)
        self.dio_dir[n] = 0
        self._changed(n, old)
        return self.level(n)

    def write_dio(self, n: int, v: int) -> None:
        """``DIO#`` write: the line becomes an output at ``v``."""
        old = self.level(n)
        self.dio_dir[n], self.dio_out[n] = 1, v
        self._changed(n, old)

    def state_bits(self) -> int:
        return sum(self.level(n) << n for n in range(self.n_dio))

    def direction_bits(self) -> int:
        return sum(self.dio_dir[n] << n for n in range(self.n_dio))

    def write_state_bits(self, bits: int, direction: bool, inhibit: int | None = None) -> None:
        """``DIO_STATE`` (outputs' levels) or ``DIO_DIRECTION`` writes, bits in the inhibit mask skipped."""
        inh = self.dio_inhibit if inhibit is None else inhibit
        for n in range(self.n_dio):
            if inh >> n & 1:
                continue
            old = self.level(n)
            if direction:
                self.dio_dir[n] = bits >> n & 1
            else:
                self.dio_out[n] = bits >> n & 1
            self._changed(n, old)

    # -- the watchdog -------------------------------------------------------------------------
    def clear(self) -> None:
        self.last_clear_ns = self.clock_ns()
        self.cleared_since_boot = True

    def request(self, strict_key_written: int | None) -> None:
        """A command-response packet arrived (``strict_key_written``: the value written to
        WATCHDOG_STRICT_CLEAR in it, if any): clears the timer as the mode says."""
        f = self.flash
        if not f["strict_enable"]:
            self.clear()
        elif strict_key_written is not None and strict_key_written == f["strict_key"]:
            self.clear()

    def check(self) -> bool:
        """Run the timer; True when the watchdog acted."""
        f = self.flash
        if not f["enable"]:
            return False
        period_s = f["startup_delay_s"] if (not self.cleared_since_boot and f["startup_delay_s"]) else f["timeout_s"]
        if period_s <= 0:
            return False
        now = self.clock_ns()
        if now - self.last_clear_ns < period_s * 1_000_000_000:
            return False
        self.watchdog_trips.append(now)
        self.last_clear_ns = now
        self.cleared_since_boot = True  # the first timeout ends the start-up period too
        if f["reset_enable"]:
            self.restarts += 1
            self.power_up()
            return True
        if f["advanced"] & 3:  # IO config set to factory / to default: the power-up I/O, no restart
            keep = (self.boot_ns, self.last_clear_ns, self.cleared_since_boot)
            self.power_up()
            self.boot_ns, self.last_clear_ns, self.cleared_since_boot = keep
        for n in range(self.n_dac):
            if f.get(f"dac{n}_enable"):
                self.dac_V[n] = max(0.0, min(5.0, float(f[f"dac{n}_value"])))
        if f["dio_enable"]:
            inh = int(f["dio_inhibit"])
            self.write_state_bits(int(f["dio_direction"]), True, inh)
            self.write_state_bits(int(f["dio_state"]), False, inh)
        return True
