"""Latency compensation: the velocity predicted ahead (plain floats, per tick).

Latency compensation: on an exchange link the current computed from sample k
reaches the damper one to two ticks later (one request/reply per tick, and the
device applies a setpoint at its own next tick). Over that delay the demanded
force moves by dF/dt·delay: at c_des = 500 N·s/m on the paper's 1 Hz sine,
140 N/s RMS × 1.5 ms ≈ 0.2 N, more than the model error of the law itself.
:class:`VelocityLead` predicts the velocity ``lead_s`` ahead with a smoothed
acceleration, so the demand and the inverse law work on the state the damper
will be in when the current arrives. The acceleration is low-pass filtered
because differencing a noisy velocity amplifies its noise by √2/dt.
"""

from __future__ import annotations

import math


class VelocityLead:
    """v̂(t + lead) = v + â·lead, â a first-order-filtered finite difference."""

    __slots__ = ("lead_s", "dt", "alpha", "v_prev", "a_hat", "_started")

    def __init__(self, lead_s: float, dt: float, smoothing_s: float = 0.005) -> None:
        if lead_s < 0.0 or not math.isfinite(lead_s):
            raise ValueError("lead_s must be finite and >= 0")
        self.lead_s = lead_s
        self.dt = dt
        # discrete first-order low-pass with time constant smoothing_s
        self.alpha = 1.0 if smoothing_s <= 0.0 else 1.0 - math.exp(-dt / smoothing_s)
        self.v_prev = 0.0
        self.a_hat = 0.0
        self._started = False

    def reset(self) -> None:
        self._started = False
        self.a_hat = 0.0

    def update(self, v: float, ticks: int = 1) -> float:
        """Feed this tick's velocity (m/s); ``ticks`` since the last update.
        Returns the predicted velocity (m/s). A non-finite v passes through
        (the safety supervisor deals with it) without corrupting the state."""
        if not -math.inf < v < math.inf:
            return v
        if self._started:
            a = (v - self.v_prev) / (self.dt * ticks)
            self.a_hat += (a - self.a_hat) * self.alpha
        else:
            self._started = True
        self.v_prev = v
        return v + self.a_hat * self.lead_s
