"""Road profiles for the quarter-car bench: x_r(t) (m) and v_r(t) (m/s).

The same :class:`~mrctl.model.excitation.Excitation` protocol as the
shaker's profiles (on the shaker bench they move the shaker). A sine sweep
is :class:`~mrctl.model.excitation.Chirp`. Pure numerics: numpy at
construction, plain floats per tick.

- :class:`Bump`: one (1 − cos) bump of a given height and length, driven
  over at a speed.
- :class:`ISO8608Road`: a random road of ISO 8608 class A–H: displacement
  PSD G_d(n) = G_d(n0)·(n/n0)^−2, n0 = 0.1 cycle/m, over 0.011–2.83
  cycle/m (the standard's band), as a sum of harmonics with seeded random
  phases, sampled along a profile of ``length_m`` (repeated after it) and
  driven over at ``speed_mps``. ``scale`` scales heights (a lab-scale rig).
"""

from __future__ import annotations

import math

import numpy as np

from mrctl.model.excitation import Interpolator

#: ISO 8608 class → G_d(n0) (m³), the geometric mean of each class
ISO8608_GD0: dict[str, float] = {c: 16e-6 * 4.0 ** i for i, c in enumerate("ABCDEFGH")}
N0 = 0.1  # cycle/m
N_MIN, N_MAX = 0.011, 2.83  # cycle/m, the standard's band


class Bump:
    """x_r = h/2·(1 − cos(2π·V·(t − t0)/L)) while the wheel is on the bump, else 0."""

    def __init__(self, height_m: float, length_m: float, speed_mps: float, at_s: float = 0.5) -> None:
        if not (length_m > 0.0 and speed_mps > 0.0 and at_s >= 0.0):
            raise ValueError("bump: length_m and speed_mps must be > 0, at_s >= 0")
        self.h = float(height_m)
        self.w = 2.0 * math.pi * float(speed_mps) / float(length_m)
        self.t0 = float(at_s)
        self.t1 = self.t0 + float(length_m) / float(speed_mps)
        self.settle_s = 0.0

    def position(self, t: float) -> float:
        if self.t0 < t < self.t1:
            return 0.5 * self.h * (1.0 - math.cos(self.w * (t - self.t0)))
        return 0.0

    def velocity(self, t: float) -> float:
        if self.t0 < t < self.t1:
            return 0.5 * self.h * self.w * math.sin(self.w * (t - self.t0))
        return 0.0

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        on = (t > self.t0) & (t < self.t1)
        ph = self.w * (t - self.t0)
        return (np.where(on, 0.5 * self.h * (1.0 - np.cos(ph)), 0.0),
                np.where(on, 0.5 * self.h * self.w * np.sin(ph), 0.0))


class ISO8608Road:
    """A seeded random road of one ISO 8608 class, driven over at a speed."""

    def __init__(self, road_class: str, speed_mps: float, seed: int = 0, length_m: float = 1000.0,
                 scale: float = 1.0, step_m: float = 0.02) -> None:
        if road_class not in ISO8608_GD0:
            raise ValueError(f"road_class must be one of {', '.join(ISO8608_GD0)}, got {road_class!r}")
        if not (speed_mps > 0.0 and length_m > 0.0 and step_m > 0.0 and scale >= 0.0):
            raise ValueError("speed_mps, length_m and step_m must be > 0, scale >= 0")
        n_pts = 1 << max(4, math.ceil(math.log2(length_m / step_m)))
        ds = length_m / n_pts
        n = np.fft.rfftfreq(n_pts, d=ds)  # cycle/m
        dn = n[1]
        band = (n >= N_MIN) & (n <= N_MAX)
        G = np.zeros_like(n)
        G[band] = ISO8608_GD0[road_class] * (n[band] / N0) ** -2.0
        amp = np.sqrt(2.0 * G * dn) * float(scale)
        phase = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, n.size)
        spec = 0.5 * n_pts * amp * np.exp(1j * phase)
        x = np.fft.irfft(spec, n_pts)
        dxds = np.fft.irfft(spec * (2j * math.pi * n), n_pts)
        s = np.arange(n_pts + 1) * ds  # closed: the profile repeats after length_m
        self.V = float(speed_mps)
        self.L = float(length_m)
        self._x = Interpolator(s.tolist(), np.append(x, x[0]).tolist())
        self._v = Interpolator(s.tolist(), (self.V * np.append(dxds, dxds[0])).tolist())
        self.rms_m = float(np.sqrt(np.mean(x * x)))
        self.settle_s = 1.0

    def _s(self, t: float) -> float:
        return (self.V * t) % self.L

    def position(self, t: float) -> float:
        return self._x(self._s(t))

    def velocity(self, t: float) -> float:
        return self._v(self._s(t))

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.mod(self.V * t, self.L)
        return np.interp(s, self._x.t, self._x.y), np.interp(s, self._v.t, self._v.y)
