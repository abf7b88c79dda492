"""What a preset link does at open before its first tick, each value read back (docs/hardware.md).

* :func:`identify`: the identity registers (a T7's ``PRODUCT_ID`` reads 7) and the firmware
  (``FIRMWARE_VERSION``): older than the watchdog block's fwmin is refused, naming the version
  needed; from ``CORE_TIMER``'s fwmin on, every sample carries the device's time;
* :func:`set_up`: per analog input in use its range, resolution index, negative channel (199 =
  single-ended) and settling; the enable output written low (writing ``DIO#`` makes it an output);
  the E-stop DIO read (reading ``DIO#`` makes it an input, and ``DIO_DIRECTION`` must then say so);
  the strict watchdog block.
"""

from __future__ import annotations

from typing import Any

from mrctl.io.base import DeviceError
from mrctl.io.devices.mbfb import as_stored

__all__ = ["DeviceSetupError", "identify", "set_up"]


class DeviceSetupError(DeviceError):
    """The device did not take (or read back) a set-up value, is not the device the config names,
    or its firmware is too old. Exit 3 at start-up."""

    def __init__(self, message: str) -> None:
        super().__init__(0, message)


def identify(link: Any) -> None:
    """Identity and firmware; refuses (DeviceSetupError) a device that is not the preset's or too old."""
    p = link.setup.preset
    link.setup_report = []
    for name, ident in (p.data.get("identity") or {}).items():
        got = link.read_value(int(ident["address"]), ident["type"])
        if got != ident["value"]:
            raise DeviceSetupError(f"{link._where()}: {name} reads {got!r}, a {p.name} has {ident['value']!r}: "
                                   "not the device the config names")
        link.setup_report.append((name, got))
    fw = p.data.get("firmware")
    if fw is None:
        return
    got = round(float(link.read_value(int(fw["address"]), fw["type"])), 4)  # a FLOAT32 such as 1.0288
    link.firmware = got
    link.setup_report.append(("FIRMWARE_VERSION", got))
    if got < float(fw["min"]):
        raise DeviceSetupError(f"{link._where()}: firmware {got:.4f} is too old: mrctl needs {float(fw['min']):.4f} "
                               "or later (the WATCHDOG_* registers' fwmin in LabJack's ljm_constants); update the "
                               "firmware with LabJack's Kipling")
    link.core_timer = "core_timer" in p.data and got >= float(fw.get("min_core_timer", 0.0))


def _set(link: Any, name: str, address: int, dtype: str, value: Any) -> None:
    link.write_value(address, dtype, value)
    got = link.read_value(address, dtype)
    if got != as_stored(dtype, value):
        raise DeviceSetupError(f"{link._where()}: {name} = {value!r} written, read back {got!r}")
    link.setup_report.append((name, got))


def set_up(link: Any) -> None:
    """Inputs, the enable output, the E-stop input, the watchdog (each read back)."""
    s = link.setup
    p = s.preset
    ain = p.io("ain")
    regs = [("RANGE", ain["range_register"], s.ain_range_V)]
    regs.append(("RESOLUTION_INDEX", ain["resolution_register"], s.ain_resolution_index))
    neg, settle = ain.get("negative_register"), ain.get("settling_register")
    by_n = {c.n: c for c in s.channels.values() if c.kind == "ain"}
    for n in s.ains:
        row = list(regs)
        if neg is not None:
            c = by_n[n]
            row.append(("NEGATIVE_CH", neg, int(neg["single_ended"]) if c.negative is None else c.negative))
        if settle is not None:
            row.append(("SETTLING_US", settle, s.ain_settling_us))
        for what, reg, value in row:
            _set(link, f"AIN{n}_{what}", int(reg["address"]) + int(reg["stride"]) * n, reg["type"], value)
    dio = p.io("dio")
    if s.enable_dio is not None:
        link.write_value(p.address("dio", s.enable_dio), dio["type"], 0)  # output, low: driver off until toggled
        link.setup_report.append((f"DIO{s.enable_dio} (enable)", "output, low"))
    if s.estop_dio is not None:
        level = link.read_value(p.address("dio", s.estop_dio), dio["type"])  # reading DIO# makes it an input
        link.setup_report.append((f"DIO{s.estop_dio} (E-stop)", f"input, reads {level}"))
    dreg = dio.get("direction_register")
    if dreg is not None and (s.enable_dio is not None or s.estop_dio is not None):
        direction = int(link.read_value(int(dreg["address"]), dreg["type"]))
        if s.enable_dio is not None and not direction >> s.enable_dio & 1:
            raise DeviceSetupError(f"{link._where()}: DIO{s.enable_dio} (enable_dio) is not an output after it "
                                   "was written (DIO_DIRECTION)")
        if s.estop_dio is not None and direction >> s.estop_dio & 1:
            raise DeviceSetupError(f"{link._where()}: DIO{s.estop_dio} (the E-stop input) is still an output after "
                                   "it was read (DIO_DIRECTION)")
    link.arm_watchdog()
