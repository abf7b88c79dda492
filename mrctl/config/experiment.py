"""The experiment schema: what an experiment YAML may say, and its cross-checks.

Every name a user can write is validated here with its key path, all
errors at once; :mod:`mrctl.experiment` then turns the validated tree into
live objects. The schema generates ``docs/config.md``'s reference tables
(``python -m mrctl.config``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from mrctl.config.acceptance import acceptance_section
from mrctl.config.bench import bench_fields, road_excitations
from mrctl.config.device import device_checks, device_fields
from mrctl.config.estop import estop_checks, estop_section
from mrctl.config.laws import LAW_GUARD_FIELDS, law_checks, law_unions
from mrctl.config.observe import stream_section
from mrctl.config.params import INPUT_KINDS, input_kind_errors, params_check
from mrctl.config.plants import plant_model_schema
from mrctl.model.params import LuGreParams
from mrctl.util.files import Fence
from mrctl.util.schema import (
    Bool,
    ConfigError,
    Custom,
    Node,
    Num,
    Section,
    Str,
    Union,
    auto_or,
    check_num,
    file_check,
    load_yaml_lines,
    optional_bool,
    quoting,
    range_check,
    schema_markdown as _markdown,
    validate_fields,
)

CONFIG_VERSION = 1
SPIN_WAIT_DOC = ("wait for each reply by polling, busy for one round trip (device pacing: for the last "
                 "loop.spin_margin_s of it), instead of sleeping in select(): a sleeping thread can wake "
                 "up to ~1.5 ms late on a VM")


def _cpu_list(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    if not isinstance(value, list) or not value:
        return None, [f"{path}: must be a non-empty list of CPU numbers or null"]
    cpus, errors = [], []
    for i, c in enumerate(value):
        n, errs = check_num(Num(integer=True, min=0, max=4095), c, f"{path}[{i}]")
        cpus.append(n)
        errors += errs
    return (frozenset(cpus) if not errors else None), errors


def _register_map(value: Any, path: str) -> tuple[Any, list[str]]:
    """The Modbus register map (docs/registers.md); null = the default map."""
    try:
        from mrctl.io.registers import default_register_map
    except ImportError:  # pragma: no cover - the module ships with mrctl
        return None, [f"{path}: Modbus register maps are not available in this build"]
    if value is None:
        return default_register_map(), []
    from mrctl.io.registers import validate_register_map

    rmap, errors = validate_register_map(value, path)
    return rmap, errors


def experiment_schema(base_dir: Path, fence: Fence | None = None) -> dict[str, Any]:
    """The experiment schema; relative file paths resolve against ``base_dir``,
    every file it names (parameters, series, plant constants) admitted by
    ``fence`` (default: under ``base_dir``'s folder; :meth:`Fence.admit`)."""
    fence = fence if fence is not None else Fence.around(base_dir)
    driver_input = Str(default="current", choices=tuple(INPUT_KINDS),
                       doc="what the driver takes: a coil current (A) or a command voltage (V); the parameter "
                           "sets' input (docs/identification.md) must match")
    modbus_common = {
        "input": driver_input,
        "timeout_s": Num(default=0.005, min=0.0, min_exclusive=True, max=1.0, doc="reply timeout (s)"),
        "use_fc23": Custom(optional_bool, default=None, doc="one FC23 transaction per tick; null = probe at start"),
        "register_map": Custom(_register_map, default=None, doc="register map (docs/registers.md); null = default"),
        "open_timeout_s": Num(default=1.0, min=0.0, min_exclusive=True, max=60.0, doc="connect and FC23 probe (s)"),
        "watchdog_ms": Num(default=50, integer=True, min=0, max=65535,
                           doc="device applies 0 A if setpoints stop this long (0 = device default)"),
        "spin_wait": Bool(default=True, doc=SPIN_WAIT_DOC),
    }
    return {
        "version": Num(integer=True, min=CONFIG_VERSION, max=CONFIG_VERSION, doc="config format version (1)"),
        "name": Str(default=None, optional=True, doc="experiment name (logs, file titles)"),
        "description": Str(default=None, optional=True, doc="free text, kept in the run log"),
        "duration_s": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=7 * 86400.0,
                          doc="run length (s); none = until stopped (excitation files: their length)"),
        "rate_hz": Num(default=1000.0, min=1.0, max=20000.0, doc="control rate (Hz)"),
        "parameters": Custom(params_check(base_dir, fence), default="table1",
                             doc="'table1', a parameters YAML path, or {file: ..., <name>: value} overrides"),
        "calibration": Custom(lambda v, path: (v, []), default=None,
                              doc="a CAL.yaml written by mrctl calibrate: channel offsets, noise, driver lag "
                                  "(merged before the rest is checked; docs/hardware.md)"),
        "excitation": Union("type", {
            "sine": {"amplitude_m": Num(min=0.0, max=1.0, doc="displacement amplitude (m)"),
                     "frequency_hz": Num(min=0.0, min_exclusive=True, max=500.0, doc="frequency (Hz)"),
                     "phase_rad": Num(default=0.0, doc="phase at t = 0 (rad)")},
            "chirp": {"amplitude_m": Num(min=0.0, max=1.0, doc="displacement amplitude (m)"),
                      "f0_hz": Num(min=0.0, min_exclusive=True, max=500.0, doc="start frequency (Hz)"),
                      "f1_hz": Num(min=0.0, min_exclusive=True, max=500.0, doc="end frequency (Hz)"),
                      "sweep_s": Num(min=0.0, min_exclusive=True, doc="sweep time (s); f1 is held afterwards")},
            "file": {"path": Custom(file_check(base_dir, fence),
                                    doc="CSV with columns t,x (s, m) and optionally v (m/s); other columns are "
                                        "ignored, so a run log replays (rows with NaN x or v are skipped)"),
                     "settle_s": Num(default=0.0, min=0.0, max=1e6,
                                     doc="start-up transient left out of the tracking figures (s); a replay "
                                         "takes the logged run's, so both are judged over one window")},
            **road_excitations(),
        }, doc="shaker motion on the simulated bench (plant.bench: quarter_car: the road)"),
        **law_unions(base_dir, fence),
        "safety": Section({
            "I_max": Num(min=0.0, min_exclusive=True, max=2.0, doc="current limit (A); RD-1097-01 rating is 1 A"),
            "max_slew_A_per_s": Custom(auto_or(Num(optional=True, min=0.0, min_exclusive=True, max=1e6)),
                                       default="auto",
                                       doc="slew limit of the command (A/s) on every path: the law's output, the "
                                           "first tick, recovery after a fault or a re-arm (a ramp from 0 A); "
                                           "a fault's 0 A is immediate. auto = 50 A/s on a real link (serial, "
                                           "Modbus), off on the in-process sim (the paper's law steps); "
                                           "null = off"),
            "hold_ticks": Num(default=5, integer=True, min=0, max=1000,
                              doc="bad samples bridged with the last good one before 0 A"),
            "max_age_s": Num(default=None, optional=True, min=0.0, min_exclusive=True,
                             doc="a sample whose read took longer is late; none = off"),
            "x_range_m": Custom(range_check, default=None, doc="[lo, hi] valid displacement (m); outside = bad sample"),
            "v_range_mps": Custom(range_check, default=None, doc="[lo, hi] valid velocity (m/s)"),
            "F_range_N": Custom(range_check, default=None, doc="[lo, hi] valid load-cell force (N)"),
            "require_force": Bool(default=False, doc="a non-finite load-cell force is a bad sample"),
            "fault_on_device_status": Bool(default=True, doc="device fault bits make a sample bad"),
            "auto_resume": Bool(default=False, doc="leave the fault by itself after good samples (never an "
                                                   "E-stop, a device watchdog trip or a link loss longer than "
                                                   "latch_after_s on a real link: those wait for mrctl arm)"),
            "latch_after_s": Num(default=0.05, optional=True, min=0.0, min_exclusive=True, max=60.0,
                                 doc="real links: a link loss (no reply) longer than this latches the fault even "
                                     "with auto_resume: 0 A until mrctl arm; null = never"),
            "resume_good_ticks": Num(default=10, integer=True, min=1, max=100000, doc="good samples needed to resume"),
            "driver_retries": Num(default=2, integer=True, min=0, max=10,
                                  doc="extra write attempts within a tick before the driver is lost"),
            "link_loss_s": Num(default=0.1, min=0.0, min_exclusive=True, max=60.0,
                               doc="exchange links: no good exchange for this long = driver lost, exit 3"),
            "reconnect_interval_s": Num(default=0.05, min=0.001, max=60.0,
                                        doc="exchange links: reopen a disconnected link at most this often"),
            **LAW_GUARD_FIELDS,
            "estop": estop_section(),
        }),
        "latency": Section({
            "lead_s": Custom(auto_or(Num(min=0.0, max=0.1)), default=0.0,
                             doc="latency compensation: predict v this far ahead (s); 'auto' = 1.5 ticks on "
                                 "exchange links (serial, Modbus), 0 on the in-process sim. Off by default: "
                                 "not yet shown to help (docs/performance.md)"),
        }, doc="what the controller does about actuation delay (mrctl/estimation.py)"),
        "loop": Section({
            "wait": Str(default="hybrid", choices=("sleep", "hybrid", "spin"), doc="how to wait for the deadline"),
            "spin_margin_s": Num(default=3e-4, min=0.0, max=0.01, doc="hybrid: spin this long before the deadline"),
            "pacing": Str(default="host", choices=("host", "device"),
                          doc="host: the loop keeps its own deadlines; device: each exchange asks the device to "
                              "answer after its next tick (SYNC flag, docs/protocol.md), so the loop runs on the "
                              "device's clock with one tick of actuation latency (serial and Modbus links)"),
        }, doc="pacing of the real-time loop (mrctl run)"),
        "rt": Section({
            "fifo_priority": Num(default=None, optional=True, integer=True, min=1, max=99, doc="SCHED_FIFO priority; null = normal"),
            "lock_memory": Bool(default=False, doc="mlockall (needs LimitMEMLOCK)"),
            "cpus": Custom(_cpu_list, default=None, doc="CPU affinity, e.g. [1]; null = any"),
            "timer_slack_ns": Num(default=None, optional=True, integer=True, min=1, max=10**9, doc="prctl timer slack"),
            "gc_freeze": Bool(default=True, doc="gc.freeze() after start-up"),
            "gc_disable": Bool(default=True, doc="no cyclic GC during the loop"),
        }, doc="real-time settings, each applied or reported refused"),
        "record": Section({
            "flush_interval_s": Num(default=1.0, min=0.05, max=10.0, doc="fsync the log at least this often (s)"),
            "buffer_ticks": Num(default=16384, integer=True, min=256, max=10**7, doc="rows buffered before overflow"),
        }, doc="run log"),
        "service": Section({
            "status_socket": Str(default=None, optional=True, doc="Unix socket for mrctl status"),
        }),
        "sensing": Section({
            "velocity": Str(default=None, optional=True, choices=("measured", "observer"),
                            doc="the velocity the demand and the laws see: the DAQ's velocity channel, or a "
                                "Kalman filter on the displacement (mrctl/estimation/observer.py; for DAQs without "
                                "a velocity channel or with a noisy one); null = measured, or observer for a "
                                "device without a velocity channel"),
            "x_noise_m": Num(default=2e-6, min=0.0, min_exclusive=True, max=0.01,
                             doc="observer: std dev of the displacement reading, noise and quantisation (m)"),
            "jerk_psd": Num(default=1.0, min=0.0, min_exclusive=True, max=1e9,
                            doc="observer: spectral density of the jerk (m^2/s^5); larger = less lag, more noise"),
            "v_noise_mps": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=10.0,
                               doc="observer: also fuse the DAQ's velocity channel, with this std dev (m/s); "
                                   "null = displacement only"),
        }, doc="where the controller's velocity comes from (applied before the safety checks and the laws)"),
        "plant": Section({
            "model": plant_model_schema(base_dir, fence),
            "parameters": Custom(params_check(base_dir, fence), default=None,
                                 doc="the simulated damper's own parameter set (same forms as parameters); "
                                     "null = the law's set. Set it to test a law with identified parameters "
                                     "against a known damper"),
            "driver_tau_s": Num(default=None, optional=True, min=0.0, max=1.0,
                                doc="input lag of the simulated damper's driver (s), 0 = ideal; null = the plant "
                                    "parameter set's tau_input (its tau_field, the field's own lag, follows)"),
            "command_delay_ticks": Custom(auto_or(Num(integer=True, min=0, max=1000)), default=0,
                                         doc="mrctl simulate: ticks from a sample to its current reaching the "
                                             "driver; 'auto' = the backend's: 1 on an exchange link (serial, "
                                             "Modbus, a DAQ preset: the current goes out with the next tick's "
                                             "request), 0 on the in-process sim (mrctl run's sim backend has none)"),
            **bench_fields(),
            "sensors": Section({
                "seed": Num(default=0, integer=True, min=0, doc="noise seed (runs are reproducible)"),
                "x_noise_m": Num(default=0.0, min=0.0, doc="std dev of displacement noise (m)"),
                "v_noise_mps": Num(default=0.0, min=0.0, doc="std dev of velocity noise (m/s)"),
                "F_noise_N": Num(default=0.0, min=0.0, doc="std dev of load-cell noise (N)"),
                "F_offset_N": Num(default=0.0, min=-1e5, max=1e5,
                                  doc="the load cell's zero error (N): an uncalibrated cell reads this at no force"),
                "x_lsb_m": Num(default=0.0, min=0.0, doc="displacement quantisation step (m), 0 = none"),
                "v_lsb_mps": Num(default=0.0, min=0.0, doc="velocity quantisation step (m/s)"),
                "F_lsb_N": Num(default=0.0, min=0.0, doc="force quantisation step (N)"),
                "load_cell": Bool(default=True, doc="false: the force channel reads NaN (a bench without a load cell)"),
                "velocity": Bool(default=True,
                                 doc="false: the velocity channel reads NaN (a DAQ that measures displacement only; "
                                     "needs sensing.velocity: observer)"),
            }),
        }, doc="simulated bench (backend sim)"),
        "backend": Union("type", {
            "sim": {"input": driver_input},
            "serial": {
                "input": driver_input,
                "url": Str(doc="device path, socket://host:port or loop://"),
                "baudrate": Num(default=921600, integer=True, min=1200, max=20_000_000, doc="baud (see docs/protocol.md)"),
                "timeout_s": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=1.0,
                                 doc="reply timeout (s); null = wire time + 250 us"),
                "watchdog_ms": Num(default=50, integer=True, min=1, max=255,
                                   doc="device applies 0 A if setpoints stop this long"),
                "spin_wait": Bool(default=True, doc=SPIN_WAIT_DOC),
            },
            "modbus-tcp": {
                "host": Str(default="127.0.0.1", doc="device address"),
                "port": Num(default=502, integer=True, min=1, max=65535, doc="TCP port"),
                "unit_id": Num(default=1, integer=True, min=0, max=247, doc="Modbus unit id"),
                "gateway": Bool(default=False, doc="the host is a Modbus TCP gateway: each unit id behind it is a "
                                                   "device of its own (else any unit id is the one device at "
                                                   "host:port, for the one-daemon-per-device lock)"),
                **modbus_common,
                **device_fields(),
            },
            "modbus-rtu": {
                "url": Str(doc="serial device path (or any pyserial URL)"),
                "baudrate": Num(default=921600, integer=True, min=1200, max=20_000_000, doc="baud"),
                "parity": Str(default="E", choices=("E", "O", "N"), doc="RTU standard: E (8E1); N needs stopbits 2"),
                "stopbits": Num(default=1, min=1, max=2, doc="stop bits"),
                "rtu_local_echo": Bool(default=False, doc="an RS-485 adapter echoes our requests: read and drop them"),
                "unit_id": Num(default=1, integer=True, min=1, max=247, doc="Modbus unit id (RTU: 1-247)"),
                **modbus_common,
            },
        }, default="sim", doc="where samples come from and currents go"),
        "link": Section({
            "on_infeasible": Str(default="refuse", choices=("refuse", "reduce_rate"),
                                 doc="if the link cannot sustain rate_hz: refuse, or run slower"),
            "probe_exchanges": Num(default=50, integer=True, min=0, max=10000,
                                   doc="round trips measured at start-up (0 = wire-time estimate only)"),
        }, doc="start-up feasibility check of real links"),
        "acceptance": acceptance_section(),
        # -- observability (docs/observe.md): kept together, in mrctl/config/observe.py --
        "stream": stream_section(),
    }


