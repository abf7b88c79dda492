"""The one object shared by the bench's clock thread and the protocol servers.

The clock thread publishes a sample per tick and reads the latest setpoint;
protocol servers (serial, Modbus TCP/RTU) do the opposite, from their own
threads. Both sides only swap references to immutable values under a lock,
so neither ever waits on the other for more than a few instructions.
"""

from __future__ import annotations

import threading
import time

from mrctl.io.base import Sample


class DeviceState:
    """Latest sample out, latest setpoint in; plus link bookkeeping."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sample = Sample(seq=0, t_dev_s=0.0, x_m=0.0, v_mps=0.0, F_N=float("nan"), status=0)
        self._setpoint_A = 0.0
        self._enable = False
        self._setpoint_ns = 0  # monotonic time of the last setpoint (0 = never)
        self.setpoints_received = 0
        self.requests_served = 0

    # -- clock side -------------------------------------------------------
    def publish(self, sample: Sample) -> None:
        with self._lock:
            self._sample = sample

    def setpoint(self) -> tuple[float, bool, int]:
        """(current A, enable, monotonic ns of arrival or 0 if none yet)."""
        with self._lock:
            return self._setpoint_A, self._enable, self._setpoint_ns

    # -- protocol side ----------------------------------------------------
    def latest_sample(self) -> Sample:
        with self._lock:
            self.requests_served += 1
            return self._sample

    def set_setpoint(self, current_A: float, enable: bool = True) -> None:
        with self._lock:
            self._setpoint_A = current_A
            self._enable = enable
            self._setpoint_ns = time.monotonic_ns()
            self.setpoints_received += 1
