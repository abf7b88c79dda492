"""An experiment's DAQ preset keys (``backend.device``, ``backend.channels``
and the device options; mrctl/io/devices/, docs/hardware.md): their schema
fields, and the check that turns them into the device's set-up once the
rest of the file is valid."""

from __future__ import annotations

from typing import Any

from mrctl.util.schema import Custom, Node, Num, Str

__all__ = ["device_fields", "device_checks"]


def device_fields() -> dict[str, Any]:
    """The keys of a device preset (mrctl/io/devices/, docs/hardware.md); checked together in
    :func:`device_checks`, where they become the device's set-up."""
    from mrctl.io.devices import preset_names

    def any_value(value: Any, path: str) -> tuple[Any, list[str]]:
        return value, []

    return {
        "device": Str(default=None, optional=True, choices=preset_names(),
                      doc="a DAQ preset (docs/hardware.md): its register map comes from channels"),
        "channels": Custom(any_value, default=None,
                           doc="device: role -> channel in volts, e.g. x: {ain: 0, m_per_V: 0.0025, offset_V: 2.5}, "
                               "current: {dac: 0, V_per_A: 2.5} (roles: x, v, F, current_monitor, current)"),
        "ain_range_V": Num(default=None, optional=True, doc="device: analog input range (+/- V); null = widest"),
        "ain_resolution_index": Num(default=None, optional=True, integer=True,
                                    doc="device: analog input resolution index; null = the fastest"),
        "device_watchdog_s": Num(default=None, optional=True,
                                 doc="device: its own watchdog (T7: whole seconds) puts the DAC at 0 A; null = 1"),
        "enable_dio": Num(default=None, optional=True, integer=True,
                          doc="device: digital output toggled while running, for the driver's enable "
                              "through a monostable (docs/hardware.md); null = not wired"),
        "enable_toggle_s": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=1.0,
                               doc="device: shortest toggle period of enable_dio (s), at most once a tick; null = 0.002"),
        "ain_settling_us": Num(default=None, optional=True,
                               doc="device: settling time of every input used (µs), set and read back; "
                                   "null = 0 (the device's automatic)"),
        "time_stamps": Str(default=None, optional=True, choices=("device", "host"),
                           doc="device: what time stamps the samples for the velocity observer: device = its "
                               "clock (T7: CORE_TIMER, read in the tick's request) when its firmware has one, "
                               "host = the host's clock when the reply arrives (the device's clock, if read, "
                               "still tells a stale sample); null = device"),
    }


_DEVICE_OPTIONS = ("ain_range_V", "ain_resolution_index", "device_watchdog_s", "enable_dio", "enable_toggle_s",
                   "ain_settling_us", "time_stamps")


def device_checks(cfg: Node, data: dict[str, Any]) -> tuple[Node, list[str]]:
    """A device preset's channels and options, checked with the preset (key
    paths under ``backend``); the backend then carries the set-up in
    ``device`` (and no register map). Also settles ``sensing.velocity``
    (null: observer when there is no velocity register or channel)."""
    backend = cfg.backend
    raw = data.get("backend") if isinstance(data.get("backend"), dict) else {}
    errors: list[str] = []
    if backend is not None and backend.get("device") is not None:
        from mrctl.io.devices import resolve_device

        if "register_map" in raw:
            errors.append("backend.register_map: a device preset builds the register map from backend.channels; "
                          "remove one of the two")
        if raw.get("use_fc23"):
            errors.append(f"backend.use_fc23: a {backend.device} has no FC23 (read/write multiple registers)")
        I_max = cfg.safety.get("I_max") if "safety" in cfg else None
        options = {k: backend.get(k) for k in _DEVICE_OPTIONS}
        estop = cfg.safety.get("estop") if "safety" in cfg else None
        if estop is not None and estop.get("input") is not None:
            from mrctl.config.estop import parse_dio

            options.update(estop_dio=parse_dio(str(estop.input)), estop_input=estop.input,
                           estop_active=estop.get("active"))
        setup, errs = resolve_device(backend.device, backend.channels, options, "backend",
                                     I_max if isinstance(I_max, float) else None)
        errors += errs
        if setup is not None and not errors:
            backend = backend.replace(device=setup, register_map=None, use_fc23=False)
            if "port" not in raw:
                backend = backend.replace(port=setup.preset.port)
            cfg = cfg.replace(backend=backend)
    elif backend is not None:
        for k in ("channels",) + _DEVICE_OPTIONS:
            if raw.get(k) is not None:
                errors.append(f"backend.{k}: only with backend.device (a DAQ preset: {', '.join(_presets())})")
    sensing = cfg.get("sensing")
    if sensing is not None and not errors:
        setup = backend.get("device") if backend is not None else None
        if setup is not None:  # a preset: a velocity channel or none
            no_v = "v" not in setup.channels
        else:
            rmap = backend.get("register_map") if backend is not None else None
            no_v = rmap is not None and not rmap.has("v_mps")
        velocity = sensing.velocity
        if velocity is None:
            velocity = "observer" if no_v else "measured"
            cfg = cfg.replace(sensing=sensing.replace(velocity=velocity))
        elif velocity == "measured" and no_v:
            errors.append("sensing.velocity: 'measured', but the register map has no velocity (v_mps); "
                          "use observer (the default for such a device)")
    return cfg, errors


def _presets() -> tuple[str, ...]:
    from mrctl.io.devices import preset_names

    return preset_names()