def _cross_checks(cfg: Node, base_dir: Path) -> list[str]:
    """Rules that span keys (each still names the key to fix)."""
    errors: list[str] = []
    I_max = cfg.safety.get("I_max") if "safety" in cfg else None
    params = cfg.get("parameters")
    if isinstance(params, LuGreParams) and isinstance(I_max, float):
        errors += [f"parameters: {e}" for e in params.check_range(I_max)]
    plant_params = cfg.plant.get("parameters") if "plant" in cfg else None
    if isinstance(plant_params, LuGreParams) and isinstance(I_max, float):
        errors += [f"plant.parameters: {e}" for e in plant_params.check_range(I_max)]
    errors += _plant_checks(cfg, I_max)
    errors += estop_checks(cfg)
    errors += law_checks(cfg, base_dir)
    loop, backend = cfg.get("loop"), cfg.get("backend")
    if loop is not None and loop.get("pacing") == "device" and backend is not None and backend.get("type") == "sim":
        errors.append("loop.pacing: 'device' needs a device with its own clock (a serial or Modbus backend); "
                      "the in-process sim bench is ticked by the loop itself")
    exc = cfg.get("excitation")
    if exc is not None and exc.get("type") == "chirp":
        f0, f1 = exc.get("f0_hz"), exc.get("f1_hz")
        if isinstance(f0, float) and isinstance(f1, float) and f1 == f0:
            errors.append("excitation.f1_hz: must differ from f0_hz (use type: sine for one frequency)")
    return errors


