"""Loopback HIL helpers for the tests: see :mod:`hil_sim.harness`."""

from hil_sim.harness import ROOT, HilSim, hil_tracking, run_daemon  # noqa: F401
