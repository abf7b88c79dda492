"""Identification of the LuGre parameters from a lab's measured records
described by a dataset YAML, or from mrctl's own runs described as one.

The paper's Section III, usable on a lab's own damper and on any bench's
records. A *dataset description* (:mod:`mrctl.config.dataset`) says where
the records are and what they mean; mrctl's own run CSVs (a sine stroke
through a staircase of constant currents, e.g.
``config/experiments/identify.yaml``) are described by :mod:`.runs`, the
description mrctl writes itself. Then, for both:

1. :mod:`.records` reads CSV or .mat in SI units; :mod:`.prep` cuts the
   windows, resamples (anti-aliased) and differentiates;
2. one of two protocols: constant-input sine tests with pauses, ramps and
   several levels (:mod:`.sine`: steady cycles per level, Θ per level by
   :mod:`.fit` on the vectorised model of :mod:`.model`), or broadband and
   switched-input records by an output-error fit of the laws, offset,
   stiffness and input lag (:mod:`.bbmodel`, :mod:`.broadband`);
3. the laws (6)–(11) or a table of the per-level Θ (:mod:`.laws`), chosen
   by how each predicts a level it was not fitted to;
4. :mod:`.guards` refuses a set that leaves what the data support;
5. :mod:`.pipeline` scores the set on held-out data and returns one
   :class:`IdentificationResult` (:mod:`.result`: the parameters YAML, the
   JSON summary, the printed table).

Errors are :mod:`.errors`': ``IdentificationError`` (bad input, exit 2) and
``DependencyMissing`` (exit 2). The figure is
:func:`mrctl.offline.identify_figure.make_identification_figure` (it
imports identification, never the reverse). See ``docs/identification.md``.

scipy is needed here (``pip install 'mrctl[identify]'``), imported lazily so
that the daemon never needs it.
"""

from __future__ import annotations

from mrctl.offline.identify.errors import DependencyMissing, IdentificationError
from mrctl.offline.identify.fit import DEFAULT_METHOD, METHODS, initial_guess
from mrctl.offline.identify.laws import LawFit, fit_laws, theta_from_params
from mrctl.offline.identify.model import THETA_NAMES, THETA_UNITS, lugre_force
from mrctl.offline.identify.pipeline import identify_dataset, identify_runs, parse_holdout
from mrctl.offline.identify.result import IdentificationResult, Score, format_summary, json_path, write_result
from mrctl.offline.identify.runs import describe_runs, load_runs

__all__ = [
    "THETA_NAMES",
    "THETA_UNITS",
    "METHODS",
    "DEFAULT_METHOD",
    "IdentificationError",
    "DependencyMissing",
    "LawFit",
    "lugre_force",
    "initial_guess",
    "fit_laws",
    "theta_from_params",
    "describe_runs",
    "load_runs",
    "identify_dataset",
    "identify_runs",
    "IdentificationResult",
    "Score",
    "format_summary",
    "write_result",
    "json_path",
    "parse_holdout",
]
