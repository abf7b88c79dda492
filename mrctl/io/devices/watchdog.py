"""A device preset's watchdog block (the T7's ``WATCHDOG_*_DEFAULT``), armed strict, or disarmed.

What mrctl needs from the T7's watchdog (datasheet 23.0 "Watchdog"; registers and their
fwmin from ``labjack/ljm_constants``; docs/hardware.md):

* **strict mode with a key**: only a write of the key to ``WATCHDOG_STRICT_CLEAR`` clears the
  timer, so a monitoring client polling the T7 (Kipling, an EPICS IOC, mbpoll) no longer keeps
  DAC0 alive after mrctl dies; mrctl writes the key every tick;
* **actions**: DAC0 (or DAC1) to the volts of 0 A, the enable line (if wired) an output, low;
* **no device reset, no IO-config reset, a start-up delay equal to the timeout**: a reboot would
  drop the connection every time the host is quiet for the timeout, and LabJack warns that a short
  timeout with reset can keep a device rebooting; the start-up delay is written explicitly because
  the datasheet does not say what 0 means there.

The block lives in flash ("each write will wear the flash memory"): every register is read, only
the ones that differ are written, the watchdog is disabled first (only if it is enabled: the other
registers refuse writes while it is) and enabled last, and everything is read back.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

from mrctl.io.devices.mbfb import as_stored

__all__ = ["watchdog_plan", "configure_watchdog", "disarm_watchdog", "WatchdogError"]

Read = Callable[[int, str], Any]
Write = Callable[[int, str, Any], None]


class WatchdogError(Exception):
    """A watchdog register did not keep what was written (the caller says where)."""


def _same(dtype: str, got: Any, want: Any) -> bool:
    return bool(got == as_stored(dtype, want))


def watchdog_plan(wd: Mapping[str, Any], timeout_s: int, dac_n: int, dac_volts_0A: float,
                  enable_dio: int | None, n_dio: int) -> dict[str, Any]:
    """Every register of the block but ``enable``, at the value mrctl needs."""
    regs = wd["registers"]
    want: dict[str, Any] = {"timeout_s": int(timeout_s), "startup_delay_s": int(timeout_s), "advanced": 0,
                            "reset_enable": 0, "strict_enable": 1, "strict_key": int(wd["strict_key"])}
    for n in (0, 1):
        if f"dac{n}_enable" in regs:
            want[f"dac{n}_enable"] = 1 if n == dac_n else 0
            want[f"dac{n}_value"] = float(dac_volts_0A) if n == dac_n else 0.0
    if enable_dio is not None:
        bit = 1 << enable_dio
        want.update(dio_enable=1, dio_state=0, dio_direction=bit, dio_inhibit=((1 << n_dio) - 1) & ~bit)
    else:
        want.update(dio_enable=0, dio_state=0, dio_direction=0, dio_inhibit=(1 << n_dio) - 1)
    return {k: v for k, v in want.items() if k in regs}


def configure_watchdog(wd: Mapping[str, Any], want: Mapping[str, Any], read: Read, write: Write
                       ) -> tuple[list[tuple[str, Any]], list[str]]:
    """Arm the block with ``want`` (from :func:`watchdog_plan`); returns (every register as read
    back, the names written). Raises :class:`WatchdogError` when one does not read back."""
    regs = wd["registers"]

    def get(k: str) -> Any:
        return read(int(regs[k]["address"]), regs[k]["type"])

    def put(k: str, v: Any) -> None:
        write(int(regs[k]["address"]), regs[k]["type"], v)
        written.append(k)

    written: list[str] = []
    differs = [k for k, v in want.items() if not _same(regs[k]["type"], get(k), v)]
    enabled = get("enable")
    if differs:
        if enabled != 0:
            put("enable", 0)
        for k in differs:
            put(k, want[k])
    if differs or enabled != 1:
        put("enable", 1)
    report: list[tuple[str, Any]] = []
    for k, v in {**want, "enable": 1}.items():
        got = get(k)
        if not _same(regs[k]["type"], got, v):
            raise WatchdogError(f"watchdog {k} did not keep {v!r} (read back {got!r})")
        report.append((k, got))
    return report, written


def disarm_watchdog(wd: Mapping[str, Any], read: Read, write: Write) -> bool:
    """``WATCHDOG_ENABLE_DEFAULT`` to 0 (only if it is not 0 already), read back; True if it was armed."""
    reg = wd["registers"]["enable"]
    addr, dtype = int(reg["address"]), reg["type"]
    was = read(addr, dtype)
    if was != 0:
        write(addr, dtype, 0)
    got = read(addr, dtype)
    if got != 0:
        raise WatchdogError(f"watchdog enable did not keep 0 (read back {got!r})")
    return was != 0
