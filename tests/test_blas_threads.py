"""mrctl's entry points ask for one BLAS thread unless the user set a number
(mrctl/util/blas.py): OpenBLAS's workers would spin on the loop's cores."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from mrctl.util.blas import BLAS_THREAD_VARS, limit_blas_threads

ROOT = Path(__file__).resolve().parents[1]

# After mrctl's CLI module is imported, numpy is loaded; then: the variable, the process's threads.
PROBE = ("import os, mrctl.cli, numpy; "
         "print(os.environ.get('OPENBLAS_NUM_THREADS'), len(os.listdir('/proc/self/task')))")


def _probe(**env_over: str) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARS}
    env.update(env_over)
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=60, check=True).stdout.split()
    return out[0], int(out[1])


def test_the_cli_runs_numpy_with_one_blas_thread() -> None:
    value, threads = _probe()
    assert value == "1" and threads == 1


def test_a_users_number_is_kept_and_takes_effect() -> None:
    value, threads = _probe(OPENBLAS_NUM_THREADS="2")
    assert value == "2" and threads >= 2  # OpenBLAS's worker started: the probe can tell


def test_too_late_once_numpy_is_loaded_and_nothing_changed() -> None:
    import numpy  # noqa: F401  (loaded in this process anyway)

    env: dict[str, str] = {}
    assert limit_blas_threads(env) is False and env == {}


def test_sets_every_variable_it_names_but_keeps_a_set_one(monkeypatch) -> None:
    monkeypatch.delitem(sys.modules, "numpy")  # as if numpy were not imported yet
    env = {"MKL_NUM_THREADS": "4"}
    assert limit_blas_threads(env) is True
    assert env == {"OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "4"}
