"""``mrctl calibrate CONFIG --out CAL.yaml``: day one on a bench.

With the damper at rest and 0 A the link is read for ``rest_s``: the mean
of each analog input (in volts, through the channel's own scaling) is its
offset, the spread its noise: the displacement's sets the observer's
``sensing.x_noise_m``, the load cell's is reported. With a current-monitor
channel the current then steps between 0 and ``step_A`` (``steps`` times up
and down, ``step_s`` each) and a first-order lag with a dead time is fitted
to the monitor's reading: τ (the driver + coil, ``parameters.tau_input``)
and the dead time (the link and the DAQ, not the coil). The result is a
YAML file an experiment names with ``calibration: CAL.yaml``
(:mod:`mrctl.config.calibration`).

Host time: each exchange is stamped on the host (a T7 has no sample
clock); the command's time is when its exchange began, the reading's when
its reply came. The dead time absorbs the constant part of that; the
jitter is noise in the fit. The exchanges are paced at ``rate_hz``
(absolute deadlines, a rate the link sustains: the default 200 Hz suits a T7).
"""

from __future__ import annotations

import contextlib
import datetime
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mrctl.daemon import ownership
from mrctl.daemon.interlocks import cause_of, read_until_clean, start_refusal
from mrctl.errors import BadInput, LinkFailure
from mrctl.io.base import LinkError, Status

__all__ = ["CalibrationOptions", "calibrate", "fit_lag", "run_from_args", "write_calibration"]


@dataclass(frozen=True)
class CalibrationOptions:
    rest_s: float = 2.0
    step_A: float | None = None  #: None = half of safety.I_max
    steps: int = 8
    step_s: float = 0.08
    rate_hz: float = 200.0
    #: write the calibration although an input read one constant value at rest (else exit 2)
    accept_dead_channels: bool = False
    #: what the device lock records as the owner (``mrctl ls``, the busy message)
    note: str = "mrctl calibrate"


#: what stops a calibration at once, at 0 A (and refuses one that would start with it)
_STOPS = int(Status.ESTOP | Status.WATCHDOG_TRIPPED | Status.DRIVER_FAULT)


class DeadChannels(BadInput):
    """An analog input read exactly one value at rest: zero noise on a 16-bit
    converter is a disconnected or stuck input, not a calibration (exit 2
    unless ``--accept-dead-channels``)."""


def _step_response(t: np.ndarray, t_cmd: np.ndarray, I_cmd: np.ndarray, tau: float, delay: float) -> np.ndarray:
    """A first-order lag (τ) with dead time (``delay``) of the command history,
    at times ``t``: the sum of each command change's exponential approach."""
    y = np.zeros_like(t)
    prev = 0.0
    for tc, I in zip(t_cmd, I_cmd):
        d = I - prev
        if d != 0.0:
            s = t - (tc + delay)
            y += np.where(s > 0.0, d * (1.0 - np.exp(-np.maximum(s, 0.0) / tau)), 0.0)
        prev = I
    return y


