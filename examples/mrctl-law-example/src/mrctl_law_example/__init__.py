"""Example mrctl law plugin (docs/laws.md): ``force_pi`` and ``sine_force``."""

from mrctl_law_example.laws import ForcePI, SineForce

__all__ = ["ForcePI", "SineForce"]