def _plant_checks(cfg: Node, I_max: Any) -> list[str]:
    """The simulated bench's model and sensors against the rest."""
    errors: list[str] = []
    plant = cfg.get("plant")
    if plant is None:
        return errors
    model = plant.get("model")
    if model is not None and model.get("type") == "bouc-wen":
        if plant.get("parameters") is not None:
            errors.append("plant.parameters: a LuGre parameter set, but plant.model.type is bouc-wen "
                          "(its constants are in plant.model.parameters)")
        bw = model.get("parameters")
        if bw is not None and isinstance(I_max, float):
            errors += [f"plant.model.parameters: {e}" for e in bw.check_range(I_max)]
    sensors, sensing = plant.get("sensors"), cfg.get("sensing")
    if (sensors is not None and sensors.get("velocity") is False and sensing is not None
            and sensing.get("velocity") != "observer"):
        errors.append("plant.sensors.velocity: false leaves the controller without a velocity: "
                      "set sensing.velocity: observer")
    return errors


def validate_experiment(data: Any, base_dir: Path, source: str | None = None, *, allow_outside: bool = False,
                        allowed: Sequence[Path] = (), fence: Fence | None = None) -> Node:
    """Validate a parsed experiment; raises ConfigError listing every problem.
    Every file it names is admitted by ``fence``, by default
    ``Fence.around(base_dir, allow_outside, allowed)``: under ``base_dir``'s
    folder (its ``config/`` tree) unless ``allow_outside``, files in
    ``allowed`` (named on the command line) anywhere."""
    if not isinstance(data, dict):
        raise ConfigError([f"config: must be a mapping, got {type(data).__name__}"], source)
    fence = fence if fence is not None else Fence.around(base_dir, allow_outside, allowed)
    # the safety section is required: a daemon must never guess a current limit
    schema = experiment_schema(base_dir, fence)
    schema["safety"] = Section(schema["safety"].fields, optional=False)
    data, errors = apply_calibration(data, base_dir, fence)
    if errors:
        raise ConfigError(errors, source)
    node, errors = validate_fields(schema, data, "")
    if not errors:
        node, errors = device_checks(node, data)
    if not errors:
        errors = _cross_checks(node, base_dir)
        errors += input_kind_errors(data, base_dir, node.backend.get("input"), fence)
    if errors:
        raise ConfigError(errors, source)
    return node


def apply_calibration(data: dict[str, Any], base_dir: Path, fence: Fence | None = None
                      ) -> tuple[dict[str, Any], list[str]]:
    """``calibration: CAL.yaml`` merged into the experiment (mrctl/config/calibration.py)."""
    from mrctl.config.calibration import merge_calibration

    return merge_calibration(data, base_dir, fence)


def load_experiment(path: str | Path, *, allow_outside: bool = False, fence: Fence | None = None) -> Node:
    """Load and validate an experiment YAML file (files it names as
    :func:`validate_experiment`; a key that is not a name called by its line)."""
    p = Path(path)
    data, lines = load_yaml_lines(p)
    with quoting(lines=lines):
        return validate_experiment(data, p.parent, str(p), allow_outside=allow_outside, fence=fence)




def schema_markdown() -> str:
    """The experiment schema as markdown tables (docs/config.md's generated part)."""
    return _markdown(experiment_schema(Path(".")))
