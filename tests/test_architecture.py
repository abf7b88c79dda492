"""The import contract (pyproject's [tool.importlinter]) holds, and has teeth.

docs/design.md draws the layers; lint-imports checks every import against
them. The second test plants violations in a copy of the tree and checks
that the contract catches each one, so a contract that silently stopped
checking (a renamed package, a typo in a layer) fails here too.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _lint(cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "importlinter.cli"]
    return subprocess.run([*cmd, "--no-cache"], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_import_contract_is_kept():
    res = _lint(ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 broken" in res.stdout


@pytest.mark.parametrize("victim, line, broken", [
    ("mrctl/model/params.py", "import hil_sim  # noqa: F401", "mrctl never imports hil_sim BROKEN"),
    ("mrctl/model/lugre.py", "import mrctl.daemon.loop  # noqa: F401", "each imports only the ones below it BROKEN"),
    ("mrctl/io/base.py", "import mrctl.laws.base  # noqa: F401", "each imports only the ones below it BROKEN"),
    ("mrctl/offline/simulate.py", "import mrctl.daemon.safety  # noqa: F401",
     "each imports only the ones below it BROKEN"),
    ("hil_sim/bench.py", "import hil_sim.testing.harness  # noqa: F401", "never imports its test harnesses BROKEN"),
])
def test_a_violating_import_breaks_the_contract(tmp_path, victim, line, broken):
    for pkg in ("mrctl", "hil_sim"):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    target = tmp_path / victim
    target.write_text(target.read_text() + "\n" + line + "\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    res = _lint(tmp_path, env)
    assert res.returncode != 0, res.stdout
    assert broken in res.stdout, res.stdout
