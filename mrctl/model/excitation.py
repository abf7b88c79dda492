"""Displacement profiles for the simulated shaker: x(t) in m and v(t) in m/s.

Each profile gives position and velocity analytically (or by interpolation of
a file), so the simulated bench has no differentiation noise of its own.
Pure numerics: a profile from a file gets its samples from the caller
(:class:`Sampled`). ``settle_s`` is the start-up transient excluded from tracking metrics: the
first excitation period, as in the paper's Fig 5 (which starts at 1 s).
"""

from __future__ import annotations

import bisect
import math
from typing import Protocol

import numpy as np


class Excitation(Protocol):
    settle_s: float

    def position(self, t: float) -> float:
        """Displacement (m) at time t (s)."""
        ...

    def velocity(self, t: float) -> float:
        """Velocity (m/s) at time t (s)."""
        ...

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x (m) and v (m/s) at all times t at once, for offline runs."""
        ...


class _PointwiseTrajectory:
    """Fallback ``trajectory`` built from the per-tick methods."""

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([self.position(tk) for tk in t.tolist()]),  # type: ignore[attr-defined]
                np.array([self.velocity(tk) for tk in t.tolist()]))  # type: ignore[attr-defined]


class Sine:
    """x = A·sin(2π f t + φ): the paper's excitation (A = 10 mm, f = 1 Hz)."""

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ph = self.w * t + self.phase
        return self.A * np.sin(ph), self.A * self.w * np.cos(ph)

    def __init__(self, amplitude_m: float, frequency_hz: float, phase_rad: float = 0.0) -> None:
        self.A = float(amplitude_m)
        self.w = 2.0 * math.pi * float(frequency_hz)
        self.phase = float(phase_rad)
        self.settle_s = 1.0 / float(frequency_hz)

    def position(self, t: float) -> float:
        return self.A * math.sin(self.w * t + self.phase)

    def velocity(self, t: float) -> float:
        return self.A * self.w * math.cos(self.w * t + self.phase)


class Chirp(_PointwiseTrajectory):
    """Linear chirp from f0 to f1 (Hz) over ``sweep_s``, constant amplitude.

    x = A·sin(φ(t)), φ = 2π(f0·t + (f1 − f0)·t²/(2·T)); held at f1 after T."""

    def __init__(self, amplitude_m: float, f0_hz: float, f1_hz: float, sweep_s: float) -> None:
        self.A = float(amplitude_m)
        self.f0 = float(f0_hz)
        self.f1 = float(f1_hz)
        self.T = float(sweep_s)
        self.k = (self.f1 - self.f0) / self.T
        self.settle_s = 1.0 / self.f0

    def _phase_and_rate(self, t: float) -> tuple[float, float]:
        if t <= self.T:
            return 2.0 * math.pi * (self.f0 * t + 0.5 * self.k * t * t), 2.0 * math.pi * (self.f0 + self.k * t)
        phase_T = 2.0 * math.pi * (self.f0 * self.T + 0.5 * self.k * self.T * self.T)
        return phase_T + 2.0 * math.pi * self.f1 * (t - self.T), 2.0 * math.pi * self.f1

    def position(self, t: float) -> float:
        return self.A * math.sin(self._phase_and_rate(t)[0])

    def velocity(self, t: float) -> float:
        phase, rate = self._phase_and_rate(t)
        return self.A * rate * math.cos(phase)


class Interpolator:
    """Linear interpolation in a strictly increasing table, O(1) amortised for
    monotone queries (the common case in a loop), held at the ends."""

    __slots__ = ("t", "y", "i")

    def __init__(self, t: list[float], y: list[float]) -> None:
        self.t = t
        self.y = y
        self.i = 0

    def __call__(self, tq: float) -> float:
        t = self.t
        if tq <= t[0]:
            return self.y[0]
        if tq >= t[-1]:
            return self.y[-1]
        i = self.i
        if not (t[i] <= tq < t[i + 1]):
            i = bisect.bisect_right(t, tq) - 1
            self.i = i
        w = (tq - t[i]) / (t[i + 1] - t[i])
        return self.y[i] + w * (self.y[i + 1] - self.y[i])


class Sampled(_PointwiseTrajectory):
    """Displacement from samples ``t, x`` (s, m) and optionally ``v`` (m/s),
    linearly interpolated and held at the ends (an excitation file: loaded by
    :mod:`mrctl.experiment`). Without ``v`` the velocity is the central
    difference of x."""

    def __init__(self, t: list[float], x: list[float], v: list[float] | None = None) -> None:
        if v is None:
            n = len(t)
            v = [0.0] * n
            for i in range(n):
                a, b = max(i - 1, 0), min(i + 1, n - 1)
                v[i] = (x[b] - x[a]) / (t[b] - t[a])
        self._x = Interpolator(t, x)
        self._v = Interpolator(t, v)
        self.settle_s = 0.0
        self.duration_s = t[-1]

    def position(self, t: float) -> float:
        return self._x(t)

    def velocity(self, t: float) -> float:
        return self._v(t)
