"""The ``acceptance`` section: what a finished run must meet to count as good data.

Why it exists: a run that spent most of its ticks at 0 A in a fault, or
skipped a fifth of its deadlines, still ends normally; without bounds a
batch script takes it for a good experiment. The defaults are what a lab
would accept from a 1 kHz damper experiment (docs/config.md, README); a run
that breaks one ends with exit 5 and a sidecar ``verdict: degraded`` that
names the bound and the figure (:mod:`mrctl.runlog.acceptance`).
"""

from __future__ import annotations

from typing import Any

from mrctl.util.schema import Num, Section

#: the defaults, also the bounds of a config without the section
DEFAULTS: dict[str, Any] = {
    "max_fault_share": 0.02,
    "max_skipped_share": 0.05,
    "max_gap_s": 0.1,
    "max_zero_stretch_s": 0.1,
    "max_force_nrmse": None,
    "max_latched_s": 0.0,
}


def acceptance_section() -> Section:
    """The schema of ``acceptance`` (every key optional, defaults above)."""
    return Section({
        "max_fault_share": Num(default=DEFAULTS["max_fault_share"], min=0.0, max=1.0,
                               doc="largest share of ticks the safety supervisor may spend in FAULT (0 A)"),
        "max_skipped_share": Num(default=DEFAULTS["max_skipped_share"], min=0.0, max=1.0,
                                 doc="largest share of deadlines the loop may skip (skipped / (ticks + skipped)); "
                                     "mrctl run only"),
        "max_gap_s": Num(default=DEFAULTS["max_gap_s"], min=0.0, min_exclusive=True, max=3600.0,
                         doc="longest gap between two tick starts (s); never tighter than 2 periods at the rate "
                             "run; mrctl run only"),
        "max_zero_stretch_s": Num(default=DEFAULTS["max_zero_stretch_s"], min=0.0, min_exclusive=True, max=3600.0,
                                  doc="longest stretch the supervisor forced 0 A (no usable sample or FAULT) (s)"),
        "max_force_nrmse": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=10.0,
                               doc="largest force NRMSE over the settled window (0.02 = 2 %); null = not judged"),
        "max_latched_s": Num(default=DEFAULTS["max_latched_s"], min=0.0, max=1e7,
                             doc="longest total time latched (an E-stop, the device's watchdog, a long link loss: "
                                 "0 A until mrctl arm) (s); mrctl run only"),
    }, doc="bounds a finished run must meet, else it ends with exit 5 and verdict degraded "
           "(mrctl run and mrctl simulate)")


def bounds(cfg: Any) -> dict[str, Any]:
    """The bounds of a validated experiment as a plain dict (the defaults
    where the section is absent)."""
    sec = cfg.get("acceptance") if cfg is not None else None
    return {k: (sec.get(k, v) if sec is not None else v) for k, v in DEFAULTS.items()}