def fit_lag(t: np.ndarray, y: np.ndarray, t_cmd: np.ndarray, I_cmd: np.ndarray,
            min_delay_s: float = -0.005, max_delay_s: float = 0.03) -> tuple[float, float, float]:
    """(τ s, dead time s, robust residual spread A: 1.4826 × median |r|) of a first-order lag with dead time
    fitted to readings ``y`` at ``t`` of the command steps (``t_cmd``,
    ``I_cmd``: the time and value of each command change).

    Each step is fitted on its own (the readings until the next change,
    normalised to a unit step), and the medians are taken: a stall of the
    host or the link spoils one step's fit, not the result. The spread is
    that of the whole record against the medians' model."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    ok = np.isfinite(y)
    t, y = t[ok], y[ok]
    t_cmd, I_cmd = np.asarray(t_cmd, float), np.asarray(I_cmd, float)
    taus, delays = [], []
    prev = 0.0
    for i, (tc, I) in enumerate(zip(t_cmd, I_cmd)):
        end = t_cmd[i + 1] if i + 1 < len(t_cmd) else math.inf
        w = (t >= tc + min_delay_s) & (t < end + min_delay_s)
        if w.sum() >= 6 and I != prev:
            tau_i, d_i, _ = _fit(t[w] - tc, (y[w] - prev) / (I - prev), np.zeros(1), np.ones(1),
                                 min_delay_s, max_delay_s)
            taus.append(tau_i)
            delays.append(d_i)
        prev = I
    if len(taus) >= 3:
        tau, d = float(np.median(taus)), float(np.median(delays))
    else:
        tau, d, _ = _fit(t, y, t_cmd, I_cmd, min_delay_s, max_delay_s)
    r = _step_response(t, t_cmd, I_cmd, tau, d) - y
    return tau, d, float(1.4826 * np.median(np.abs(r))) if len(r) else math.nan


def _fit(t: np.ndarray, y: np.ndarray, t_cmd: np.ndarray, I_cmd: np.ndarray, min_delay_s: float,
         max_delay_s: float) -> tuple[float, float, float]:
    """Least squares (τ, dead time) on a grid of dead times, τ by golden section."""

    def sse(tau: float, d: float) -> float:
        r = _step_response(t, t_cmd, I_cmd, tau, d) - y
        return float(r @ r)

    def best_tau(d: float) -> tuple[float, float]:
        lo, hi = math.log(2e-4), math.log(0.5)
        g = (math.sqrt(5) - 1) / 2
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        fa, fb = sse(math.exp(a), d), sse(math.exp(b), d)
        for _ in range(40):
            if fa < fb:
                hi, b, fb = b, a, fa
                a = hi - g * (hi - lo)
                fa = sse(math.exp(a), d)
            else:
                lo, a, fa = a, b, fb
                b = lo + g * (hi - lo)
                fb = sse(math.exp(b), d)
        tau = math.exp((lo + hi) / 2)
        return tau, sse(tau, d)

    # a dead time below 0: the reading's stamp is later than the sampling it
    # reports (a DAQ that answers with its last conversion), not physics
    grid = np.linspace(min_delay_s, max_delay_s, 36)
    results = [(best_tau(float(d)), float(d)) for d in grid]
    (tau, err), d = min(results, key=lambda r: r[0][1])
    step = grid[1] - grid[0]
    for dd in np.linspace(d - step, d + step, 21):
        (tau2, err2) = best_tau(float(dd))
        if err2 < err:
            tau, err, d = tau2, err2, float(dd)
    return tau, d, math.sqrt(err / max(1, len(y)))


def _paced(link: Any, period_s: float, schedule: list[float],
           phase: str) -> list[tuple[float, float | None, Any, float]]:
    """One tick per period with the currents of ``schedule``: [(t the command
    went out, I or None if it did not get through, sample or None, t the
    sample's request went out)], host monotonic seconds. A split link writes,
    then reads, each stamped just before its request leaves (a late reply
    then does not move the stamp); an exchange link's one request carries
    both (its stamp for both). A sample that says the E-stop opened, the
    device's watchdog tripped or the driver faulted ends it at once
    (:class:`~mrctl.errors.LinkFailure`: the caller's close commands 0 A,
    output disabled, before any further step)."""
    out = []
    t_start = t_next = time.monotonic()
    split = link.split
    for I in schedule:
        now = time.monotonic()
        if t_next > now:
            time.sleep(t_next - now)
        t0 = t1 = time.monotonic()
        s = None
        sent: float | None = None
        try:
            if split:
                link.write(I)
                sent = I
                t1 = time.monotonic()
                s = link.read()
            else:
                s = link.exchange(I)
                sent = I
        except LinkError:
            pass
        if s is not None and int(s.status) & _STOPS:
            raise LinkFailure(f"calibrate: stopped at 0 A: {cause_of(int(s.status))} ({phase}, "
                              f"{t0 - t_start:.2f} s in); nothing written")
        out.append((t0, sent, s, t1))
        t_next += period_s
        if t_next < time.monotonic() - period_s:  # fell behind (a stall): do not burst
            t_next = time.monotonic()
    return out


def calibrate(exp: Any, opts: CalibrationOptions, say: Any = print) -> dict[str, Any]:
    """Measure offsets, noise and the driver lag on ``exp``'s link (a built
    :class:`~mrctl.experiment.Experiment` whose backend is a device preset).
    Returns the calibration mapping (the CAL.yaml content)."""
    cfg = exp.config
    setup = cfg.backend.get("device") if cfg.backend.get("device") is not None else None
    if setup is None or not hasattr(setup, "channels"):
        raise BadInput("calibrate: the experiment's backend has no device preset (backend.device, "
                       "backend.channels: docs/hardware.md); mrctl calibrate measures a DAQ's channels in volts")
    I_max = float(cfg.safety.I_max)
    step_A = opts.step_A if opts.step_A is not None else 0.5 * I_max
    if not 0 < step_A <= I_max:
        raise BadInput(f"--step-A: {step_A:g} A must be > 0 and <= safety.I_max ({I_max:g} A)")
    period = 1.0 / opts.rate_hz
    link = exp.make_link()
    # the same lock as mrctl run: calibrating under a running loop would rewrite the device's set-up
    # and step its current under the loop's feet (refused here, exit 3, before a byte goes out)
    with ownership.own(link, opts.note, lambda msg: say(f"calibrate: {msg}")) or contextlib.nullcontext():
        return _calibrate_open(link, setup, opts, step_A, period, say)


def _calibrate_open(link: Any, setup: Any, opts: CalibrationOptions, step_A: float, period: float,
                    say: Any) -> dict[str, Any]:
    """The measurement itself, on the locked device's link (opened here, closed at the end)."""
    try:
        link.open()
    except LinkError as e:
        raise LinkFailure(f"calibrate: cannot open {link.describe()}: {e}") from None
    # not a control loop: a late reply is still a reading (its stamp is when it was asked for)
    link.timeout_s = max(link.timeout_s, 0.05)
    try:
        # as a run starts: what an earlier run left latched is cleared; an E-stop still open, or a
        # watchdog trip or driver fault that does not clear, refuses before a current step (exit 3)
        why = start_refusal(read_until_clean(link, _STOPS), _STOPS, "the current steps")
        if why:
            raise LinkFailure(f"calibrate: {why}")
        n_rest = max(10, round(opts.rest_s / period))
        say(f"calibrate: {n_rest} samples at rest, 0 A ({opts.rest_s:g} s at {opts.rate_hz:g} Hz)")
        rest = [r for r in _paced(link, period, [0.0] * n_rest, "at rest") if r[2] is not None]
        if len(rest) < n_rest // 2:
            raise LinkFailure(f"calibrate: only {len(rest)} of {n_rest} exchanges answered at rest")
        samples = [r[2] for r in rest]
        field = {"x": "x_m", "v": "v_mps", "F": "F_N", "current_monitor": "current_A"}
        channels: dict[str, Any] = {}
        noise: dict[str, float] = {}
        dead: list[str] = []
        for role, ch in setup.channels.items():
            if ch.kind != "ain":
                continue
            phys = np.array([getattr(s, field[role]) for s in samples], float)
            phys = phys[np.isfinite(phys)]
            if len(phys) < 2:
                continue
            volts = phys / ch.per_V + ch.offset_V
            channels[role] = {"offset_V": float(np.mean(volts)), "noise_V": float(np.std(volts, ddof=1))}
            if np.ptp(phys) == 0.0:
                dead.append(f"{role} ({ch.kind.upper()}{ch.n}) read {volts[0]:.6g} V on all {len(phys)} samples")
            if role == "x":
                noise["x_m"] = max(float(np.std(phys, ddof=1)), 1e-9)
            elif role == "F":
                noise["F_N"] = float(np.std(phys, ddof=1))
        if dead:
            what = "; ".join(dead)
            if not opts.accept_dead_channels:
                raise DeadChannels(f"calibrate: an input read one constant value at rest: {what}. Zero noise on a "
                                   "16-bit converter is a disconnected or stuck input (check its wiring and the "
                                   "sensor's supply); --accept-dead-channels writes the calibration anyway")
            say(f"calibrate: warning: constant at rest (accepted): {what}")
        out: dict[str, Any] = {
            "version": 1,
            "written_by": f"mrctl calibrate on {datetime.date.today().isoformat()}",
            "device": setup.preset.name,
            "channels": channels,
            "noise": noise,
        }
        if "current_monitor" in setup.channels and opts.steps > 0:
            n_step = max(4, round(opts.step_s / period))
            sched: list[float] = []
            for _ in range(opts.steps):
                sched += [step_A] * n_step + [0.0] * n_step
            say(f"calibrate: {opts.steps} current steps 0 <-> {step_A:g} A, {opts.step_s:g} s each")
            rows = _paced(link, period, sched, "during the current steps")
            t_cmd, I_cmd, prev = [], [], 0.0
            for t0, I, _s, _t1 in rows:  # the changes that got through, when they did
                if I is not None and I != prev:
                    t_cmd.append(t0)
                    I_cmd.append(I)
                    prev = I
            t = np.array([t1 for _t0, _I, s, t1 in rows if s is not None])
            y = np.array([s.current_A for _t0, _I, s, _t1 in rows if s is not None])
            # the monitor's own zero, from the rest phase (its offset is calibrated above)
            if len(t) < 0.5 * len(rows):
                raise LinkFailure(f"calibrate: only {len(t)} of {len(rows)} readings answered during the current "
                                  "steps; the lag fit needs them all (a stalled host or link): run it again")
            tau, delay, rms = fit_lag(t, y, np.array(t_cmd), np.array(I_cmd))
            if not (2.5e-4 < tau < 0.45 and -0.0049 < delay < 0.0299 and rms < 0.1 * step_A):
                raise LinkFailure(f"calibrate: the lag fit did not settle (tau {tau * 1e3:.2f} ms, dead time "
                                  f"{delay * 1e3:.2f} ms, residual {rms * 1e3:.1f} mA): a stalled host or link, or no "
                                  "current monitor on that input; run it again")
            out["driver"] = {"tau_s": float(tau), "delay_s": float(delay), "steps": 2 * opts.steps}
            say(f"calibrate: driver+coil lag tau {tau * 1e3:.2f} ms, dead time {delay * 1e3:.2f} ms "
                f"(residual {rms * 1e3:.1f} mA, robust)")
        return out
    finally:
        link.close()


def run_from_args(args: Any, load: Any) -> int:
    """``mrctl calibrate``'s body: check the options, measure, write, print."""
    for name in ("rest_s", "step_s", "rate_hz") + (("step_A",) if args.step_A is not None else ()):
        v = getattr(args, name)
        if not (v > 0 and math.isfinite(v)):
            raise BadInput(f"--{name.replace('_', '-')}: must be > 0, got {v}")
    if args.steps < 0:
        raise BadInput(f"--steps: must be >= 0, got {args.steps}")
    exp = load(args.config)
    if os.path.lexists(args.out) and not args.force:
        raise BadInput(f"{args.out}: exists; refusing to replace it (pass --force)")
    cal = calibrate(exp, CalibrationOptions(rest_s=args.rest_s, step_A=args.step_A, steps=args.steps,
                                            step_s=args.step_s, rate_hz=args.rate_hz,
                                            accept_dead_channels=args.accept_dead_channels,
                                            note=f"mrctl calibrate {Path(args.config).resolve()}"))
    p = write_calibration(args.out, cal, force=args.force)
    for role, ch in cal.get("channels", {}).items():
        print(f"  {role}: offset {ch['offset_V']:.5f} V, noise {ch['noise_V'] * 1e3:.3f} mV rms")
    print(f"wrote {p}")
    print(f"the experiment takes it with  calibration: {calibration_ref(p, Path(args.config))}  (a path relative "
          f"to the experiment's folder, as every file it names)")
    return 0


def calibration_ref(cal: Path, experiment: Path) -> str:
    """What ``experiment`` writes as ``calibration:`` to take ``cal``: a path
    relative to the experiment's folder (where every file it names resolves),
    absolute when they share nothing but the root."""
    here, there = experiment.resolve().parent, cal.resolve()
    try:
        return os.path.relpath(there, here) if os.path.commonpath([here, there]) != "/" else str(there)
    except ValueError:
        return str(there)


def write_calibration(path: str | os.PathLike[str], cal: dict[str, Any], force: bool = False) -> Path:
    """Write ``cal`` as YAML; an existing file only with ``force`` (atomically replaced)."""
    p = Path(path)
    if p.is_dir():
        raise BadInput(f"{p}: is a directory; --out names the calibration YAML file")
    if os.path.lexists(p) and not force:
        raise BadInput(f"{p}: exists; refusing to replace it (pass --force)")
    text = ("# driver lag, offsets and noise measured by mrctl calibrate (docs/hardware.md);\n"
            "# an experiment takes them with  calibration: " + p.name + "\n"
            + yaml.safe_dump(cal, sort_keys=False))
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as exc:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise BadInput(f"{p}: cannot write it: {exc.strerror or exc}") from None
    return p
