"""Run the daemon against hil_sim under scheduled faults, and measure from the logs.

Used by ``bench/faults.py`` (the long form, writes docs/reliability.md) and
``tests/test_faults.py`` (the CI short form). Nothing here asserts: it runs
processes and turns the daemon's run log + sidecar and hil_sim's truth log +
summary into numbers.

What is measured, and from where (never from wall-clock latency):

* **daemon ticks to 0 A**: in the daemon's run log, ``i0`` is the first row
  after the last row whose sample came from before the fault (``t_dev <
  k0·dt``): the first tick that saw a bad (or no) sample of the fault. The
  count is rows (= the daemon's own ticks; skipped deadlines are not ticks)
  from ``i0`` to the first row with ``I == 0``.
* **device ticks to 0 A**: in the truth log, device ticks from the fault's
  first tick ``k0`` to the first tick whose applied driver input ``I_cmd``
  is 0, and whether it was the device watchdog (``WATCHDOG_TRIPPED``) or the
  daemon's setpoint that did it.
* **recovered**: a row with ``I > 0`` whose sample is from after the fault
  (``t_dev ≥ k1·dt``), and how many daemon ticks after the fault that was.
* **ticks lost**: the loop's tick count in the sidecar (``summary.timing.ticks``)
  minus the run log's rows; the ``k`` column's jumps are skipped deadlines,
  reported separately and checked against the sidecar's count.

Modules: :mod:`.scenario` (the Scenario row, the suite's settings, the
experiment file), :mod:`.runner` (the processes), :mod:`.analysis` (the
measurements from the logs), :mod:`.table` (rows of docs/reliability.md,
deviations from the expected outcome, whether a run is usable).
"""

from __future__ import annotations

from hil_sim.testing.fault_suite.analysis import analyse, analyse_process, fault_window, load_logs, tick_accounting
from hil_sim.testing.fault_suite.runner import Daemon, run_scenario, warm_up
from hil_sim.testing.fault_suite.scenario import (
    ENABLED_BIT,
    PINNED_SAFETY,
    RATE_HZ,
    REACTION_TICKS,
    ROBUST_BACKEND,
    ROBUST_LINK,
    ROBUST_SERVE,
    WATCHDOG_TICKS,
    WD_BIT,
    Scenario,
    experiment_config,
)
from hil_sim.testing.fault_suite.table import deviations, table_row, usable

__all__ = [
    "ENABLED_BIT",
    "PINNED_SAFETY",
    "RATE_HZ",
    "REACTION_TICKS",
    "ROBUST_BACKEND",
    "ROBUST_LINK",
    "ROBUST_SERVE",
    "WATCHDOG_TICKS",
    "WD_BIT",
    "Daemon",
    "Scenario",
    "analyse",
    "analyse_process",
    "deviations",
    "experiment_config",
    "fault_window",
    "load_logs",
    "run_scenario",
    "table_row",
    "tick_accounting",
    "usable",
    "warm_up",
]
