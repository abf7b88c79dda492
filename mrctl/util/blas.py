"""One BLAS thread per mrctl process, unless the user chose otherwise.

numpy's and scipy's OpenBLAS start a worker thread per core when they are
imported, and after each BLAS call those workers spin for a while on the
cores a 1 kHz loop needs. mrctl's matrices are small (the observer's 3×3,
identification's Jacobians of about twenty columns) and its parallel work is
done by processes (sweeps), so the workers buy nothing and cost the loop
CPU; starting them is also ~60 ms of a ~0.2 s ``mrctl simulate`` start-up on
a 2-vCPU machine (docs/performance.md, "Start-up"). The variables must be set
before numpy is first imported: the command-line entry points call
:func:`limit_blas_threads` before they import anything that imports numpy.
A value already in the environment is kept (``OPENBLAS_NUM_THREADS=2
mrctl identify ...`` uses two).
"""

from __future__ import annotations

import os
import sys
from typing import MutableMapping

__all__ = ["BLAS_THREAD_VARS", "limit_blas_threads"]

#: OpenBLAS (numpy's and scipy's wheels) and MKL (conda's numpy) read these at load
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads(environ: MutableMapping[str, str] | None = None) -> bool:
    """Ask for one BLAS thread where the user set no number; False (and nothing
    changed) when numpy is already loaded, as the setting would not take."""
    if "numpy" in sys.modules:
        return False
    env = os.environ if environ is None else environ
    for var in BLAS_THREAD_VARS:
        env.setdefault(var, "1")
    return True
