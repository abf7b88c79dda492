"""Velocity from displacement: a constant-acceleration Kalman filter.

State s = [x, v, a] (m, m/s, m/s²), driven by white jerk of spectral
density q (m²/s⁵), sampled every dt:

    s_k = F·s_{k−1} + w,   F = [[1, dt, dt²/2], [0, 1, dt], [0, 0, 1]]
    Q   = q·[[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]]

measured: x (std dev ``x_noise_m``, noise and quantisation together) and,
optionally, the DAQ's velocity channel (std dev ``v_noise_mps``). The gains
are the steady-state Kalman gains (the Riccati recursion iterated to its
fixed point at construction, with numpy); the per-tick update is a dozen
plain-float operations:

    predict  x⁻ = x + v·dt + a·dt²/2,  v⁻ = v + a·dt,  a⁻ = a
    update   s = s⁻ + K·(y − H·s⁻)

q sets the bandwidth: larger follows faster motion with less delay and
more noise. Measured delay and noise against the bench's true velocity are
in docs/robust-tracking.md (``bench/observer.py``).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["KinematicObserver", "steady_state_gain"]


def _model(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    F = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    Q = q * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                      [dt**3 / 6, dt**2 / 2, dt]])
    return F, Q


def steady_state_gain(dt: float, q: float, x_noise_m: float, v_noise_mps: float | None = None) -> np.ndarray:
    """The steady-state Kalman gain (3×1, or 3×2 when v is measured too)."""
    F, Q = _model(dt, q)
    if v_noise_mps is None:
        H, R = np.array([[1.0, 0.0, 0.0]]), np.array([[x_noise_m**2]])
    else:
        H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        R = np.diag([x_noise_m**2, v_noise_mps**2])
    P = np.eye(3)
    K = np.zeros((3, H.shape[0]))
    for _ in range(100000):
        Pm = F @ P @ F.T + Q
        K_new = Pm @ H.T @ np.linalg.inv(H @ Pm @ H.T + R)
        P = (np.eye(3) - K_new @ H) @ Pm
        if np.allclose(K_new, K, rtol=1e-12, atol=0.0):
            return K_new
        K = K_new
    return K  # pragma: no cover - converges in a few thousand steps for any sane setting


class KinematicObserver:
    """v̂ from x (and optionally the measured v), once per tick."""

    __slots__ = ("dt", "q", "x_noise_m", "v_noise_mps", "kx", "kxv", "x", "v", "a", "_started", "_gap_gains")

    def __init__(self, dt: float, x_noise_m: float, jerk_psd: float, v_noise_mps: float | None = None) -> None:
        for name, val in (("dt", dt), ("x_noise_m", x_noise_m), ("jerk_psd", jerk_psd)):
            if not (val > 0.0 and math.isfinite(val)):
                raise ValueError(f"{name} must be finite and > 0, got {val!r}")
        if v_noise_mps is not None and not (v_noise_mps > 0.0 and math.isfinite(v_noise_mps)):
            raise ValueError(f"v_noise_mps must be finite and > 0 or None, got {v_noise_mps!r}")
        self.dt, self.q, self.x_noise_m, self.v_noise_mps = dt, jerk_psd, x_noise_m, v_noise_mps
        #: gains for x alone (every tick, or when v is not finite)
        self.kx = tuple(float(g) for g in steady_state_gain(dt, jerk_psd, x_noise_m)[:, 0])
        #: gains for (x, v) when the velocity channel is fused
        self.kxv = None if v_noise_mps is None else tuple(
            tuple(float(g) for g in row) for row in steady_state_gain(dt, jerk_psd, x_noise_m, v_noise_mps))
        #: ticks → (kx, kxv) for updates that many ticks apart: the one-tick gains over a gap of
        #: 4 ticks or more make the update unstable (a loop that keeps skipping deadlines diverged)
        self._gap_gains: dict[int, tuple] = {1: (self.kx, self.kxv)}
        for n in range(2, 9):  # the usual gaps, off the hot path (~1.3 ms each to solve)
            self._gains(n)
        self.reset()

    def reset(self) -> None:
        self.x = self.v = self.a = 0.0
        self._started = False

    def update(self, x: float, v: float = math.nan, ticks: int = 1, h: float = 0.0) -> float:
        """Feed this tick's readings; ``ticks`` since the last update. Returns v̂
        (m/s). A non-finite x only predicts (the supervisor judges the sample).
        ``h`` (s, > 0): the time since the last update when it is not ``ticks``
        whole periods (a device clock's stamps): the prediction spans ``h``, the
        gains are those of ``ticks`` periods (the nearest)."""
        if not self._started:
            if x != x or x in (math.inf, -math.inf):
                return v
            self._started = True
            self.x, self.v, self.a = x, (v if v == v and self.kxv is not None else 0.0), 0.0
            return self.v
        if not h > 0.0:
            h = self.dt * ticks
        gains = self._gap_gains.get(ticks)
        if gains is None:
            gains = self._gains(ticks)
        kx, kxv = gains
        a = self.a
        xp = self.x + (self.v + 0.5 * a * h) * h
        vp = self.v + a * h
        if not -math.inf < x < math.inf:
            self.x, self.v = xp, vp
            return vp
        ex = x - xp
        if kxv is not None and -math.inf < v < math.inf:
            ev = v - vp
            (k00, k01), (k10, k11), (k20, k21) = kxv
            self.x = xp + k00 * ex + k01 * ev
            self.v = vp = vp + k10 * ex + k11 * ev
            self.a = a + k20 * ex + k21 * ev
            return vp
        k0, k1, k2 = kx
        self.x = xp + k0 * ex
        self.v = vp = vp + k1 * ex
        self.a = a + k2 * ex
        return vp

    def _gains(self, ticks: int) -> tuple:
        """The steady-state gains for updates ``ticks`` apart (kept for up to 64 gap lengths)."""
        h = self.dt * ticks
        kx = tuple(float(g) for g in steady_state_gain(h, self.q, self.x_noise_m)[:, 0])
        kxv = None if self.v_noise_mps is None else tuple(
            tuple(float(g) for g in row) for row in steady_state_gain(h, self.q, self.x_noise_m, self.v_noise_mps))
        if len(self._gap_gains) < 64:
            self._gap_gains[ticks] = (kx, kxv)
        return kx, kxv
