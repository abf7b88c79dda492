"""A preset link's tick: its operations in order, and the vendor's model of how long it takes."""

from __future__ import annotations

from mrctl.io.devices import DeviceSetup
from mrctl.io.devices.mbfb import Op

__all__ = ["model_period_s", "tick_ops"]

def model_period_s(setup: DeviceSetup, medium: str = "ethernet", mbfb: bool = True) -> float:
    """One tick's command-response time by the vendor's figures: the overhead of a request with
    I/O (datasheet A-1, table A.1.1) per request, plus each input's sample time at its resolution
    index and its settling (A-3-1). The inputs are read as one block from the lowest to the highest
    in use, so the T7 converts every input in between too."""
    t = setup.preset.data["timing"]
    per_ain = float(t["ain_sample_s"][setup.ain_resolution_index]) + setup.ain_settling_us * 1e-6
    n_req = 1 if mbfb else len(tick_ops(setup))
    return n_req * float(t["overhead_io_s"][medium]) + setup.ain_block[1] * per_ain


#: what a written op carries: the DAC's volts, the enable output's level, the watchdog key
_DAC, _ENABLE, _KEY = 0, 1, 2


def tick_ops(setup: DeviceSetup, core_timer: bool = True) -> list[tuple[Op, int]]:
    """The tick's operations in order, each with what it writes (-1: a read)."""
    p = setup.preset
    dac = p.address("dac", setup.dac.n)
    ops = [(Op(False, dac, "float32"), -1), (Op(True, dac, "float32"), _DAC)]
    if setup.enable_dio is not None:
        ops.append((Op(True, p.address("dio", setup.enable_dio), p.io("dio")["type"]), _ENABLE))
    wd = p.watchdog
    if wd is not None:
        ops.append((Op(True, int(wd["strict_clear"]["address"]), wd["strict_clear"]["type"]), _KEY))
    lo, n = setup.ain_block
    ops.append((Op(False, p.address("ain", lo), p.io("ain")["type"], n), -1))
    if setup.estop_dio is not None:
        ops.append((Op(False, p.address("dio", setup.estop_dio), p.io("dio")["type"]), -1))
    if core_timer and "core_timer" in p.data:
        ops.append((Op(False, int(p.data["core_timer"]["address"]), p.data["core_timer"]["type"]), -1))
    return ops
