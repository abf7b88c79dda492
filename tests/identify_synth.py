"""Synthetic measured records for identification tests, made by our own plant.

Real benches add what mrctl's own runs never had: a force offset, an
accumulator's stiffness, an input lag, load-cell noise and quantisation,
displacement not centred, records that start at rest, ramp in and out,
pause, switch the input. These generators put each of those into records
made by :class:`mrctl.model.plant.DamperPlant` with a known parameter set,
and write them the way a lab would (CSV with its own column names and units,
or a MATLAB .mat), so the tests can check what identification recovers.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mrctl.model.params import LuGreParams
from mrctl.model.plant import DamperPlant, Sensors

#: A damper whose laws are physical over 0–2.5 (A or V), with the bench terms.
TRUTH = LuGreParams(F0=20.0, Ac=300.0, Bc=-0.8, sigma0A=4.0e4, sigma0B=2.0e5, sigma1A=200.0, sigma1B=300.0,
                    sigma2A=200.0, sigma2B=100.0, FsA=60.0, FsB=25.0, vsA=-0.006, vsB=0.03,
                    F_offset=40.0, k_x=2000.0, tau_input=0.006)


def telegraph(n: int, dt: float, high: float, rng: np.random.Generator, dwell=(0.010, 0.120),
              glitch: float = 0.0) -> np.ndarray:
    """A random telegraph between 0 and ``high``, dwelling 10–120 ms, with rare negative glitches."""
    u = np.empty(n)
    k, level = 0, 0.0
    while k < n:
        m = int(rng.uniform(*dwell) / dt)
        u[k:k + m] = level
        level = high - level
        k += m
    if glitch:
        idx = rng.choice(n, size=max(1, n // 2000), replace=False)
        u[idx] = -glitch
    return u


def random_motion(t: np.ndarray, rng: np.random.Generator, amp_m: float = 0.004, f_lo: float = 0.5,
                  f_hi: float = 12.0, components: int = 14) -> tuple[np.ndarray, np.ndarray]:
    """Band-limited random displacement (a sum of sines) and its exact velocity."""
    f = rng.uniform(f_lo, f_hi, components)
    ph = rng.uniform(0.0, 2.0 * math.pi, components)
    a = amp_m / np.sqrt(components) / (1.0 + f / f_hi)
    w = 2.0 * math.pi * f
    x = (a[:, None] * np.sin(w[:, None] * t + ph[:, None])).sum(0)
    v = (a[:, None] * w[:, None] * np.cos(w[:, None] * t + ph[:, None])).sum(0)
    return x, v


def run_plant(params: LuGreParams, x: np.ndarray, v: np.ndarray, u: np.ndarray, dt: float, seed: int = 0,
              F_noise_N: float = 0.0, F_lsb_N: float = 0.0, x_lsb_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The plant's measured force and displacement for commanded input u (negative commands read as 0)."""
    plant = DamperPlant(params, dt)
    sens = Sensors(seed, 0.0, 0.0, F_noise_N, x_lsb_m, 0.0, F_lsb_N)
    F = np.empty(v.size)
    xm = np.empty(v.size)
    for k, (vk, uk, xk) in enumerate(zip(v.tolist(), u.tolist(), x.tolist())):
        F[k] = sens.F(plant.tick(vk, uk if uk > 0.0 else 0.0, xk))
        xm[k] = sens.x(xk)
    return F, xm


def broadband_record(seconds: float = 8.0, rate_hz: float = 3000.0, seed: int = 1, params: LuGreParams = TRUTH,
                     high: float = 2.25, F_noise_N: float = 1.0) -> dict[str, np.ndarray]:
    """A switched-input, random-motion record: 3 kHz raw, force noise and quantisation, input glitches."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    t = np.arange(int(seconds * rate_hz)) * dt
    x, v = random_motion(t, rng)
    u = telegraph(t.size, dt, high, rng, glitch=0.3)
    F, xm = run_plant(params, x, v, u, dt, seed, F_noise_N=F_noise_N, F_lsb_N=0.1, x_lsb_m=1e-6)
    return {"t": t, "x": xm, "v": v, "F": F, "u": u}


def sine_levels_record(levels: list[float], rate_hz: float = 500.0, freq_hz: float = 2.0, amp_m: float = 0.008,
                       steady_cycles: int = 6, params: LuGreParams = TRUTH, seed: int = 2, x0_m: float = 0.012,
                       F_noise_N: float = 0.3) -> tuple[dict[str, np.ndarray], list[tuple[float, float, float]]]:
    """One record through several constant levels, each: rest, a 2-cycle ramp in, steady cycles, a
    1-cycle ramp out, a pause. Displacement not centred (x0), quantised; returns the record and the
    [(from_s, to_s, level)] segments."""
    dt = 1.0 / rate_hz
    T = 1.0 / freq_hz
    pieces_x, segs = [], []
    t_now = 0.0
    for lv in levels:
        n_rest = int(0.6 / dt)
        n_ramp, n_steady, n_out = int(2 * T / dt), int(steady_cycles * T / dt), int(T / dt)
        tt = np.arange(n_ramp + n_steady + n_out) * dt
        env = np.concatenate([np.linspace(0.0, 1.0, n_ramp), np.ones(n_steady), np.linspace(1.0, 0.0, n_out)])
        xs = np.concatenate([np.zeros(n_rest), amp_m * env * np.sin(2 * math.pi * freq_hz * tt)])
        segs.append((t_now, t_now + xs.size * dt, lv))
        t_now += xs.size * dt
        pieces_x.append(xs)
    x = np.concatenate(pieces_x + [np.zeros(int(0.3 / dt))])
    t = np.arange(x.size) * dt
    v = np.gradient(x, dt)
    u = np.zeros(x.size)
    for a, b, lv in segs:
        u[(t >= a) & (t < b)] = lv
    F, xm = run_plant(params, x + x0_m, v, u, dt, seed, F_noise_N=F_noise_N, F_lsb_N=0.05, x_lsb_m=5e-6)
    return {"t": t, "x": xm, "v": v, "F": F, "u": u}, segs


def write_csv(path: Path, cols: dict[str, np.ndarray], names: dict[str, str], scale: dict[str, float] | None = None,
              quoted: bool = False, trailing_comma: bool = False) -> Path:
    """Write columns under a lab's own names and units (value / scale)."""
    scale = scale or {}
    keys = list(names)
    head = [f'"{names[k]}"' if quoted else names[k] for k in keys]
    with path.open("w") as fh:
        fh.write(",".join(head) + ("," if trailing_comma else "") + "\n")
        data = np.column_stack([cols[k] / scale.get(k, 1.0) for k in keys])
        for row in data:
            fh.write(",".join(f"{q:.9g}" for q in row) + ("," if trailing_comma else "") + "\n")
    return path
