"""Loopback HIL helpers for the tests: see :mod:`hil_sim.testing.harness`."""

from hil_sim.testing.harness import ROOT, HilSim, hil_tracking, run_daemon  # noqa: F401
