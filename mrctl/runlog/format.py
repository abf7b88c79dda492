"""The run log's columns: names, text formats, units.

Shared by what writes a run log (the daemon's recorder) and what reads one
(report, identify), so both agree on what each column is.
"""

from __future__ import annotations

#: Columns of the run log: the core six of ``mrctl simulate`` first.
RUN_COLUMNS = (
    "t", "x", "v", "F_des", "F", "I",
    "k", "seq", "t_dev", "I_applied", "F_true", "late_us", "compute_us", "fault", "link_errors",
)
#: Their units.
RUN_UNITS = dict(zip(RUN_COLUMNS, ("s", "m", "m/s", "N", "N", "A", "tick", "", "s", "A", "N",
                                   "us", "us", "flags", "count")))
#: Their text formats. 9 significant digits are far below any sensor's
#: resolution, and format 5x faster than exact repr (2.9 vs 14 us per row):
#: the writer thread shares the GIL with the loop. Counters and clocks get 10
#: digits, exact for integers below 1e10 and to 1 us for device times.
RUN_FORMATS = {c: "%.9g" for c in RUN_COLUMNS} | {"t": "%.10g", "k": "%.10g", "seq": "%.10g", "t_dev": "%.10g"}
