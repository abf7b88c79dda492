"""Identification of the LuGre parameters: from mrctl's constant-current
runs, and from a lab's measured records described by a dataset YAML.

The paper's Section III, usable on a lab's own damper: record the damper
under a sine stroke at a staircase of constant currents (one run CSV, e.g.
``config/experiments/identify.yaml``), then

1. split each record into segments of constant commanded current ``I`` and
   drop the first period(s) after every change (settling) — :mod:`.runs`;
2. per current, fit Θ = [σ0, σ1, σ2, Fc, Fs, vs] minimising
   Q = ∫ (F_meas − F_LuGre(v_meas))² dt over whole periods, the candidate
   model (:mod:`.model`, vectorised over time and parameter sets) driven by
   the *measured* velocity after a warm-up so that z's initial condition
   does not bias the fit — :mod:`.fit`;
3. fit the approximating laws (6)–(11) to the per-current values (eq 6 by
   variable projection on Bc, the linear laws by ordinary least squares) —
   :mod:`.laws`;
4. report fit quality (NRMSE against the sensor-noise floor) and how well
   each parameter is determined (Jacobian at the optimum), and write a
   parameters YAML that ``mrctl.config.load_params_file`` accepts —
   :mod:`.result`.

Measured records (``mrctl identify --dataset``, :func:`identify_dataset`):
a dataset description (:mod:`mrctl.config.dataset`) says where the data
is and what it means; :mod:`.records` reads CSV or .mat, :mod:`.prep`
resamples (anti-aliased) and differentiates, then one of two protocols:
constant-input sine tests with pauses, ramps and several levels
(:mod:`.sine`), or broadband and switched-input records by an output-error
fit of the laws, offset, stiffness and input lag (:mod:`.bbmodel`,
:mod:`.broadband`); :mod:`.guards` refuses a set that leaves what the data
support; :mod:`.dataset_result` writes the YAML and the JSON summary with
the held-out scores.

:mod:`.pipeline` strings the run-CSV steps together (:func:`identify` on run records,
:func:`identify_files` on CSV paths, what ``mrctl identify`` calls). Errors
are :mod:`.errors`': ``IdentificationError`` (bad input, exit 2) and
``DependencyMissing`` (exit 2). The figure of the result is
:func:`mrctl.offline.report.make_identification_report` (report imports
identification, never the reverse). See ``docs/identification.md``.

scipy is needed here (``pip install 'mrctl[identify]'``), imported lazily so
that the daemon never needs it.
"""

from __future__ import annotations

from mrctl.offline.identify.dataset_fit import identify_dataset, identify_dataset_file, parse_holdout
from mrctl.offline.identify.dataset_result import DatasetResult, Score, format_dataset_summary, json_path
from mrctl.offline.identify.errors import DependencyMissing, IdentificationError
from mrctl.offline.identify.fit import DEFAULT_METHOD, METHODS, initial_guess
from mrctl.offline.identify.laws import LawFit, fit_laws, theta_from_params
from mrctl.offline.identify.model import THETA_NAMES, THETA_UNITS, lugre_force
from mrctl.offline.identify.pipeline import ProgressFn, identify, identify_files
from mrctl.offline.identify.result import (
    CurrentFit,
    IdentificationResult,
    format_summary,
    result_metadata,
    write_params_yaml,
)
from mrctl.offline.identify.runs import estimate_period, load_identification_run

__all__ = [
    "THETA_NAMES",
    "THETA_UNITS",
    "METHODS",
    "DEFAULT_METHOD",
    "IdentificationError",
    "DependencyMissing",
    "CurrentFit",
    "LawFit",
    "IdentificationResult",
    "ProgressFn",
    "lugre_force",
    "initial_guess",
    "estimate_period",
    "load_identification_run",
    "fit_laws",
    "theta_from_params",
    "identify",
    "identify_files",
    "result_metadata",
    "write_params_yaml",
    "format_summary",
    "DatasetResult",
    "Score",
    "identify_dataset",
    "identify_dataset_file",
    "format_dataset_summary",
    "json_path",
    "parse_holdout",
]
