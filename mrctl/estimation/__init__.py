"""Signal estimates the controller feeds to the laws (plain floats, per tick).

- :class:`VelocityLead` (:mod:`.lead`): latency compensation, v predicted
  ``latency.lead_s`` ahead;
- :class:`KinematicObserver` (:mod:`.observer`): velocity from displacement
  (``sensing.velocity: observer``), a steady-state Kalman filter on a
  constant-acceleration model, for DAQs without a velocity channel or with
  a noisy one.
"""

from mrctl.estimation.lead import VelocityLead
from mrctl.estimation.observer import KinematicObserver

__all__ = ["VelocityLead", "KinematicObserver"]
