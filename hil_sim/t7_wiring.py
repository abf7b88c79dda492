"""The bench config's ``labjack_t7`` section (the bench's wiring to the emulated T7,
:mod:`hil_sim.labjack_t7`) and what ``--device labjack_t7`` needs to start."""

from __future__ import annotations

from typing import Any

from mrctl.util.schema import Custom, Num, Section

__all__ = ["t7_fields", "device_errors"]


def _optional_section(fields: dict[str, Any], what: str) -> Custom:
    from mrctl.util.schema import validate_fields

    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if value is None:
            return None, []
        return validate_fields(fields, value, path)

    return Custom(check, default=None, doc=what)


def t7_fields() -> dict[str, Any]:
    """The bench config's ``labjack_t7`` section: the bench's wiring to the emulated T7."""

    def ain(per: str, off: float) -> Section:
        return Section({"ain": Num(integer=True, min=0, max=13, doc="AIN number"),
                        per: Num(doc="physical units per volt"),
                        "offset_V": Num(default=off, doc="volts at zero (what mrctl calibrate finds)"),
                        "negative_ain": Num(default=None, optional=True, integer=True, min=1, max=13,
                                            doc="wired differentially: the AIN carrying the sensor's minus side"),
                        "common_mode_V": Num(default=0.0, doc="differential wiring: volts on both pins "
                                                              "(a single-ended read sees them)")})

    def level(v: Any, path: str) -> tuple[Any, list[str]]:
        return v, [] if v in ("low", "high") else [f"{path}: {v!r} not allowed (low or high)"]

    return {
        "latency_s": Num(default=0.001, min=0.0, max=0.1,
                         doc="command-response overhead per request (s): datasheet A-1, Ethernet, no I/O"),
        "latency_io_extra_s": Num(default=0.0001, min=0.0, max=0.1,
                                  doc="more when the request writes a DAC or DIO (A-1: 1.1 ms against 1.0)"),
        "x": ain("m_per_V", 2.5),
        "F": ain("N_per_V", 0.0),
        "current_monitor": _optional_section({
            "ain": Num(integer=True, min=0, max=13), "A_per_V": Num(), "offset_V": Num(default=0.0)},
            "the driver's current-monitor output on an AIN; null = not wired"),
        "driver": Section({"dac": Num(default=0, integer=True, min=0, max=1, doc="DAC driving the driver"),
                           "A_per_V": Num(default=0.4, min=0.0, min_exclusive=True,
                                          doc="driver gain: 0-5 V in -> 0-2 A out at 0.4")}),
        "enable": _optional_section({
            "dio": Num(integer=True, min=0, max=22, doc="DIO into the monostable"),
            "hold_s": Num(default=0.04, min=0.0, min_exclusive=True, max=1.0,
                          doc="monostable time: the driver stays enabled this long after an edge"),
            "pull_down": Num(default=1, integer=True, min=0, max=1,
                             doc="1: an external pull-down holds the line low while it is an input (at "
                                 "power-up); 0: the T7's pull-up makes it high, and a restart gives an edge")},
            "the driver's enable input through a retriggerable monostable; null = not wired (always enabled)"),
        "estop": _optional_section({
            "dio": Num(integer=True, min=0, max=22, doc="DIO the E-stop contact is wired to"),
            "active": Custom(level, default="low", doc="the level the DIO reads while the E-stop is open")},
            "the E-stop contact on a DIO (hil_sim's --fault estop opens it); null = not wired"),
        "firmware": Num(default=1.0288, min=0.0, doc="FIRMWARE_VERSION the emulated T7 reports"),
        "mbfb": Num(default=1, integer=True, min=0, max=1, doc="1: Modbus Feedback (76) answered; 0: ILLEGAL_FUNCTION"),
        "max_connections": Num(default=2, integer=True, min=1, max=16, doc="TCP clients at once (a T7: 2)"),
        "core_timer": Section({"drift_ppm": Num(default=0.0, doc="CORE_TIMER's rate error (ppm)"),
                               "jitter_s": Num(default=0.0, min=0.0, doc="1-sigma noise of each reading (s)"),
                               "seed": Num(default=0, integer=True)}),
    }


def device_errors(args: Any, cfg: Any) -> list[str]:
    """Why ``python -m hil_sim --device labjack_t7 ...`` cannot start (empty: it can)."""
    errors = []
    if args.transport != "modbus-tcp":
        errors.append(f"--device {args.device}: needs --transport modbus-tcp")
    if args.serve != "inline":
        errors.append(f"--device {args.device}: needs --serve inline (its timers run in the clock's idle loop)")
    if cfg.t7 is None:
        errors.append(f"--device {args.device}: the config has no labjack_t7 section (the bench's wiring)")
    if args.latency_s is not None and not 0 <= args.latency_s <= 0.1:
        errors.append(f"--latency-s: must be 0-0.1 s, got {args.latency_s}")
    return errors
